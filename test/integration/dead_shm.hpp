// remove_dead_shm_of(): cleanup after tests whose publishers run as pid 1 of a pid namespace.
#pragma once

#include <sys/mman.h>
#include <sys/types.h>

#include <string>

#include "lcmx/shm/liveness.hpp"
#include "support.hpp"

namespace lcmx::it {

// Removes only the segments of `pid` whose Writer is gone (shm::owner_alive). For pids that
// are not unique to one test: pid 1 of a pid namespace is pid 1 in every other test's
// containers too, and ctest -j2 runs tests side by side, so removing every "pid 1" segment
// pulled a live publisher's segments from under another test (its subscriber could then not
// watch the Writer and saw its death only after the lease).
inline void remove_dead_shm_of(pid_t pid) {
  for (const auto& n : shm_segments_of(pid))
    if (!lcmx::shm::owner_alive(n)) ::shm_unlink(("/" + n).c_str());
}

}  // namespace lcmx::it
