// Private declarations shared by the lcmx_shm sources.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "lcmx/shm/detail/layout.hpp"
#include "lcmx/shm/segment.hpp"

namespace lcmx::shm::detail {

// ---- processes (process.cpp) ----

// /proc/<pid>/stat field 22 (start time in clock ticks since boot); nullopt if unreadable.
std::optional<std::uint64_t> process_start_time(pid_t pid);
std::uint64_t self_start_time();  // 0 if /proc is unavailable
// Alive: kill(pid, 0) succeeds or fails with EPERM, the process is not a zombie, and its
// start time equals `start_time` (guards pid reuse). Unknown (stat unreadable) => alive.
// Meaningful only for a pid of our own pid namespace.
bool process_alive(std::int32_t pid, std::uint64_t start_time);
std::uint64_t self_pidns() noexcept;  // inode of /proc/self/ns/pid, 0 if unknown

// ---- SIGBUS guard (guard.cpp) ----
// Registers a mapping; returns a slot (or -1: table full, unguarded). Thread-safe.
int guard_register(void* base, std::size_t len) noexcept;
void guard_unregister(int slot) noexcept;
// True once a SIGBUS hit the mapping (file truncated under it): its content is now zeros.
bool guard_faulted(int slot) noexcept;

// ---- OFD locks (locks.cpp) ----
// A file descriptor of our own open file description of a segment file, for OFD locks.
// Closed on destruction by the process that opened it; a fork()ed child closes its inherited
// copies at fork (pthread_atfork), so a child never keeps its parent's locks alive.
class LockFd {
 public:
  LockFd() = default;
  explicit LockFd(int fd);
  LockFd(LockFd&& o) noexcept;
  LockFd& operator=(LockFd&& o) noexcept;
  ~LockFd();
  int get() const noexcept { return fd_; }

 private:
  void reset() noexcept;
  int fd_ = -1;
  pid_t pid_ = 0;
};
bool try_lock(int fd, std::uint64_t byte) noexcept;   // F_OFD_SETLK write lock; true if ours
void unlock(int fd, std::uint64_t byte) noexcept;
// True if another open file description holds a lock on `byte` (F_OFD_GETLK). Errors: true.
bool locked_by_other(int fd, std::uint64_t byte) noexcept;

// A mapping of a segment file, guarded against truncation; unmapped on destruction.
struct Mapping {
  void* addr = nullptr;
  std::size_t len = 0;
  int guard = -1;
  Mapping() = default;
  Mapping(void* a, std::size_t n) : addr(a), len(n), guard(guard_register(a, n)) {}
  Mapping(Mapping&& o) noexcept
      : addr(std::exchange(o.addr, nullptr)), len(o.len), guard(std::exchange(o.guard, -1)) {}
  Mapping& operator=(Mapping&& o) noexcept;
  Mapping(const Mapping&) = delete;
  Mapping& operator=(const Mapping&) = delete;
  ~Mapping();
  bool faulted() const noexcept { return guard_faulted(guard); }
};

// ---- segment files (segment_file.cpp) ----

// One mapped generation. The geometry is a private copy validated at open: code never
// re-reads slot_count/slot_size/offsets from shared memory.
struct Segment {
  std::string name;
  Mapping map;
  LockFd lock;  // our own open file description of the file (OFD locks)
  Geometry geo;
  std::uint64_t generation = 0;
  std::uint64_t first_global_seq = 0;  // global number of seq 0 (see layout.hpp)
  std::uint32_t carried = 0;           // validated copy of SegmentHeader::carried
  std::uint64_t writer_created_ns = 0; // copy of SegmentHeader::writer_created_ns
  SegmentHeader* hdr = nullptr;

