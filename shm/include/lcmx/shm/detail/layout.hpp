// lcmx shared-memory segment layout (one file per generation, "/dev/shm/<base>_g<N>").
// Installed but NOT a stable API: tools and tests may read it; users should not.
//
//   offset 0                   SegmentHeader (4 cache lines, 256 B)
//     line 0  immutable after creation: magic (written last, release), version, geometry,
//             generation, owner pid + start time, carried, first_global_seq
//     line 1  offsets (validated by readers against their own computation),
//             next_generation, writer_closed, sub_high_water
//     line 2  write_seq      (writer-side, alone on its line)
//     line 3  futex_word + waiters (the wake-up line)
//   subscribers_offset        SubscriberEntry[max_subscribers], one cache line each
//   desc_offset               std::atomic<u64>[slot_count] descriptor ring, padded to 64 B
//   slots_offset              Slot[slot_count]: SlotHeader (64 B) + slot_size payload bytes
//   total_size                = slots_offset + slot_count * (64 + slot_size)
//
// Rules: standard layout, fixed-width types, no pointers (offsets only), no hidden padding
// (explicit reserved fields), every atomic lock-free and address-free (process-shared).
// Memory bound per generation: total_size ~= header + slot_count * slot_size.
//
// Sequence numbers ("seq") count messages committed in one generation, starting at 0.
// Carried messages: with WriterOptions::keep > 0, a new generation starts with copies of the
// last `carried` messages of the previous one (seqs 0..carried-1, same sizes and bytes,
// written with write_seq = carried before magic is published). They are not new messages:
// first_global_seq is the global number of this generation's seq 0, i.e. messages committed
// in all earlier generations minus `carried`, so a message keeps its global number in every
// generation it is in. A Reader following from the previous generation starts at `carried`;
// one that had to skip a generation can still count its drops exactly.
//
// Slot states (SlotHeader::seq): kSlotEmpty (never written / aborted loan), kSlotWriting
// (the writer owns it; a writer that dies mid-write leaves it so: never delivered), or the
// seq of the message it holds. Pins (SubscriberEntry::pins): kPinFree or a message seq.
// Descriptor: desc[m % slot_count] = (m << 16) | slot index, written at commit of m.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <type_traits>

