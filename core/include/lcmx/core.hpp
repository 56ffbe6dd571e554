// lcmx public API: include this one header (and link lcmx::core). It brings the runtime
// (lcmx::runtime, lcmx/core/*.hpp: Runtime, Node, publishers, subscribers) and the services
// built on it (lcmx::services, lcmx/services/*.hpp: services and actions).
#pragma once

#include "lcmx/core/error.hpp"
#include "lcmx/core/node.hpp"
#include "lcmx/core/options.hpp"
#include "lcmx/core/publisher.hpp"
#include "lcmx/core/runtime.hpp"
#include "lcmx/core/stats.hpp"
#include "lcmx/core/subscriber.hpp"
#include "lcmx/services/action.hpp"
#include "lcmx/services/service.hpp"
