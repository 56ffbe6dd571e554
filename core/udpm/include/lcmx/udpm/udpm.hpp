#pragma once
// lcmx::udpm — LCM's UDP multicast wire format on lcmx's own sockets. Umbrella header.
#include "lcmx/udpm/config.hpp"
#include "lcmx/udpm/error.hpp"
#include "lcmx/udpm/filter.hpp"
#include "lcmx/udpm/group.hpp"
#include "lcmx/udpm/keys.hpp"
#include "lcmx/udpm/source.hpp"
#include "lcmx/udpm/wire.hpp"