namespace lcmx::shm::detail {

inline constexpr std::size_t kCacheLine = 64;
inline constexpr std::uint32_t kMagic = 0x584d434cu;  // "LCMX" little-endian
// 2: SubscriberEntry::next replaces received. 3: liveness by OFD locks (see below), state
// word with an epoch, armed flag, owner pid namespace, final_seq. 4: `carried` (was
// reserved0) and first_global_seq = global number of seq 0 (a version-3 Reader would
// deliver carried messages twice and miscount drops: it is refused as "unsupported version").
// 5: SlotHeader::commit_ns and SegmentHeader::writer_created_ns (Reader::open's `since`).
inline constexpr std::uint32_t kVersion = 5;
inline constexpr int kMaxPins = 4;                     // == Reader::kMaxPins

inline constexpr std::uint64_t kSlotEmpty = ~std::uint64_t{0} - 1;
inline constexpr std::uint64_t kSlotWriting = ~std::uint64_t{0};
inline constexpr std::uint64_t kPinFree = ~std::uint64_t{0};
inline constexpr std::uint64_t kDescEmpty = ~std::uint64_t{0};
inline constexpr unsigned kDescIndexBits = 16;
inline constexpr std::uint64_t kMaxSeq = (std::uint64_t{1} << (64 - kDescIndexBits)) - 2;

// Limits checked by the Writer at creation and by Readers at open (hostile-header guard:
// with these, no layout computation can overflow 64 bits).
inline constexpr std::uint32_t kMaxSlotCount = (1u << kDescIndexBits) - 1;
inline constexpr std::uint32_t kMaxSubscribersLimit = 4096;
inline constexpr std::uint64_t kMaxSlotSize = std::uint64_t{1} << 40;

// SubscriberEntry::state = (epoch << 8) | SubState. The epoch changes on every transition,
// so a compare-exchange that read the word before someone freed and re-claimed the entry
// fails (no ABA). Mutating an entry also requires its OFD lock (below).
enum SubState : std::uint32_t {
  kSubFree = 0,
  kSubActive = 2,
};
constexpr std::uint32_t sub_state(std::uint32_t word) noexcept { return word & 0xffu; }
constexpr std::uint32_t sub_epoch(std::uint32_t word) noexcept { return word >> 8; }
constexpr std::uint32_t sub_word(std::uint32_t epoch, std::uint32_t state) noexcept {
  return (epoch << 8) | state;
}

// Liveness: open file description (OFD) locks on the segment file, which the kernel drops
// when the holder dies, in any pid namespace sharing the file. Byte kWriterLockByte is held
// (write lock) by the Writer for its lifetime; byte kEntryLockBase + i by the Reader owning
// subscriber entry i (and briefly by a process registering into or reclaiming entry i). The
// bytes are lock offsets only (they may lie past the end of the file).
inline constexpr std::uint64_t kWriterLockByte = 0;
inline constexpr std::uint64_t kEntryLockBase = 1;
constexpr std::uint64_t pack_desc(std::uint64_t seq, std::uint32_t slot) noexcept {
  return (seq << kDescIndexBits) | slot;
}
constexpr std::uint64_t desc_seq(std::uint64_t d) noexcept { return d >> kDescIndexBits; }
constexpr std::uint32_t desc_slot(std::uint64_t d) noexcept {
  return static_cast<std::uint32_t>(d & ((std::uint64_t{1} << kDescIndexBits) - 1));
}

struct SegmentHeader {
  // ---- line 0: immutable once magic is published ----
  std::atomic<std::uint32_t> magic;   // kMagic, stored last with release
  std::uint32_t version;              // kVersion
  std::uint32_t slot_count;
  std::uint32_t max_subscribers;
  std::uint64_t slot_size;            // payload bytes per slot, multiple of kCacheLine
  std::uint64_t total_size;           // bytes of the whole segment
  std::uint64_t generation;
  std::int32_t owner_pid;             // in the owner's pid namespace (informational, pidfd)
  // Messages copied from the previous generation into seqs 0..carried-1 (< slot_count;
  // 0 in generation 0). Written before magic (release), so before next_generation too.
  std::uint32_t carried;
  std::uint64_t owner_start_time;     // /proc/<pid>/stat field 22 (clock ticks since boot)
  std::uint64_t first_global_seq;
  // ---- line 1 ----
  std::uint64_t subscribers_offset;
  std::uint64_t desc_offset;
  std::uint64_t slots_offset;
  std::uint64_t slot_stride;          // kSlotHeaderSize + slot_size
  std::atomic<std::uint64_t> next_generation;  // 0 = none; else successor's generation
  std::atomic<std::uint32_t> writer_closed;    // 1 once the Writer was destroyed
  std::atomic<std::uint32_t> sub_high_water;   // entries [0, hw) may be non-free
  std::uint64_t owner_pidns;          // inode of the owner's /proc/self/ns/pid (0 = unknown)
  // Messages the Writer committed in all generations (global count), stored before
  // writer_closed (release) in every generation it still had: a Reader that cannot reach
  // a later generation after the Writer exited counts the rest as drops.
  std::atomic<std::uint64_t> final_seq;
  // ---- line 2: writer-side index ----
  std::atomic<std::uint64_t> write_seq;  // messages committed in this generation
  // CLOCK_MONOTONIC (ns) when the Writer was created (its first generation), the same in
  // every generation. Immutable once magic is published.
  std::uint64_t writer_created_ns;
  std::uint64_t reserved2[6];
  // ---- line 3: wake-up ----
  std::atomic<std::uint32_t> futex_word; // +1 on every commit (and on next_generation/close)
  std::atomic<std::uint32_t> waiters;    // Readers between arm() and disarm()
  std::uint64_t reserved3[7];
};

struct SubscriberEntry {
  std::atomic<std::uint32_t> state;      // sub_word(epoch, SubState)
  std::atomic<std::int32_t> pid;         // informational (liveness is the entry's lock)
  std::atomic<std::uint32_t> armed;      // 1 while counted in SegmentHeader::waiters
  std::uint32_t reserved;
  std::atomic<std::uint64_t> pins[kMaxPins];
  std::atomic<std::uint64_t> drops;      // informational (the Reader keeps its own copy)
  // Seq (this generation) of the next message this Reader will take. A hint for the Writer's
  // slot choice (relaxed; pins and seq checks keep reads safe whatever it says).
  std::atomic<std::uint64_t> next;
};

struct SlotHeader {
  std::atomic<std::uint64_t> seq;        // kSlotEmpty / kSlotWriting / message seq
  std::uint64_t size;                    // committed payload bytes (valid when seq is a seq)
  // CLOCK_MONOTONIC (ns) of the commit, stored (relaxed) before seq's release; a Reader
  // trusts it only between two loads of seq that both read the message's seq.
  std::atomic<std::uint64_t> commit_ns;
  // The Writer's bits for this message (Writer::commit's `flags`), opaque to shm: written and
  // read like `size` (valid when seq is a seq), carried with the message into a new
  // generation. A Writer that sets none says nothing (0).
  std::uint64_t flags;
  std::uint64_t reserved[4];
};

inline constexpr std::size_t kHeaderSize = sizeof(SegmentHeader);
inline constexpr std::size_t kSlotHeaderSize = sizeof(SlotHeader);

static_assert(std::atomic<std::uint64_t>::is_always_lock_free);
static_assert(std::atomic<std::uint32_t>::is_always_lock_free);
static_assert(std::atomic<std::int32_t>::is_always_lock_free);
static_assert(sizeof(std::atomic<std::uint64_t>) == 8 && alignof(std::atomic<std::uint64_t>) == 8);
static_assert(sizeof(std::atomic<std::uint32_t>) == 4);
static_assert(std::is_standard_layout_v<SegmentHeader>);
static_assert(std::is_standard_layout_v<SubscriberEntry>);
static_assert(std::is_standard_layout_v<SlotHeader>);
static_assert(sizeof(SegmentHeader) == 4 * kCacheLine && alignof(SegmentHeader) == 8);
static_assert(offsetof(SegmentHeader, magic) == 0);
static_assert(offsetof(SegmentHeader, version) == 4);
static_assert(offsetof(SegmentHeader, slot_size) == 16);
static_assert(offsetof(SegmentHeader, owner_pid) == 40);
static_assert(offsetof(SegmentHeader, carried) == 44);
static_assert(offsetof(SegmentHeader, first_global_seq) == 56);
static_assert(offsetof(SegmentHeader, subscribers_offset) == 1 * kCacheLine);
static_assert(offsetof(SegmentHeader, next_generation) == 1 * kCacheLine + 32);
static_assert(offsetof(SegmentHeader, owner_pidns) == 1 * kCacheLine + 48);
static_assert(offsetof(SegmentHeader, final_seq) == 1 * kCacheLine + 56);
static_assert(offsetof(SegmentHeader, write_seq) == 2 * kCacheLine);
static_assert(offsetof(SegmentHeader, writer_created_ns) == 2 * kCacheLine + 8);
static_assert(offsetof(SegmentHeader, futex_word) == 3 * kCacheLine);
static_assert(offsetof(SegmentHeader, waiters) == 3 * kCacheLine + 4);
static_assert(sizeof(SubscriberEntry) == kCacheLine);
static_assert(offsetof(SubscriberEntry, armed) == 8);
static_assert(offsetof(SubscriberEntry, pins) == 16);
static_assert(offsetof(SubscriberEntry, next) == 56);
static_assert(sizeof(SlotHeader) == kCacheLine);
static_assert(offsetof(SlotHeader, size) == 8);
static_assert(offsetof(SlotHeader, commit_ns) == 16);
static_assert(offsetof(SlotHeader, flags) == 24);

constexpr std::uint64_t round_up(std::uint64_t v, std::uint64_t a) noexcept {
  return (v + a - 1) / a * a;
}

// Geometry derived from (slot_count, max_subscribers, slot_size); both sides compute it.
struct Geometry {
  std::uint32_t slot_count = 0;
  std::uint32_t max_subscribers = 0;
  std::uint64_t slot_size = 0;
  std::uint64_t subscribers_offset = 0;
  std::uint64_t desc_offset = 0;
  std::uint64_t slots_offset = 0;
  std::uint64_t slot_stride = 0;
  std::uint64_t total_size = 0;
};

// Precondition: arguments within the k*Limit constants above (no overflow then).
constexpr Geometry make_geometry(std::uint32_t slot_count, std::uint32_t max_subscribers,
                                 std::uint64_t slot_size) noexcept {
  Geometry g;
  g.slot_count = slot_count;
  g.max_subscribers = max_subscribers;
  g.slot_size = slot_size;
  g.subscribers_offset = kHeaderSize;
  g.desc_offset = g.subscribers_offset + std::uint64_t{max_subscribers} * sizeof(SubscriberEntry);
  g.slots_offset = round_up(g.desc_offset + std::uint64_t{slot_count} * 8, kCacheLine);
  g.slot_stride = kSlotHeaderSize + slot_size;
  g.total_size = g.slots_offset + std::uint64_t{slot_count} * g.slot_stride;
  return g;
}

}  // namespace lcmx::shm::detail
