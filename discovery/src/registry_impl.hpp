// Private face of registry.cpp: the shared-memory layout of the host registry and the
// operations the Discovery uses on it (docs/discovery.md "Registry").
//
// Trust: the file is mode 0666 (participants of several users share it). It holds no
// pointers; every field a reader uses is bounded and checked (slot indices, lengths, pids),
// and the beacons themselves lie in state files owned by their participants (refused when
// writable by others), decoded by the hostile-input-safe decoder.
#pragma once

#include <sys/types.h>

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "lcmx/discovery/registry.hpp"

namespace lcmx::discovery::reg {

inline constexpr std::size_t kCacheLine = 64;
inline constexpr std::uint32_t kVersion = 1;
inline constexpr std::uint32_t kStateVersion = 1;
inline constexpr std::size_t kTopicWords = 16;  // a 1024-bit filter of a participant's topics

// Slot states (low 8 bits of Slot::state; the epoch above them grows on every reuse).
inline constexpr std::uint64_t kFree = 0, kClaimed = 1, kLive = 2, kDead = 3;
inline constexpr std::uint64_t state_of(std::uint64_t s) { return s & 0xff; }
inline constexpr std::uint64_t epoch_of(std::uint64_t s) { return s >> 8; }
inline constexpr std::uint64_t make_state(std::uint64_t epoch, std::uint64_t st) { return (epoch << 8) | st; }

// Slot::flags bits above the beacon's FLAG_* byte.
inline constexpr std::uint32_t kSlotObserver = 1u << 8;   // reads everything, never listed
inline constexpr std::uint32_t kSlotWildcard = 1u << 9;   // wants every participant (bridge, patterns)

// OFD lock bytes (offsets past the file's end; they lock nothing but themselves).
inline constexpr off_t kLockInit = (off_t{1} << 40) - 2;     // held while creating / removing
inline constexpr off_t kLockSpeaker = (off_t{1} << 40) - 1;  // the host-local group's speaker
inline constexpr off_t kLockDeputy = (off_t{1} << 40) - 3;   // its deputy (takes over at once)
// Every open Registry holds a read lock on this byte; the file is removed only by whoever gets
// a write lock on it (no one else has it open): the last one to close, or a sweep.
inline constexpr off_t kLockUsers = (off_t{1} << 40) - 4;
inline constexpr off_t kLockSlots = off_t{1} << 40;          // + slot index: its participant lives
inline constexpr off_t kLockVehicle = off_t{1} << 41;        // + (group hash & 2^40-1): vehicle speaker
inline constexpr off_t kLockVehicleActing = (off_t{1} << 41) + (off_t{1} << 40);  // + the same: acting for a silent one

// Offset 0 of the file. Written once by the creator (under kLockInit), `version` last.
struct alignas(kCacheLine) Header {
  std::atomic<std::uint32_t> version;  // 0 while initialising; kVersion when ready (release)
  std::uint32_t header_size;           // sizeof(Header)
  std::uint32_t slot_count;
  std::uint32_t slot_size;             // sizeof(Slot)
  std::uint64_t host_id;
  std::uint64_t group_hash;
  std::uint64_t registry_id;           // random per file: a restarted host has a new one
  std::uint64_t reserved0[3];
  // -- line 1: written by every participant
  std::atomic<std::uint32_t> changes;   // futex word: +1 after every change of a slot (release)
  // Futex word: +1 after a vehicle speaker wrote a vehicle table with new content (release;
  // docs/discovery.md "Vehicle table"). One for every vehicle group of the registry.
  std::atomic<std::uint32_t> vehicle_changes;
  std::atomic<std::uint32_t> high_water;  // slots [0, high_water) may be in use
  std::uint32_t reserved2;
  std::atomic<std::int64_t> observed_until_ns;  // CLOCK_MONOTONIC: an observer wants fresh statistics
  std::atomic<std::int64_t> speaker;            // participant id of the host-local speaker (display)
  std::uint64_t reserved3[4];
  // -- line 2: the change log's head (entries: the ring after the slots)
  std::atomic<std::uint64_t> log_head;  // next change log position (fetch_add by writers)
  std::uint32_t log_size;               // entries in the ring (a power of two)
  std::uint32_t reserved5;
  std::uint64_t reserved4[14];
};
static_assert(std::is_standard_layout_v<Header>);
static_assert(sizeof(Header) == 256 && alignof(Header) == kCacheLine);
static_assert(offsetof(Header, log_head) == 128);

// Change log entry: (position << 20) | slot index. A reader that finds another position in an
// entry than the one it expects (not yet written, or overwritten: it fell behind) rescans.
inline constexpr std::uint32_t kLogSize = 4096;
// Wake-up words by topic (after the change log): a change of a participant bumps the words of
// the filter bits its topics set (before and after the change); a reader sleeps on the words
// of its own topics' first bits, so changes that cannot concern it do not wake it. Readers that
// want everything (speakers, observers, bridges) sleep on Header::changes.
inline constexpr std::uint32_t kBuckets = 1024;
inline constexpr std::uint64_t log_entry(std::uint64_t pos, std::uint32_t slot) { return (pos << 20) | slot; }
static_assert(offsetof(Header, version) == 0 && offsetof(Header, changes) == 64);
static_assert(std::atomic<std::uint32_t>::is_always_lock_free && std::atomic<std::uint64_t>::is_always_lock_free);

// One participant. Claimed by CAS on `state` (kFree -> kClaimed), filled, then kLive (release).
// Its content (revision, flags, topics, and the state file) changes under the seqlock `seq`:
// odd while the owner writes; a reader that saw the same even value before and after its
// reads has a consistent view. `heartbeat_ns` alone is written outside it, every period.
struct alignas(kCacheLine) Slot {
  std::atomic<std::uint64_t> state;        // make_state(epoch, kFree/kClaimed/kLive/kDead)
  std::atomic<std::int64_t> participant_id;
  std::atomic<std::uint64_t> revision;     // +1 on a structural change (not on statistics)
  std::atomic<std::uint64_t> seq;          // seqlock over revision, flags, topics, state file
  std::atomic<std::uint64_t> stats_seq;    // +1 when only the statistics were rewritten
  std::atomic<std::int64_t> heartbeat_ns;  // CLOCK_MONOTONIC, every period
  std::atomic<std::int32_t> pid;
  std::atomic<std::int32_t> lease_ms;
  std::atomic<std::int64_t> start_time;    // /proc/<pid>/stat field 22
  // -- line 1
  std::atomic<std::uint64_t> pid_namespace;
  std::atomic<std::uint32_t> uid;          // owner of its state file
  std::atomic<std::uint32_t> flags;        // beacon FLAG_* | kSlot*
  std::atomic<std::uint64_t> vehicle_group;  // hash of its vehicle group, 0: none
  std::atomic<std::uint32_t> period_ms;      // its heartbeat period
  std::uint32_t reserved0;
  std::uint64_t reserved[4];
  // -- lines 2-3
  std::atomic<std::uint64_t> topics[kTopicWords];  // filter: 3 bits per topic name
};
static_assert(std::is_standard_layout_v<Slot>);
static_assert(sizeof(Slot) == 256 && alignof(Slot) == kCacheLine);
static_assert(offsetof(Slot, state) == 0 && offsetof(Slot, pid_namespace) == 64 && offsetof(Slot, period_ms) == 88 &&
              offsetof(Slot, topics) == 128);

// A state file: this header, then the host-scope beacon, then the vehicle-scope beacon.
struct StateHeader {
  std::uint32_t version;       // kStateVersion
  std::uint32_t host_len;
  std::uint32_t vehicle_len;
  std::uint32_t reserved0;
  std::uint64_t host_struct;     // hash of the host beacon without its statistics
  std::uint64_t vehicle_struct;  // same for the vehicle beacon (0: none)
  std::uint64_t checksum;        // FNV-1a of the bytes after this header
  std::uint64_t revision;        // the slot's revision it was written with
  std::uint64_t reserved1[2];
};
static_assert(std::is_standard_layout_v<StateHeader> && sizeof(StateHeader) == 64);
static_assert(offsetof(StateHeader, version) == 0 && offsetof(StateHeader, checksum) == 32);

inline constexpr std::uint32_t kMaxStateBytes = 64u << 20;

// The 3 bits a topic name sets in a TopicFilter (computed once per own topic).
struct TopicBits {
  std::uint16_t bit[3];
};
TopicBits topic_bits(const std::string& topic);

struct TopicFilter {
  std::uint64_t w[kTopicWords]{};
  void add(const std::string& topic);
  bool may_hold(const std::string& topic) const;
  bool intersects_names(const std::vector<std::string>& topics) const;
};

std::uint64_t fnv1a(std::span<const std::byte> bytes, std::uint64_t h = 1469598103934665603ull);
std::uint64_t group_hash(const udpm::GroupConfig& g);
std::int64_t now_ns();  // CLOCK_MONOTONIC

// What a reader gets from a state file.
struct State {
  std::vector<std::byte> host, vehicle;
  std::uint64_t host_struct = 0, vehicle_struct = 0, revision = 0;
};

}  // namespace lcmx::discovery::reg