  std::byte* base() const noexcept { return static_cast<std::byte*>(map.addr); }
  bool faulted() const noexcept { return map.faulted(); }
  SubscriberEntry& sub(std::uint32_t i) const noexcept {
    return reinterpret_cast<SubscriberEntry*>(base() + geo.subscribers_offset)[i];
  }
  std::atomic<std::uint64_t>& desc(std::uint32_t i) const noexcept {
    return reinterpret_cast<std::atomic<std::uint64_t>*>(base() + geo.desc_offset)[i];
  }
  SlotHeader& slot(std::uint32_t i) const noexcept {
    return *reinterpret_cast<SlotHeader*>(base() + geo.slots_offset + i * geo.slot_stride);
  }
  std::byte* payload(std::uint32_t i) const noexcept {
    return base() + geo.slots_offset + i * geo.slot_stride + kSlotHeaderSize;
  }
};

// Validates a mapped header against the file size; returns the geometry or an error text.
// Reads each shared field once.
struct HeaderInfo {
  Geometry geo;
  std::uint64_t generation = 0;
  std::uint64_t first_global_seq = 0;
  std::uint32_t carried = 0;
  std::int32_t owner_pid = 0;
  std::uint64_t owner_start_time = 0;
  std::uint64_t owner_pidns = 0;
  std::uint64_t writer_created_ns = 0;
};
std::optional<HeaderInfo> validate_header(const void* mem, std::uint64_t file_size,
                                          std::string* why);

// Creates a new segment (O_EXCL), takes its Writer lock, reserves its memory with
// posix_fallocate (a full tmpfs is Error(system), never a later SIGBUS). If a file of that
// name exists with a valid header and no Writer lock, removes it and retries once. Throws
// Error(system) otherwise.
// `fill` (optional) runs on the initialised segment before its magic is published: it may
// commit messages 0..c-1 into slots 0..c-1 (slot seq, size, desc; not write_seq) and returns
// c (< slot_count), which create_segment stores as `carried` and write_seq, so nobody can
// see the generation without its carried messages. first_global_seq is of seq 0.
std::unique_ptr<Segment> create_segment(
    const std::string& name, const Geometry& geo, std::uint64_t generation,
    std::uint64_t first_global_seq, std::int32_t pid, std::uint64_t start_time, std::uint64_t created_ns,
    const std::function<std::uint32_t(Segment&)>& fill = {});

// Opens and validates an existing segment read-write: a regular file owned by our euid or
// by root, not writable by others (Error(untrusted) otherwise), large enough for its
// layout. Throws Error(not_found, corrupt, untrusted, system).
std::unique_ptr<Segment> open_segment(const std::string& name);

// Reads only the header of `name` (read-only mapping). nullopt + *why if missing/invalid.
std::optional<HeaderInfo> peek_segment(const std::string& name, std::string* why);

// True if the Writer lock of `name` is held (its Writer lives). Missing file: false.
bool writer_lock_held(const std::string& name) noexcept;

// Unlinks the generations of `base` that no live Reader can still need, for a base whose
// Writer is gone (closed or dead). With `oldest` the oldest generation a live Reader is
// registered in (only for a cleanly closed Writer; `caller_gen` is the caller's own,
// counted even if its name is already gone): generations below `oldest` go; from `oldest`
// on they stay while there is a newer one to follow to (keeping the oldest Reader's own name
// shows later callers, e.g. reclaim_orphans, that it is there); else all go.
// Returns how many it removed.
std::size_t release_unneeded_generations(
    const std::string& base, std::uint64_t caller_gen = ~std::uint64_t{0}) noexcept;
bool has_live_subscriber(const Segment& seg) noexcept;

bool unlink_segment(const std::string& name) noexcept;

// "<base>_g<N>" -> (base, N); nullopt if the name has no generation suffix.
std::optional<std::pair<std::string, std::uint64_t>> split_generation(const std::string& name);
std::string generation_name(const std::string& base, std::uint64_t gen);
// Highest N such that /dev/shm/<base>_g<N> exists.
std::optional<std::uint64_t> find_highest_generation(const std::string& base);
// Names in /dev/shm starting with prefix.
std::vector<std::string> list_shm(const std::string& prefix);

// ---- subscriber table (segment_file.cpp) ----

// Clears entries whose owner is dead (entry lock free), whatever state a killed process left
// them in; subtracts a dead armed Reader from the waiter count. Returns how many.
std::size_t reclaim_dead_subscribers(const Segment& seg) noexcept;
// True if entry i is owned by a live Reader (non-free and its lock held by someone else).
bool subscriber_alive(const Segment& seg, std::uint32_t i) noexcept;
// Claims an entry (free, or reclaiming a dead one) and keeps its lock on `lock`, which must
// be an open file description of this segment's file of its own. Returns the entry index and
// the state word (epoch) it stored. Throws Error(no_subscriber_slot).
std::pair<std::uint32_t, std::uint32_t> register_subscriber(const Segment& seg, int lock,
                                                            std::int32_t pid);
void deregister_subscriber(const Segment& seg, std::uint32_t entry, int lock) noexcept;

// ---- Writer / Reader state ----

struct WriterImpl {
  std::string base;
  WriterOptions opt;
  std::unique_ptr<Segment> seg;
  std::vector<std::uint64_t> slot_seq;  // writer's private copy of each slot's seq
  // Earlier generations still named in /dev/shm, oldest first: generation k keeps its name
  // while a Reader is registered in a generation <= k (it follows by name).
  std::deque<std::unique_ptr<Segment>> old_gens;
  std::uint64_t commits = 0;
  std::uint32_t next_slot = 0;
  std::uint64_t write_seq = 0;          // == seg->hdr->write_seq (only we store it)
  bool loan_out = false;
  std::uint32_t loan_slot = 0;
  bool loan_scratch = false;            // the loan is the drop buffer (every slot pinned)
  bool hot_slot = true;                 // Writer::set_hot_slot
  std::vector<std::byte> scratch;       // drop buffer, allocated on first need
  std::uint64_t dropped = 0;            // messages dropped because every slot was pinned
  std::chrono::steady_clock::time_point next_reclaim{};
  std::int32_t pid = 0;
  std::uint64_t start_time = 0;
  std::uint64_t pidns = 0;
  std::uint64_t created_ns = 0;         // CLOCK_MONOTONIC at Writer::create

