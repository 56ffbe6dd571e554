// lcmx shared-memory transport: one Writer (publisher) per segment, any number of Readers
// (subscribers, in any process of the host) per segment.
//
// Contract summary (details on each member):
//  - The Writer never blocks on Readers. A slow, stopped or killed Reader loses the oldest
//    messages (counted per Reader as drops); it never sees a torn message.
//  - A Writer that dies mid-write never delivers that message.
//  - A message larger than the current slot size makes the Writer move to a new, larger
//    segment generation ("<base>_g<N>"); Readers follow by themselves.
//  - Memory is bounded: slot_count * slot size per generation, slot size <= max_message_size.
//  - Notification: one futex word per segment; one FUTEX_WAKE wakes every waiting Reader.
//
// Errors: constructors/factories and loan() throw lcmx::shm::Error; "nothing new" is an empty
// std::optional, never an exception.
// Threads: a Writer and each Reader are used by one thread at a time (move between threads ok).
#pragma once

#include <atomic>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>

namespace lcmx::shm {

// Every segment name lcmx creates starts with this, e.g. "lcmx_3f2a..._1234n4026531836_7_g0".
inline constexpr const char* kPrefix = "lcmx_";

// This process's part of segment names: "<pid>n<pid-namespace inode, hex>" (a random
// component instead if /proc is unavailable). Unique among processes sharing /dev/shm even
// across pid namespaces (containers), where bare pids collide.
std::string process_tag();

enum class Errc {
  too_large,         // message exceeds WriterOptions::max_message_size
  not_found,         // no such segment (publisher gone)
  corrupt,           // bad magic/version/layout
  no_subscriber_slot,// segment's subscriber table is full of live readers
  invalid_argument,  // bad options or name
  system,            // an OS call failed (message says which, with errno text)
  untrusted,         // segment file owned by another user (not root) or writable by others
};

class Error : public std::runtime_error {
 public:
  Error(Errc code, const std::string& what) : std::runtime_error(what), code_(code) {}
  Errc code() const noexcept { return code_; }

 private:
  Errc code_;
};

struct WriterOptions {
  std::uint32_t slot_count = 8;            // ring depth (>= 2): messages a Reader may lag by
  std::uint32_t max_subscribers = 32;      // Readers registered at once (live ones)
  std::size_t initial_slot_size = 4096;    // first generation's slot payload size
  std::size_t max_message_size = 64u << 20;// bound: loan(size) above it throws too_large
  // Keep last N: the last `keep` committed messages stay readable for late Readers
  // (Reader::open's backlog), also across a generation change: a new generation (growth or
  // a truncated file) starts with copies of the old one's last min(keep, committed) messages
  // whose slots are intact (fewer, possibly 0, if slots were lost: truncation, every slot
  // pinned), same bytes and global sequence numbers; they are not new messages (published()
  // and Readers that followed see each message once). Must be < slot_count, else
  // Writer::create throws Error(invalid_argument). Best effort while Readers pin slots (a
  // pinned slot is skipped, so a newer one is overwritten). 0: nothing kept on purpose (the
  // Writer may then reuse the newest message's slot once every Reader has taken it).
  std::uint32_t keep = 0;
  // The caller vouches that no other live Writer uses this base name (lcmx's runtime: its
  // names hold the pid, the pid namespace and an endpoint id, and a process has one runtime).
  // Writer::create then skips its scan of /dev/shm for a live Writer at a later generation of
  // the base: one readdir of every segment of the host per Writer made a host's start
  // quadratic (issue 33: 500 processes of 10 publishers, 5,000 segments). Creating generation
  // 0 still refuses a name whose owner is alive.
  bool unique_base = false;
};

namespace detail {
struct WriterImpl;
struct ReaderImpl;
struct GenView;
struct PinLedger;
}  // namespace detail

class Writer;
class DetachedSample;

// A slot reserved by Writer::loan(): write up to capacity() bytes at data(), then
// Writer::commit(). Destroyed without commit: the slot goes back, nothing is published.
// Must not outlive its Writer.
class WriteLoan {
 public:
  WriteLoan(WriteLoan&&) noexcept;
  WriteLoan& operator=(WriteLoan&&) noexcept;
  WriteLoan(const WriteLoan&) = delete;
  WriteLoan& operator=(const WriteLoan&) = delete;
  ~WriteLoan();

  std::byte* data() const noexcept { return data_; }
  std::size_t capacity() const noexcept { return capacity_; }

