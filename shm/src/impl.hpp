// Private declarations shared by the lcmx_shm sources.
#pragma once

#include <sys/types.h>

#include <boost/interprocess/mapped_region.hpp>

#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <string>
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
bool process_alive(std::int32_t pid, std::uint64_t start_time);

// ---- segment files (segment_file.cpp) ----

// One mapped generation. The geometry is a private copy validated at open: code never
// re-reads slot_count/slot_size/offsets from shared memory.
struct Segment {
  std::string name;
  boost::interprocess::mapped_region region;
  Geometry geo;
  std::uint64_t generation = 0;
  std::uint64_t first_global_seq = 0;
  SegmentHeader* hdr = nullptr;

  std::byte* base() const noexcept { return static_cast<std::byte*>(region.get_address()); }
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
  std::int32_t owner_pid = 0;
  std::uint64_t owner_start_time = 0;
};
std::optional<HeaderInfo> validate_header(const void* mem, std::uint64_t file_size,
                                          std::string* why);

// Creates a new segment (O_EXCL). If a file of that name exists with a valid header whose
// owner is dead, removes it and retries once. Throws Error(system) otherwise.
std::unique_ptr<Segment> create_segment(const std::string& name, const Geometry& geo,
                                        std::uint64_t generation, std::uint64_t first_global_seq,
                                        std::int32_t pid, std::uint64_t start_time);

// Opens and validates an existing segment read-write. Throws Error(not_found, corrupt, system).
std::unique_ptr<Segment> open_segment(const std::string& name);

// Reads only the header of `name` (read-only mapping). nullopt + *why if missing/invalid.
std::optional<HeaderInfo> peek_segment(const std::string& name, std::string* why);

bool unlink_segment(const std::string& name) noexcept;

// "<base>_g<N>" -> (base, N); nullopt if the name has no generation suffix.
std::optional<std::pair<std::string, std::uint64_t>> split_generation(const std::string& name);
std::string generation_name(const std::string& base, std::uint64_t gen);
// Highest N such that /dev/shm/<base>_g<N> exists.
std::optional<std::uint64_t> find_highest_generation(const std::string& base);
// Names in /dev/shm starting with prefix.
std::vector<std::string> list_shm(const std::string& prefix);

// ---- subscriber table (segment_file.cpp) ----

// Clears entries whose process is dead (CAS on state). Returns how many were reclaimed.
std::size_t reclaim_dead_subscribers(const Segment& seg);
// Claims a free entry (reclaiming dead ones first). Throws Error(no_subscriber_slot).
std::uint32_t register_subscriber(const Segment& seg, std::int32_t pid, std::uint64_t start);
void deregister_subscriber(const Segment& seg, std::uint32_t entry) noexcept;

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
  std::int32_t pid = 0;
  std::uint64_t start_time = 0;

  ~WriterImpl();
  void grow(std::size_t size);
  bool pinned(std::uint64_t seq) const noexcept;
  std::uint32_t acquire_slot();
  bool readers_caught_up() const noexcept;
  void abort_loan(std::uint32_t slot) noexcept;
  std::uint64_t commit(std::uint32_t slot, std::size_t size);
  void bump_and_wake(const Segment& s) noexcept;
  void release_old_generations(bool reclaim_dead) noexcept;
};

// A generation as seen by one Reader: mapping + our subscriber entry there. Destroyed when
// neither the Reader nor any ReadSample uses it; then deregisters.
struct GenView {
  std::unique_ptr<Segment> seg;
  std::uint32_t entry = 0;
  std::int32_t pid = 0;
  ~GenView();
  SubscriberEntry& sub() const noexcept { return seg->sub(entry); }
};

struct ReaderImpl {
  std::string base;
  std::shared_ptr<GenView> cur;
  std::uint64_t next = 0;  // next seq to read in cur
  std::uint64_t drops = 0;
  std::uint64_t received = 0;
  bool dead_end = false;   // next_generation set but no newer generation can be opened
  std::shared_ptr<GenView> pin_gen[kMaxPins];
  std::shared_ptr<GenView> armed;
  std::int32_t pid = 0;
  std::uint64_t start_time = 0;

  ~ReaderImpl();
  bool try_follow();
  void unpin(int pin) noexcept;
  void publish_counters() noexcept;
};

}  // namespace lcmx::shm::detail
