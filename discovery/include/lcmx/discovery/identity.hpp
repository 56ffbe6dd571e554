// Host identity (DESIGN.md "Identity").
#pragma once

#include <cstdint>
#include <string>

namespace lcmx::discovery {

// Stable id of this host: a hash of /etc/machine-id (or the boot id when it is missing), of
// this process's network namespace (/proc/thread-self/ns/net inode) and of the /dev/shm it
// sees (device + inode), so two network namespaces on one machine are two hosts, and so are
// two containers sharing a network namespace but not /dev/shm (no shared memory between
// them). The pid namespace is not part of it: containers sharing /dev/shm but not their pid
// namespace are one host (shared memory works; liveness checks compare pids only within one
// pid namespace, see pid_namespace()). LCMX_HOST_ID (decimal or 0x-hex, non-zero) overrides it.
// Throws std::invalid_argument if LCMX_HOST_ID is set but not a valid non-zero number.
std::uint64_t host_id();

// A random 63-bit id for a new participant (never 0).
std::uint64_t random_participant_id();

// Name of this process (/proc/self/comm), for display.
std::string process_name();

// Start time of a process in clock ticks since boot (/proc/<pid>/stat field 22), 0 if gone.
std::uint64_t process_start_time(int pid);

// Inode of this process's pid namespace (/proc/self/ns/pid), 0 if unknown. Two processes'
// pids name the same processes only when this is equal (on one kernel).
std::uint64_t pid_namespace();

}  // namespace lcmx::discovery
