// Services moved to lcmx::services, a layer above this library: lcmx/services/service.hpp.
// This forwarding header keeps `#include "lcmx/core/service.hpp"` working for programs that
// link lcmx::core (which brings lcmx::services); lcmx's own code includes the new one.
#pragma once

#include "lcmx/services/service.hpp"
