// Liveness of segment Writers and fast death notification, for the runtime (core).
//
// Liveness is not judged from pids: a Writer holds an OFD lock (fcntl F_OFD_SETLK) on each
// of its segment files for as long as it lives; the kernel drops it when the process dies,
// and any process that can open the file tests it (F_OFD_GETLK), whatever its pid namespace
// (containers sharing /dev/shm but not the pid namespace) and immune to pid reuse.
//
// Threads: owner_alive and shm_domain_id are thread-safe. An OwnerWatch is used by one
// thread at a time. Errors: Error(system) from the OwnerWatch constructor; never otherwise.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "lcmx/shm/segment.hpp"

namespace lcmx::shm {

// True if the Writer of `segment_name` (a generation's name, "<base>_g<N>") still runs and
// holds the file. False if the file is gone or its Writer exited or died. One open + fcntl.
bool owner_alive(const std::string& segment_name) noexcept;

// Identity of the shared-memory domain /dev/shm (its device and inode mixed; 0 if it cannot
// be stat'ed). discovery::host_id() includes it (one notion of "same /dev/shm"). Two processes of one host can exchange segments only if their
// domains are equal (containers with a private /dev/shm have another one): put it in the
// host identity / beacons and choose another path when it differs.
std::uint64_t shm_domain_id() noexcept;

// Watches the Writers of segments and says quickly (typically well under 100 ms) when one
// dies, without polling /proc. Poll fd() for POLLIN (e.g. in the executor's epoll set or a
// poll() with the other descriptors), then call take_dead().
// Mechanism per watched Writer: a pidfd (readable when the process exits) when the Writer
// is in our pid namespace (header's pid-namespace inode equals ours, start time matches);
// otherwise inotify on the file (IN_CLOSE_WRITE: the kernel closes a dying Writer's file)
// followed by the lock test, re-tested every 5 ms for 200 ms after an event (the kernel
// sends the close event just before it drops the lock).
class OwnerWatch {
 public:
  OwnerWatch();
  ~OwnerWatch();
  OwnerWatch(const OwnerWatch&) = delete;
  OwnerWatch& operator=(const OwnerWatch&) = delete;

  int fd() const noexcept;  // readable when take_dead() may have something

  // Starts watching the Writer of `segment_name`; returns a key for take_dead/unwatch.
  // A Writer already dead is reported by the next take_dead(). Throws Error(not_found) if
  // the segment does not exist, Error(system) if no watch can be set up.
  std::uint64_t watch(const std::string& segment_name);
  void unwatch(std::uint64_t key) noexcept;

  // Non-blocking: the keys whose Writer died (or closed) since the last call; each is
  // reported once and no longer watched.
  std::vector<std::uint64_t> take_dead();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace lcmx::shm
