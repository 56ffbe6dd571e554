// Host identity (DESIGN.md "Identity").
#pragma once

#include <cstdint>
#include <string>

namespace lcmx::discovery {

// Stable id of this host: a hash of /etc/machine-id (or the boot id when it is missing) and
// of this process's network namespace (/proc/thread-self/ns/net inode), so two namespaces on one
// machine are two hosts. LCMX_HOST_ID (decimal or 0x-hex, non-zero) overrides it.
// Throws std::invalid_argument if LCMX_HOST_ID is set but not a valid non-zero number.
std::uint64_t host_id();

// A random 63-bit id for a new participant (never 0).
std::uint64_t random_participant_id();

// Name of this process (/proc/self/comm), for display.
std::string process_name();

// Start time of a process in clock ticks since boot (/proc/<pid>/stat field 22), 0 if gone.
std::uint64_t process_start_time(int pid);

}  // namespace lcmx::discovery