namespace lcmx::discovery {

struct Registry::Impl {
  RegistryOptions options;
  std::string path;
  int fd = -1;
  std::size_t size = 0;
  reg::Header* header = nullptr;
  reg::Slot* slots = nullptr;
  std::atomic<std::uint64_t>* log = nullptr;  // kLogSize entries after the slots
  std::atomic<std::uint32_t>* buckets = nullptr;  // kBuckets words after the log
  std::uint32_t slot_count = 0;
  bool created = false;  // open() initialised the file (no lcmx process of the host had it)

  // This process's membership (one slot for its host and vehicle Discovery).
  std::mutex mutex;
  int own = -1;                 // slot index, -1: none yet
  std::int64_t own_id = 0;
  int state_fd = -1;
  std::string state_path;
  std::vector<std::byte> host_bytes, vehicle_bytes;
  std::uint64_t host_struct = 0, vehicle_struct = 0;
  int members = 0;              // Discovery objects using the slot

  ~Impl();
  reg::Slot& slot(std::uint32_t i) const { return slots[i]; }
  std::string state_path_for(std::int64_t participant) const;

  // Claims a slot for `participant` (idempotent). Throws std::runtime_error when the table is full.
  void join(std::int64_t participant, std::int32_t lease_ms, std::int32_t period_ms);
  // Rewrites the state file with this scope's beacon. `structural`: its hash without
  // statistics; a change of it (either scope) bumps the revision and wakes everyone.
  // Returns true if the revision was bumped.
  bool publish(bool vehicle, std::vector<std::byte> bytes, std::uint64_t structural,
               const reg::TopicFilter* topics, std::uint32_t flags, std::uint64_t vehicle_group);
  void heartbeat();
  // A member stops using the slot; the last one frees it, removes the state file, and the
  // registry file too when no slot is left in use.
  void leave();