  ~WriterImpl();
  void grow(std::size_t size, bool same_size = false);
  // Copies the last min(opt.keep, intact) messages of `from` (the current generation) into
  // slots 0..c-1 of `to`; returns c. Only a contiguous tail whose slots still hold it.
  std::uint32_t carry(const Segment& from, Segment& to) const;
  void maybe_reclaim() noexcept;
  bool pinned(std::uint64_t seq) const noexcept;
  std::optional<std::uint32_t> acquire_slot();
  bool readers_caught_up() const noexcept;
  void abort_loan(std::uint32_t slot) noexcept;
  std::uint64_t commit(std::uint32_t slot, std::size_t size, std::uint64_t flags);
  void bump_and_wake(const Segment& s) noexcept;
  void release_old_generations(bool reclaim_dead) noexcept;
};

// A generation as seen by one Reader: mapping + our subscriber entry there. Destroyed when
// neither the Reader nor any ReadSample uses it; then deregisters.
struct GenView {
  std::unique_ptr<Segment> seg;
  std::uint32_t entry = 0;
  std::uint32_t word = 0;  // our entry's state word (epoch): changed => entry taken from us
  std::int32_t pid = 0;
  ~GenView();
  bool still_ours() const noexcept {
    return sub().state.load(std::memory_order_acquire) == word && !seg->faulted();
  }
  SubscriberEntry& sub() const noexcept { return seg->sub(entry); }
};

// Pins of one Reader held by DetachedSamples (bit i: pin i). Set by the Reader's owner
// thread (detach), cleared by whichever thread destroys the DetachedSample, after it stored
// kPinFree into the pin word (fetch_and release; take()'s acquire load pairs with it).
// Shared: it outlives the Reader while DetachedSamples do.
struct PinLedger {
  std::atomic<std::uint32_t> detached{0};
};

struct ReaderImpl {
  std::string base;
  std::shared_ptr<GenView> cur;
  std::uint64_t next = 0;  // next seq to read in cur
  std::uint64_t drops = 0;
  std::uint64_t received = 0;
  bool dead_end = false;   // next_generation set but no newer generation can be opened
  // After a failed follow: no retry (and has_data() false) before this time.
  std::chrono::steady_clock::time_point retry_at{};
  std::chrono::milliseconds backoff{0};
  std::shared_ptr<GenView> pin_gen[kMaxPins];
  std::shared_ptr<GenView> armed;
  std::shared_ptr<PinLedger> ledger = std::make_shared<PinLedger>();
  std::uint64_t detach_refused = 0;
  std::int32_t pid = 0;
  std::uint64_t start_time = 0;

  ~ReaderImpl();
  bool try_follow();
  bool follow_fault();  // current generation truncated under us: move to the newest one
  void unpin(int pin) noexcept;
  void publish_counters() noexcept;
};

}  // namespace lcmx::shm::detail