 private:
  friend class Writer;
  WriteLoan(detail::WriterImpl* w, std::uint32_t slot, std::byte* data, std::size_t cap)
      : writer_(w), slot_(slot), data_(data), capacity_(cap) {}
  detail::WriterImpl* writer_ = nullptr;
  std::uint32_t slot_ = 0;
  std::byte* data_ = nullptr;
  std::size_t capacity_ = 0;
};

class Writer {
 public:
  // Creates generation 0 of segment "<base_name>_g0". base_name must start with kPrefix and
  // be a valid POSIX shm name without '/'. Throws Error (invalid_argument: bad name or
  // options, e.g. keep >= slot_count; system).
  // Records this process's pid and start time in the header so orphans can be reclaimed.
  // A same-name segment left by a dead process is removed first; one whose owner is alive
  // (any generation of base_name) makes create throw Error(system).
  static Writer create(const std::string& base_name, const WriterOptions& options);

  Writer(Writer&&) noexcept;
  Writer& operator=(Writer&&) noexcept;
  // Unlinks every generation it created (mapped Readers keep their mapping), marks the
  // segment closed and wakes sleeping Readers (they then see writer_alive() == false).
  ~Writer();

  // Reserves a slot of at least `size` bytes, moving to a larger generation first if needed
  // (or to a fresh one if another process truncated the current file).
  // Never waits for Readers: skips slots pinned by Readers (reclaiming pins of dead Readers).
  // If every slot is pinned by live Readers (possible when slot_count < kMaxPins * live
  // Readers + 1, e.g. the defaults with 3+ Readers holding samples), the loan is a private
  // buffer: committing it publishes nothing but takes a sequence number, so every Reader
  // counts it as a drop, and dropped() counts it here. Never throws for pinned slots.
  // Throws Error(too_large) if size > max_message_size, Error(system) if growth fails (e.g.
  // /dev/shm full: posix_fallocate's ENOSPC), and Error(invalid_argument) if another
  // WriteLoan of this Writer is still alive (one at a time).
  WriteLoan loan(std::size_t size);

  // Publishes the first `size` bytes of the loan as the next message and wakes all waiting
  // Readers with one futex wake. size <= loan.capacity(). Returns the message's sequence:
  // global across generations, 0 for the Writer's first message, +1 per commit (aborted loans
  // take none). Throws Error(invalid_argument) for a loan of another Writer or size > capacity.
  // `flags`: the caller's bits for this message, opaque to shm; Readers see them with it
  // (ReadSample::flags), also when it is carried into a new generation.
  std::uint64_t commit(WriteLoan&& loan, std::size_t size, std::uint64_t flags = 0);

  // Copy-in convenience: loan + memcpy + commit.
  std::uint64_t write(const void* data, std::size_t size, std::uint64_t flags = 0);

  const std::string& segment_name() const;     // current generation's name
  std::uint64_t published() const noexcept;    // messages committed so far (dropped included)
  std::uint64_t dropped() const noexcept;      // commits dropped because every slot was pinned
  std::uint32_t live_readers() const noexcept; // Readers registered now (dead ones not counted)
  // Readers registered now in this or an older generation they have not left yet, dead
  // ones included until reclaimed. Cheap (no /proc access): for the publish hot path;
  // live_readers() checks each reader's process (current generation only).
  std::uint32_t registered_readers() const noexcept;
  // While false, a commit never reuses the newest message's slot (the cache-hot choice when
  // every Reader has caught up), so the ring keeps the last slot_count - 1 messages for a
  // Reader that opens late with a backlog or a `since` (the start-up window). Default true.
  void set_hot_slot(bool allowed) noexcept;

 private:
  explicit Writer(std::unique_ptr<detail::WriterImpl> impl);
  std::unique_ptr<detail::WriterImpl> impl_;
};

// A message pinned in its slot: zero-copy read; the Writer cannot reuse the slot until the
// sample is destroyed. Must not outlive its Reader. At most kMaxPins samples per Reader.
class ReadSample {
 public:
  ReadSample(ReadSample&&) noexcept;
  ReadSample& operator=(ReadSample&&) noexcept;
  ReadSample(const ReadSample&) = delete;
  ReadSample& operator=(const ReadSample&) = delete;
  ~ReadSample();

  const std::byte* data() const noexcept { return data_; }
  std::size_t size() const noexcept { return size_; }
  std::uint64_t sequence() const noexcept { return sequence_; }  // as returned by commit()
  std::uint64_t flags() const noexcept { return flags_; }        // as given to commit()
  // Call AFTER reading (decoding/copying) the data: true if the slot still holds this message
  // and this Reader's registration was never taken over, i.e. nothing rewrote what was read
  // (seqlock-style re-check). False after a hostile truncation or a broken pin: discard what
  // was read and count it as a drop. Cheap (two loads).
  bool intact() const noexcept;

