// The host registry (docs/discovery.md "Registry"): where the participants of one host and one
// host-local group meet, in shared memory, without a daemon. One file
// /dev/shm/lcmxreg_<host id hex>_<group hash hex> holds a table of slots (one per participant:
// identity, heartbeat, revision, a topic filter); each participant's beacons (host and vehicle
// scope) lie in a state file of its own beside it. Whoever comes first creates the file.
//
// A process opens it once (Registry::open) and hands it to both of its Discovery objects
// (discovery::Options::registry): they share one slot. Threads: every member function is
// thread-safe. Errors: open() throws std::runtime_error with a clear message when the file
// cannot be created, opened, sized (a full /dev/shm), mapped, or is not a registry.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "lcmx/udpm/udpm.hpp"

namespace lcmx::discovery {

struct RegistryOptions {
  std::uint64_t host_id = 0;         // 0: discovery::host_id()
  udpm::GroupConfig group;           // the host-local group: one registry per address:port
  // Slots of a registry this call creates (an existing one keeps its size): participants of
  // one host at most. Bounded to [2, 65536].
  std::uint32_t slots = 1024;
  std::string directory = "/dev/shm";  // tests may use another tmpfs directory
};

class Registry {
 public:
  static std::shared_ptr<Registry> open(const RegistryOptions& options);
  ~Registry();
  Registry(const Registry&) = delete;
  Registry& operator=(const Registry&) = delete;

  const std::string& path() const;        // the registry file
  std::uint64_t host_id() const;
  std::uint32_t slots() const;
  // Whether open() initialised the file: no lcmx process of this host and group held it, so
  // whatever lcmx left in /dev/shm before is nobody's (RuntimeImpl then reclaims orphans; while
  // the registry lives its speaker reclaims each dead participant's segments by name).
  bool created() const;
  // Participants holding a slot now (live, or claimed and not yet reclaimed).
  std::uint32_t occupied() const;

  // The file name a registry of (host_id, group) has, for tests and `lcmx` diagnostics.
  static std::string path_for(std::uint64_t host_id, const udpm::GroupConfig& group,
                              const std::string& directory = "/dev/shm");
  // Removes the registry of (host id, group) and the state files beside it whose owners are
  // gone. For tests' clean-up; never needed by users (the last participant to leave removes it).
  static void remove(std::uint64_t host_id, const udpm::GroupConfig& group,
                     const std::string& directory = "/dev/shm");

  struct Impl;
  Impl& impl() { return *impl_; }

 private:
  explicit Registry(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace lcmx::discovery
