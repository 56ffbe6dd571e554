// core internals, for the code of core/src that works across components (node.cpp,
// publisher.cpp, service.cpp, action.cpp): every component's private header. The map and the
// lock order: runtime_impl.hpp and docs/ARCHITECTURE.md.
#pragma once

#include "node_impl.hpp"
#include "pairs.hpp"
#include "publisher_impl.hpp"
#include "runtime_impl.hpp"
#include "subscriber_state.hpp"