  // Readers. nullopt: torn, gone, not trusted or malformed (the caller retries next pass).
  std::optional<reg::State> read_state(std::uint32_t i, std::int64_t participant, std::uint64_t seq) const;
  // True when the slot's owner holds its liveness lock (or the lock cannot be tested).
  bool owner_alive(std::uint32_t i) const;
  bool try_lock(off_t byte);  // OFD write lock, non-blocking
  void unlock(off_t byte);
  // Logs slot i's change and wakes its waiters (futex): those of Header::changes, and those of
  // the topic words of slot i's filter and of `also` (its filter before the change).
  void bump_changes(std::uint32_t i, const std::uint64_t* also = nullptr);
  // Removes the file (and its state files) if no one else has it open. Returns true if removed.
  bool remove_if_unused();
  // The speaker frees a slot whose owner is dead: state file, shm segments, slot.
  void reclaim(std::uint32_t i, std::uint64_t seen_state);

  // The vehicle table of a vehicle group (vehicle_table.hpp, docs/discovery.md "Vehicle table"):
  // a file beside the registry, `<path>_pv<group hash hex>` (removed with the state files).
  // write_table replaces it whole (a temporary file renamed over it: a reader sees the old one or
  // the new one), mode 0644, then bumps Header::vehicle_changes and wakes its waiters; false if it
  // could not be written (a full /dev/shm: the error is the caller's to report; errno says why).
  // patch_table_time writes `written_ns` into the current file in place (false: none, or failed).
  std::string table_path_for(std::uint64_t vehicle_group) const;
  bool write_table(std::uint64_t vehicle_group, std::span<const std::byte> bytes) const;
  bool patch_table_time(std::uint64_t vehicle_group, std::int64_t written_ns) const;
};

}  // namespace lcmx::discovery