  // Detaches the sample from its Reader so that it can outlive the Reader's thread, the
  // Reader itself and the Writer's move to a new generation (zero-copy hand-off, e.g. to a
  // network stack that frees buffers on its own thread). Owner thread (the Reader's) only.
  // On success the pin and the mapping move into the returned DetachedSample and *this
  // becomes empty (data() stays as it was, intact() false). Returns nullopt and leaves *this
  // unchanged when kMaxDetached samples of this Reader are already detached and alive: the
  // last pin is kept for take(), so detaching can never make take() fail. The Writer keeps
  // skipping the slot until the DetachedSample is destroyed (so held samples cost the Writer
  // slots: see Writer::loan() for what happens when every slot is pinned). Never throws.
  std::optional<DetachedSample> detach() noexcept;

 private:
  friend class Reader;
  ReadSample(detail::ReaderImpl* r, int pin, const std::byte* d, std::size_t n, std::uint64_t s, std::uint64_t f)
      : reader_(r), pin_(pin), data_(d), size_(n), sequence_(s), flags_(f) {}
  detail::ReaderImpl* reader_ = nullptr;
  int pin_ = -1;
  const std::byte* data_ = nullptr;
  std::size_t size_ = 0;
  std::uint64_t sequence_ = 0;
  std::uint64_t flags_ = 0;
};

// A sample detached from its Reader (ReadSample::detach): a pinned, zero-copy message that
// may be read and destroyed on any thread, any number of threads reading at once.
// Thread contract: the destructor (or move-assignment over it) may run on any thread,
// concurrently with the Reader's owner thread calling take() and with other
// DetachedSamples being destroyed. Release protocol: the destructor stores kPinFree into
// its pin word in shared memory (release: every read of the payload happens-before the
// Writer's reuse of the slot), then clears the pin's bit in the Reader's detached mask
// (release; the owner thread's acquire load of the mask in take() pairs with it, so a pin
// is reused only after the free store, never overwritten by it). It keeps the generation's
// mapping and subscriber entry alive by itself: it stays valid after its Reader is
// destroyed, after the Writer moved to another generation, and after the Writer exited;
// the last holder of an old generation deregisters from it.
class DetachedSample {
 public:
  DetachedSample(DetachedSample&&) noexcept;
  DetachedSample& operator=(DetachedSample&&) noexcept;
  DetachedSample(const DetachedSample&) = delete;
  DetachedSample& operator=(const DetachedSample&) = delete;
  ~DetachedSample();  // releases the pin: any thread

  const std::byte* data() const noexcept { return data_; }
  std::size_t size() const noexcept { return size_; }
  std::uint64_t sequence() const noexcept { return sequence_; }
  // As ReadSample::intact(), callable from any thread: false if the slot was rewritten (a
  // broken pin: our entry reclaimed as dead) or the file truncated by another process.
  bool intact() const noexcept;

 private:
  friend class ReadSample;
  DetachedSample() = default;
  void release() noexcept;
  std::shared_ptr<detail::GenView> gen_;
  std::shared_ptr<detail::PinLedger> ledger_;
  int pin_ = -1;
  const std::byte* data_ = nullptr;
  std::size_t size_ = 0;
  std::uint64_t sequence_ = 0;
};

// What to wait on before sleeping: see Reader::arm().
struct WaitToken {
  const std::atomic<std::uint32_t>* word = nullptr;
  std::uint32_t expected = 0;
  // The word is in this process's private memory and woken with futex_wake_all_private
  // (FUTEX_PRIVATE_FLAG: the kernel keys it by address, no page lookup). Default: a word in
  // shared memory, woken with futex_wake_all from any process.
  bool process_private = false;
};

class Reader {
 public:
  static constexpr int kMaxPins = 4;  // ReadSamples alive at once per Reader
  // DetachedSamples alive at once per Reader (ReadSample::detach): one pin stays for take().
  static constexpr int kMaxDetached = kMaxPins - 1;

