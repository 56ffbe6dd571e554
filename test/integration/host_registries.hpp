// Removes the discovery registry of every emulated host of a test (network namespaces): a
// participant killed by the test's clean-up never leaves its registry, so nobody else removes
// the file from /dev/shm (a host's id comes from its network namespace, which no later test has).
#pragma once

#include <exception>
#include <string>

#include "lcmx/discovery/identity.hpp"
#include "lcmx/discovery/registry.hpp"
#include "lcmx/test/netns.hpp"
#include "lcmx/udpm/config.hpp"

namespace lcmx::it {

// Call after every process of the emulation was killed and reaped, before the namespaces go.
// Best effort, never throws (for destructors). `discovery_url`: the host-local group they used.
inline void remove_host_registries(lcmx::test::Emulation& emu, const std::string& discovery_url) noexcept {
  for (int host = 0; host < emu.hosts(); ++host) {
    try {
      const auto id = emu.run_in(host, [] { return discovery::host_id(); });
      discovery::Registry::remove(id, udpm::parse_url(discovery_url));
    } catch (const std::exception&) {
      // A file left behind costs a few hundred KB of /dev/shm until reboot; nothing else.
    }
  }
}

}  // namespace lcmx::it
