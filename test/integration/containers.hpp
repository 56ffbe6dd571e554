// Containers emulated with unshare(1), for the integration tests (LCMX_UNSHARE: its path).
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "support.hpp"

namespace lcmx::it {

// argv running `peer` with `peer_args` in new namespaces: `flags` for unshare, and with
// `private_shm` a tmpfs of its own on /dev/shm (a container without --ipc=host). The peer
// ends by itself after 60 s (--timeout-ms).
inline std::vector<std::string> in_container(std::vector<std::string> flags, bool private_shm,
                                             const std::string& peer, std::vector<std::string> peer_args) {
  std::vector<std::string> argv = {LCMX_UNSHARE};
  for (auto& f : flags) argv.push_back(std::move(f));
  argv.push_back("--");
  argv.push_back("/bin/sh");
  argv.push_back("-c");
  argv.push_back(private_shm ? "mount -t tmpfs -o size=16m lcmxit /dev/shm && exec \"$@\"" : "exec \"$@\"");
  argv.push_back("sh");
  argv.push_back(peer);
  for (auto& a : peer_args) argv.push_back(std::move(a));
  argv.push_back("--timeout-ms");
  argv.push_back("60000");
  return argv;
}

// Whether this machine lets the test create mount and pid namespaces (and mount a tmpfs).
inline bool can_unshare() {
  Child c({LCMX_UNSHARE, "--mount", "--pid", "--fork", "--mount-proc", "--propagation", "private", "/bin/sh",
           "-c", "mount -t tmpfs lcmxit /dev/shm"},
          {}, true);
  return c.wait(std::chrono::milliseconds(10000)) == 0;
}

}  // namespace lcmx::it
