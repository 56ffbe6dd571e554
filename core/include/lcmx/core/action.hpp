// Actions moved to lcmx::services, a layer above this library: lcmx/services/action.hpp.
// This forwarding header keeps `#include "lcmx/core/action.hpp"` working for programs that
// link lcmx::core (which brings lcmx::services); lcmx's own code includes the new one.
#pragma once

#include "lcmx/services/action.hpp"
