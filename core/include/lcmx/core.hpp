// lcmx public API: include this one header.
#pragma once

#include "lcmx/core/action.hpp"
#include "lcmx/core/error.hpp"
#include "lcmx/core/node.hpp"
#include "lcmx/core/options.hpp"
#include "lcmx/core/publisher.hpp"
#include "lcmx/core/runtime.hpp"
#include "lcmx/core/stats.hpp"
#include "lcmx/core/subscriber.hpp"
