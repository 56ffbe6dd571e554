// DeathWatch: fast death notice for shm publishers in another pid namespace (a container
// sharing /dev/shm: no pidfd for them, discovery leaves them to their lease). Pairs asks it to
// watch the writer of each segment it opens from such a participant (shm::OwnerWatch: inotify
// + the writer's OFD lock); the receive thread polls fd() and calls take_dead().
//
// Threads: every member is thread-safe; its lock is a leaf (taken under Pairs::mu).
// Errors: none thrown; a watch that cannot be set up leaves the publisher to its lease (logged
// at debug level); no OwnerWatch at all (constructor failure) is logged once.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "lcmx/shm/liveness.hpp"

namespace lcmx::detail {

class DeathWatch {
 public:
  explicit DeathWatch(std::uint64_t own_pid_namespace);

  // The fd to poll (POLLIN: take_dead() may have something), -1 if there is no OwnerWatch.
  int fd() const;
  // Watches the writer of `segment`, publisher (participant, endpoint) of pid namespace
  // `pid_namespace`: only when that is another pid namespace than ours (ours: discovery's pidfd
  // says it at once), once per publisher, at most 4096.
  void watch(std::uint64_t participant, std::uint64_t endpoint, std::int64_t pid_namespace,
             const std::string& segment);
  void forget(std::uint64_t participant);

  struct Dead {
    std::uint64_t participant = 0, endpoint = 0;
    std::string segment;
    bool grew = false;  // the writer only moved to a newer generation: watch that one instead
  };
  // The writers that died (or closed) since the last call. Non-blocking.
  std::vector<Dead> take_dead();

 private:
  const std::uint64_t own_pid_namespace_;
  mutable std::mutex mu_;
  std::unique_ptr<shm::OwnerWatch> watch_;                             // null: lease only
  std::map<std::uint64_t, Dead> keys_;                                 // watch key -> publisher
  std::set<std::pair<std::uint64_t, std::uint64_t>> watched_;          // (participant, endpoint)
};

}  // namespace lcmx::detail