  // Opens a Writer's segment by name (any generation; follows to the newest) and registers
  // in its subscriber table, reclaiming entries of dead processes. The file must be owned by
  // our euid or root and not writable by others (names come from unauthenticated beacons).
  // Throws Error (not_found, corrupt, untrusted, no_subscriber_slot, system).
  // backlog: the first message returned is the oldest of the last
  // min(backlog, committed, slot_count - 1) messages committed in the newest generation at
  // open ("committed" includes messages it carried from the previous one, see
  // WriterOptions::keep), then every later one in order, each at most once. Older messages
  // are not counted as drops; a backlog message the Writer overwrites before take() gets to
  // it is a drop, as for any lagging Reader. Only what the Writer still holds can be
  // returned: with WriterOptions::keep < backlog, messages beyond keep may already be gone
  // (drops). backlog 0: the first message returned is the next one committed after open.
  // since_ns (monotonic_ns(); 0: none): also every message committed at or after that time,
  // as far as the ring still holds it — a subscriber that existed before it matched the
  // publisher gets what was published meanwhile (the start-up race). When the Writer was
  // created at or after since_ns, every message it ever committed is wanted: those the ring
  // no longer holds are counted as drops at once. (When it was created before, and the ring
  // holds no message older than since_ns, how many were overwritten cannot be known; the
  // oldest held is the first returned.) The first message returned is the older of the
  // backlog's and since's.
  // Called on any thread; the Reader is then used by one thread at a time.
  static Reader open(const std::string& segment_name, std::uint32_t backlog = 0, std::uint64_t since_ns = 0);

  Reader(Reader&&) noexcept;
  Reader& operator=(Reader&&) noexcept;
  ~Reader();  // deregisters

  // The next message in order, pinned; nullopt when there is none new. Messages overwritten
  // before being read are skipped and counted in drops(). Follows generations.
  // Throws Error(too_many_pins -> invalid_argument) if kMaxPins samples (ReadSamples and
  // DetachedSamples of this Reader) are alive; when
  // following the Writer to a new generation fails, the error of open() (no_subscriber_slot,
  // corrupt, untrusted, system) once: the Reader stays where it was and retries by itself
  // after 100 ms (doubling up to 1 s; has_data() is false meanwhile, take() returns nullopt
  // without throwing again until a follow succeeds). After a clean Writer exit, a Reader
  // still in an older generation drains every later one (the Writer leaves them for it);
  // anything it cannot reach any more is counted in drops().
  std::optional<ReadSample> take();

  bool has_data() const noexcept;             // take() would return a message now (hint)
  // While has_data() is false only because the Reader is backing off (a failed generation
  // follow, a truncated file, a Writer seen inside a slot probe): when to poll again. No
  // commit may wake a futex wait for it, so bound the wait by this. Epoch (time_point{})
  // when not backing off.
  std::chrono::steady_clock::time_point retry_at() const noexcept;
  // While armed: how many Readers (this one included) are armed on this segment, i.e. were
  // woken together by the last commit (hint, for fan-out scheduling). 0 when not armed.
  std::uint32_t armed_readers() const noexcept;
  std::uint64_t drops() const noexcept;       // messages this Reader lost
  // DetachedSamples of this Reader alive now (any thread may be releasing them: a snapshot).
  int detached() const noexcept;
  // ReadSample::detach() calls refused because kMaxDetached samples were alive.
  std::uint64_t detach_refused() const noexcept;
  std::uint64_t received() const noexcept;    // messages returned by take()
  // The Writer still runs and has not closed the segment: its OFD lock on the segment file is
  // held (works across pid namespaces; no pid is involved). One fcntl call.
  bool writer_alive() const;
  const std::string& segment_name() const;    // current generation

  // Sleep protocol (no lost wake-ups):
  //   WaitToken t = r.arm();           // registers as a waiter
  //   if (!r.has_data()) futex-wait on t (e.g. wait_any);
  //   r.disarm();                      // always, once per arm()
  WaitToken arm();
  void disarm() noexcept;

 private:
  explicit Reader(std::unique_ptr<detail::ReaderImpl> impl);
  std::unique_ptr<detail::ReaderImpl> impl_;
};

// (Liveness and death notification for core: lcmx/shm/liveness.hpp.)

// Removes segments with `prefix` whose Writer is gone (its OFD lock on the file is free:
// exact in every pid namespace sharing /dev/shm, immune to pid reuse), except generations a
// live Reader still needs to drain a cleanly exited Writer. Segments of live Writers are
// left alone (not counted). Files with the prefix that are foreign, truncated, corrupt or
// untrusted are left alone, logged with spdlog::warn (one line each) and counted in
// `skipped`. Never throws for bad files.
struct ReclaimReport {
  std::size_t removed = 0;
  std::size_t skipped = 0;
};
ReclaimReport reclaim_orphans(const std::string& prefix = kPrefix);

// CLOCK_MONOTONIC in nanoseconds: the clock of commit times and Reader::open's since_ns, one
// clock for every process of a host (and its containers).
std::uint64_t monotonic_ns() noexcept;

}  // namespace lcmx::shm
