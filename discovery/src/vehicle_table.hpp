// The vehicle table (docs/discovery.md "Vehicle table"): what a host's vehicle speaker holds of
// the other hosts, in a file beside the registry, `<registry>_pv<vehicle group hash hex>`, for the
// host's other vehicle participants ("followers"). A follower reads it instead of the vehicle
// group's discovery, so only one process per host (the speaker) wakes for, decodes and answers
// what the group carries; the others read, when the table changed, only the records of the
// hosts that changed, and of those only the records whose topics concern them.
//
// Layout (fixed-width, no pointers, every count and offset bounded by the file's size):
//   Header (64 B) | Host[host_count] (64 B each) | Record[record_count] (160 B each) | bytes
// Each Host names its records, a contiguous run of Record entries; each Record names its bytes
// (encode_beacon() of the record as its host's speaker sent it: the vehicle view).
//
// Writing: the speaker builds the whole file and renames it over the old one (Registry::Impl::
// write_table): a reader sees the old table or the new one, never a mix, and keeps reading the
// one it opened. `written_ns` alone is patched in place every period (patch_table_time): its
// age tells a follower that the speaker still writes (a torn read of it only delays that
// judgement by a read). After each new table the speaker bumps the registry header's
// `vehicle_changes` futex word: followers sleep on it.
//
// Reading (File): opened without following a link, a regular file writable by nobody but its
// owner, at most kMaxStateBytes; read with pread (a file truncated under a reader gives short
// reads, never a SIGBUS). The caller checks that the owner is the uid of the writer's registry
// slot and that the writer is a live participant of the registry (Discovery::Impl::trusted).
// Threads: a File belongs to one thread; encode() is a pure function.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "registry_impl.hpp"

namespace lcmx::discovery::table {

inline constexpr std::uint32_t kVersion = 2;  // 1 was the vehicle cache (an LCM vehicle_cache_t)
inline constexpr std::uint32_t kComplete = 1;  // Header::flags: its writer had heard the whole vehicle
inline constexpr std::uint32_t kMaxHosts = 4096;

struct Header {
  std::uint32_t version;       // kVersion (offset 0)
  std::uint32_t header_size;   // sizeof(Header)
  std::uint32_t host_count;
  std::uint32_t record_count;
  std::uint64_t host_id;       // the host this table is of
  std::int64_t writer;         // participant id of the speaker that wrote it
  std::int64_t written_ns;     // CLOCK_MONOTONIC: when written or last patched (every period)
  std::uint64_t generation;    // +1 per table with other content (a follower's "seen it")
  std::uint32_t flags;         // kComplete
  std::uint32_t reserved0;
  std::uint64_t reserved1;
};
static_assert(std::is_standard_layout_v<Header> && sizeof(Header) == 64);
static_assert(offsetof(Header, version) == 0 && offsetof(Header, written_ns) == 32);

struct Host {
  std::int64_t host_id;
  std::int64_t registry_id;   // of its last heartbeat: a restarted host has a new one
  std::int64_t speaker;
  std::int64_t digest;        // its heartbeat's digest of the (participant, revision) set
  std::uint32_t address;      // IPv4, network order: the address its speakers send from
  std::int32_t lease_ms;
  std::uint32_t first_record;  // its records: [first_record, first_record + record_count)
  std::uint32_t record_count;
  // The digest of the (participant, revision) set its records make here (may differ from
  // `digest` while the speaker still lacks some): a follower re-reads a host's records only
  // when this or registry_id changed.
  std::int64_t listed_digest;
  std::uint64_t reserved;
};
static_assert(std::is_standard_layout_v<Host> && sizeof(Host) == 64);

struct Record {
  std::int64_t participant_id;
  std::int64_t revision;
  std::uint64_t offset;        // of its bytes, from the start of the file
  std::uint32_t length;
  std::uint32_t flags;         // reg::kSlotWildcard: a bridge, DDS gateway or channel-pattern reader
  std::uint64_t topics[reg::kTopicWords];  // reg::TopicFilter of its endpoints' topics
};
static_assert(std::is_standard_layout_v<Record> && sizeof(Record) == 160);

// What a speaker writes: per host its heartbeat's state and its records as sent.
struct Content {
  struct Entry {
    std::int64_t participant_id = 0, revision = 0;
    std::uint32_t flags = 0;
    reg::TopicFilter topics;
    std::vector<std::byte> bytes;  // encode_beacon()
  };
  struct HostEntry {
    Host host{};  // first_record and record_count are filled by encode()
    std::vector<Entry> records;
  };
  std::int64_t writer = 0;
  bool complete = false;
  std::vector<HostEntry> hosts;
};

// The file's bytes (written_ns = now). Records larger than kMaxStateBytes in all are left out
// (never the case in practice: a host's records are bounded by max_table_bytes).
std::vector<std::byte> encode(const Content& content, std::uint64_t host_id, std::uint64_t generation);

// A table file open for reading (see the header comment for what open() checks).
class File {
 public:
  // nullopt: no file, or one refused (then *refused, if given, is set: not a regular file,
  // writable by others, too small or large, not a table of this version, or inconsistent).
  static std::optional<File> open(const std::string& path, bool* refused = nullptr);
  File(File&&) noexcept;
  File& operator=(File&&) noexcept;
  File(const File&) = delete;
  File& operator=(const File&) = delete;
  ~File();

  const Header& header() const { return header_; }
  std::uint32_t owner() const { return owner_; }
  const std::vector<Host>& hosts() const { return hosts_; }
  // The Record entries of `host` (one of hosts()), checked against the file; nullopt if they
  // lie outside it or name bytes outside it.
  std::optional<std::vector<Record>> records(const Host& host) const;
  // The bytes of `record` (one of records()), nullopt on a short read.
  std::optional<std::vector<std::byte>> bytes(const Record& record) const;

 private:
  File() = default;
  bool read(void* out, std::size_t size, std::uint64_t offset) const;
  int fd_ = -1;
  std::uint64_t size_ = 0;
  std::uint32_t owner_ = 0;
  Header header_{};
  std::vector<Host> hosts_;
};

}  // namespace lcmx::discovery::table
