// Process-wide registry of live namespaces and child process groups, readable from a dying
// process without locks or allocation (see emergency_teardown()).
#pragma once

#include <sys/types.h>

namespace lcmx::test::detail {

// Returns false when the registry is full (the entry is then simply not registered).
bool register_netns(const char* path) noexcept;  // "/run/netns/<name>"
void unregister_netns(const char* path) noexcept;
bool register_child(pid_t pgid) noexcept;
void unregister_child(pid_t pgid) noexcept;

}  // namespace lcmx::test::detail
