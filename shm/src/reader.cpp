// Reader: one subscriber of a segment; follows the Writer across generations.
//
// Read protocol (reader keeps `next`, the seq it wants; seqs restart at 0 per generation):
//   W = write_seq (acquire; pairs with the Writer's write_seq release: desc[m % N] for all
//   m < W is visible).
//   Cases of the take() loop, each iteration either returns or advances `next`/generation:
//   a. next == W: nothing new here. If next_generation is set (acquire; pairs with the
//      Writer's release, stored after its last write_seq, so W is final) open the successor
//      and continue at its seq `carried` (its seqs 0..carried-1 are copies of the messages
//      we just drained or counted as drops here: global number first_global_seq + seq is the
//      same message in both generations; see start_in); else return nullopt.
//   b. W - next > N: the ring lapped us; the oldest W - N - next messages are gone: count
//      them as drops and jump to W - N.
//   c. d = desc[next % N] (acquire; pairs with the Writer's desc release) has another seq
//      (overwritten by next + k*N) or an out-of-range slot: drop one, advance.
//   d. pin `next` (seq_cst store), then slot.seq (seq_cst load; Dekker with the Writer's
//      WRITING store + pin scan, see writer.cpp). Equal to next => the Writer cannot reuse
//      the slot until we unpin, and the load read-from its seq release, so size and payload
//      are visible: return a zero-copy sample. WRITING => the Writer is probing or writing
//      it: re-check a bounded number of times (a probe that saw a pin restores `next`
//      without touching the payload; seqs are never reused, so seeing `next` again proves
//      it). Still WRITING after the spins and the Writer alive: it was preempted inside a
//      probe or is overwriting the slot; unpin and return nullopt without a drop (the next
//      take() looks again). Writer dead: it died mid-write: drop one, advance.
//      Anything else => overwritten: unpin, drop one, advance.
//   e. ReadSample::intact() re-checks after the caller's read (seqlock style: acquire fence,
//      then slot.seq and our entry's state word): a sample whose slot was rewritten while it
//      was read (our entry taken from us, or the file truncated under us) is not intact.
//   Open with a backlog k: next = W - min(k, W, N - 1) (case b cannot apply at once; what
//   the Writer overwrites before we get there is counted by cases b-d as usual).
//   All offsets come from the geometry validated at open; slot indices and sizes read from
//   shared memory are range-checked before use.
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <limits>
#include <utility>

#include "impl.hpp"

namespace lcmx::shm {
namespace detail {
namespace {

constexpr int kWritingSpins = 256;

inline void cpu_relax() noexcept {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#endif
}

// The commit time of message m of segment s, if the ring still holds it: read between two
// loads of the slot's seq that both see m (acquire: pairs with the Writer's seq release, after
// its relaxed commit_ns store). nullopt if it was overwritten or never written.
std::optional<std::uint64_t> commit_time(const Segment& s, std::uint64_t m) {
  const std::uint32_t n = s.geo.slot_count;
  const std::uint64_t d = s.desc(static_cast<std::uint32_t>(m % n)).load(std::memory_order_acquire);
  if (d == kDescEmpty || desc_seq(d) != m || desc_slot(d) >= n) return std::nullopt;
  const auto& sh = s.slot(desc_slot(d));
  if (sh.seq.load(std::memory_order_acquire) != m) return std::nullopt;
  const std::uint64_t t = sh.commit_ns.load(std::memory_order_relaxed);
  std::atomic_thread_fence(std::memory_order_acquire);
  if (sh.seq.load(std::memory_order_relaxed) != m) return std::nullopt;
  return t;
}

std::shared_ptr<GenView> make_view(std::unique_ptr<Segment> seg, std::int32_t pid) {
  auto v = std::make_shared<GenView>();
  std::tie(v->entry, v->word) = register_subscriber(*seg, seg->lock.get(), pid);
  v->pid = pid;
  v->seg = std::move(seg);
  return v;
}

// Messages of the Writer lost between global position `here` and `to` (both global).
std::uint64_t gap(std::uint64_t here, std::uint64_t to) {
  return to > here && to - here < (std::uint64_t{1} << 48) ? to - here : 0;
}

// Opens generation `gen` of base, or, if it is gone, the newest one above `floor`.
std::unique_ptr<Segment> open_generation_or_newer(const std::string& base, std::uint64_t gen,
                                                  std::optional<std::uint64_t> floor) {
  try {
    return open_segment(generation_name(base, gen));
  } catch (const Error& e) {
    if (e.code() != Errc::not_found) throw;
  }
  auto hi = find_highest_generation(base);
  if (!hi || (floor && *hi <= *floor)) {
    throw Error(Errc::not_found, "segment " + generation_name(base, gen) + ": not found");
  }
  return open_segment(generation_name(base, *hi));
}

// Seq in `to` at which a Reader whose next message has global number `here` continues, and
// the messages it lost in between (added to *drops). Seqs 0..carried-1 of `to` are copies of
// global messages first_global_seq.. (the previous generation's last ones): a Reader that
// drained the previous generation is at first_global_seq + carried and starts at carried
// (no duplicates); one that skipped generations and is behind first_global_seq starts at 0
// (carried messages it never had are delivered, the rest is drops).
std::uint64_t start_in(const Segment& to, std::uint64_t here, std::uint64_t* drops) {
  const std::uint64_t first = to.first_global_seq;
  if (here < first) {
    *drops += gap(here, first);
    return 0;
  }
  return std::min<std::uint64_t>(here - first, to.carried);
}

}  // namespace

// The seqlock re-check of ReadSample/DetachedSample::intact(). A Writer probing a pinned
// slot stores WRITING and then restores the seq without touching the payload (writer.cpp,
// step 3): WRITING is re-read a bounded number of times before it counts as a rewrite
// (seqs are never reused, so seeing `local` again proves the payload was not touched).
bool slot_still_holds(const std::byte* payload, std::uint64_t local, const GenView& gen) noexcept {
  // Acquire fence: the caller's payload reads happen before these loads.
  std::atomic_thread_fence(std::memory_order_acquire);
  const auto* sh = reinterpret_cast<const SlotHeader*>(payload - kSlotHeaderSize);
  std::uint64_t sq = sh->seq.load(std::memory_order_relaxed);
  for (int spin = 0; sq == kSlotWriting && spin < kWritingSpins; ++spin) {
    cpu_relax();
    sq = sh->seq.load(std::memory_order_relaxed);
  }
  return sq == local && gen.still_ours();
}

ReaderImpl::~ReaderImpl() {
  if (armed && armed->sub().armed.exchange(0, std::memory_order_acq_rel) != 0) {
    armed->seg->hdr->waiters.fetch_sub(1, std::memory_order_seq_cst);
  }
  for (int i = 0; i < kMaxPins; ++i) unpin(i);
  // The Writer exited and may have left later generations for Readers like us: the last
  // Reader that needs them removes them.
  const bool closed = cur && cur->seg->hdr->writer_closed.load(std::memory_order_acquire) != 0;
  armed.reset();
  cur.reset();  // deregisters (no view of ours is left)
  if (closed && ::getpid() == pid) release_unneeded_generations(base);
}

GenView::~GenView() {
  if (!seg || ::getpid() != pid) return;
  deregister_subscriber(*seg, entry, seg->lock.get());
  // The last holder of a generation may be a DetachedSample released after its Reader was
  // destroyed (on any thread): like ~ReaderImpl, remove what a closed Writer left for us.
  if (seg->hdr->writer_closed.load(std::memory_order_acquire) != 0) {
    if (auto sg = split_generation(seg->name)) {
      const std::string base = sg->first;
      seg.reset();
      release_unneeded_generations(base);
    }
  }
}

void ReaderImpl::unpin(int pin) noexcept {
  if (pin < 0 || pin >= kMaxPins || !pin_gen[pin]) return;
  // Release: our payload reads happen-before the Writer's reuse (its pin load reads this).
  pin_gen[pin]->sub().pins[pin].store(kPinFree, std::memory_order_release);
  pin_gen[pin].reset();
}

void ReaderImpl::publish_counters() noexcept {
  auto& e = cur->sub();
  e.drops.store(drops, std::memory_order_relaxed);
  e.next.store(next, std::memory_order_relaxed);
}

bool ReaderImpl::try_follow() {
  if (dead_end) return false;
  const Segment& s = *cur->seg;
  // Acquire: pairs with the Writer's next_generation release (after its last write_seq).
  const std::uint64_t ng = s.hdr->next_generation.load(std::memory_order_acquire);
  if (ng == 0) return false;
  if (next < s.hdr->write_seq.load(std::memory_order_acquire)) return true;  // drain first
  if (ng <= s.generation) {  // hostile or corrupt: never go backwards
    dead_end = true;
    return false;
  }
  const auto now = std::chrono::steady_clock::now();
  if (now < retry_at) return false;
  const std::uint64_t here = s.first_global_seq + next;
  std::shared_ptr<GenView> view;
  try {
    auto seg = open_generation_or_newer(base, ng, s.generation);
    if (seg->generation <= s.generation) {
      dead_end = true;
      return false;
    }
    view = make_view(std::move(seg), pid);
  } catch (const Error& e) {
    if (e.code() == Errc::not_found) {
      // Writer gone and its later generations removed (e.g. by reclaim after its exit):
      // nothing newer will come. A clean exit recorded how many it published: count them.
      dead_end = true;
      if (s.hdr->writer_closed.load(std::memory_order_acquire) != 0) {
        drops += gap(here, s.hdr->final_seq.load(std::memory_order_relaxed));
      }
      return false;
    }
    // E.g. the new generation's table is full or its file is refused: retry later (100 ms,
    // doubling to 1 s) instead of failing on every call; report the first failure only.
    const bool first = backoff.count() == 0;
    backoff = first ? std::chrono::milliseconds(100)
                    : std::min(backoff * 2, std::chrono::milliseconds(1000));
    retry_at = now + backoff;
    if (first) throw;
    return false;
  }
  backoff = std::chrono::milliseconds(0);
  retry_at = {};
  // Messages of skipped generations (if any) are drops; first_global_seq makes it exact.
  const std::uint64_t start = start_in(*view->seg, here, &drops);
  cur = std::move(view);  // the old view deregisters when unpinned
  next = start;
  publish_counters();
  if (cur->seg->hdr->writer_closed.load(std::memory_order_acquire) != 0) {
    release_unneeded_generations(base, cur->seg->generation);
  }
  return true;
}

// The current generation's file was truncated by another process (our mapping reads zeros
// from the faulting page on). The Writer moves to a fresh generation at its next loan; go
// there by name and count what was lost in between. Until it exists: nothing to read
// (has_data() false for 10 ms at a time).
bool ReaderImpl::follow_fault() {
  const Segment& s = *cur->seg;
  auto hi = find_highest_generation(base);
  std::unique_ptr<Segment> seg;
  if (hi && *hi > s.generation) {
    try {
      seg = open_segment(generation_name(base, *hi));
    } catch (const Error&) {
      seg.reset();
    }
  }
  if (!seg || seg->generation <= s.generation || seg->faulted()) {
    retry_at = std::chrono::steady_clock::now() + std::chrono::milliseconds(10);
    return false;
  }
  const std::uint64_t start = start_in(*seg, s.first_global_seq + next, &drops);
  cur = make_view(std::move(seg), pid);
  next = start;
  retry_at = {};
  publish_counters();
  return true;
}

}  // namespace detail

// ---- ReadSample ----

ReadSample::ReadSample(ReadSample&& o) noexcept
    : reader_(std::exchange(o.reader_, nullptr)), pin_(std::exchange(o.pin_, -1)),
      data_(o.data_), size_(o.size_), sequence_(o.sequence_), flags_(o.flags_) {}

ReadSample& ReadSample::operator=(ReadSample&& o) noexcept {
  if (this != &o) {
    if (reader_ != nullptr) reader_->unpin(pin_);
    reader_ = std::exchange(o.reader_, nullptr);
    pin_ = std::exchange(o.pin_, -1);
    data_ = o.data_;
    size_ = o.size_;
    sequence_ = o.sequence_;
    flags_ = o.flags_;
  }
  return *this;
}

ReadSample::~ReadSample() {
  if (reader_ != nullptr) reader_->unpin(pin_);
}

bool ReadSample::intact() const noexcept {
  if (reader_ == nullptr || pin_ < 0 || pin_ >= detail::kMaxPins) return false;
  const auto& gen = reader_->pin_gen[pin_];
  if (!gen) return false;
  return detail::slot_still_holds(data_, sequence_ - gen->seg->first_global_seq, *gen);
}

std::optional<DetachedSample> ReadSample::detach() noexcept {
  if (reader_ == nullptr || pin_ < 0 || pin_ >= detail::kMaxPins || !reader_->pin_gen[pin_]) {
    return std::nullopt;
  }
  auto& r = *reader_;
  // Only this (the owner) thread sets bits, so the count cannot grow under us; releasers
  // may clear bits meanwhile (then we refuse one that would have fit: harmless).
  const std::uint32_t mask = r.ledger->detached.load(std::memory_order_acquire);
  if (std::popcount(mask) >= Reader::kMaxDetached) {
    ++r.detach_refused;
    return std::nullopt;
  }
  DetachedSample d;
  const std::uint32_t bit = std::uint32_t{1} << pin_;
  // Relaxed: only the owner thread reads the bit to decide (it set it itself); the pin word
  // in shared memory stays set, so the Writer keeps skipping the slot.
  r.ledger->detached.fetch_or(bit, std::memory_order_relaxed);
  d.gen_ = std::move(r.pin_gen[pin_]);
  r.pin_gen[pin_].reset();
  d.ledger_ = r.ledger;
  d.pin_ = std::exchange(pin_, -1);
  d.data_ = data_;
  d.size_ = size_;
  d.sequence_ = sequence_;
  reader_ = nullptr;
  return d;
}

// ---- DetachedSample ----

DetachedSample::DetachedSample(DetachedSample&& o) noexcept
    : gen_(std::move(o.gen_)), ledger_(std::move(o.ledger_)), pin_(std::exchange(o.pin_, -1)),
      data_(o.data_), size_(o.size_), sequence_(o.sequence_) {}

DetachedSample& DetachedSample::operator=(DetachedSample&& o) noexcept {
  if (this != &o) {
    release();
    gen_ = std::move(o.gen_);
    ledger_ = std::move(o.ledger_);
    pin_ = std::exchange(o.pin_, -1);
    data_ = o.data_;
    size_ = o.size_;
    sequence_ = o.sequence_;
  }
  return *this;
}

DetachedSample::~DetachedSample() { release(); }

void DetachedSample::release() noexcept {
  if (!gen_ || pin_ < 0 || pin_ >= detail::kMaxPins) return;
  // 1. Release: the payload reads (on any thread that had the sample) happen-before the
  //    Writer's reuse of the slot (its pin load reads this store).
  gen_->sub().pins[pin_].store(detail::kPinFree, std::memory_order_release);
  // 2. Release: pairs with take()'s acquire load of the mask; the owner thread stores a new
  //    seq into this pin word only after it sees the bit clear, hence after step 1.
  ledger_->detached.fetch_and(~(std::uint32_t{1} << pin_), std::memory_order_release);
  pin_ = -1;
  // 3. The last holder of the generation unmaps it and deregisters from it (GenView).
  gen_.reset();
  ledger_.reset();
}

bool DetachedSample::intact() const noexcept {
  if (!gen_ || pin_ < 0) return false;
  return detail::slot_still_holds(data_, sequence_ - gen_->seg->first_global_seq, *gen_);
}

// ---- Reader ----

Reader::Reader(std::unique_ptr<detail::ReaderImpl> impl) : impl_(std::move(impl)) {}
Reader::Reader(Reader&&) noexcept = default;
Reader& Reader::operator=(Reader&&) noexcept = default;
Reader::~Reader() = default;

static_assert(Reader::kMaxPins == detail::kMaxPins);

Reader Reader::open(const std::string& segment_name, std::uint32_t backlog, std::uint64_t since_ns) {
  using namespace detail;
  if (segment_name.empty() || segment_name.size() > 240 ||
      segment_name.find('/') != std::string::npos) {
    throw Error(Errc::invalid_argument, "Reader: bad segment name '" + segment_name + "'");
  }
  auto impl = std::make_unique<ReaderImpl>();
  impl->pid = static_cast<std::int32_t>(::getpid());
  std::unique_ptr<Segment> seg;
  if (auto sg = split_generation(segment_name)) {
    impl->base = sg->first;
    seg = open_generation_or_newer(impl->base, sg->second, std::nullopt);
  } else {  // a base name: open its newest generation
    impl->base = segment_name;
    auto hi = find_highest_generation(impl->base);
    if (!hi) throw Error(Errc::not_found, "segment " + segment_name + ": not found");
    seg = open_segment(generation_name(impl->base, *hi));
  }
  // Follow to the newest generation (bounded: a hostile chain cannot loop us forever).
  for (int hops = 0; hops < 64; ++hops) {
    const std::uint64_t ng = seg->hdr->next_generation.load(std::memory_order_acquire);
    if (ng <= seg->generation) break;
    try {
      seg = open_generation_or_newer(impl->base, ng, seg->generation);
    } catch (const Error& e) {
      if (e.code() != Errc::not_found) throw;
      break;  // Writer gone: stay on the last one
    }
  }
  impl->cur = make_view(std::move(seg), impl->pid);
  const Segment& s = *impl->cur->seg;
  const std::uint64_t w = s.hdr->write_seq.load(std::memory_order_acquire);
  const std::uint64_t k = std::min<std::uint64_t>({backlog, w, s.geo.slot_count - 1u});
  impl->next = w - k;
  if (since_ns != 0) {
    // The oldest seq the ring may still hold (one slot is the one being written).
    const std::uint64_t lo = w - std::min<std::uint64_t>(w, s.geo.slot_count - 1u);
    std::uint64_t first = w;  // first wanted seq found in the ring
    if (since_ns <= s.writer_created_ns) {
      // Everything the Writer committed is wanted: what the ring no longer holds is lost.
      first = lo;
      impl->drops += s.first_global_seq + lo;
    } else {
      // Newest first: stop at a message older than since_ns, or one no longer held.
      for (std::uint64_t m = w; m > lo; --m) {
        const auto t = commit_time(s, m - 1);
        if (!t || *t < since_ns) break;
        first = m - 1;
      }
    }
    impl->next = std::min(impl->next, first);
  }
  impl->publish_counters();
  return Reader(std::move(impl));
}

std::optional<ReadSample> Reader::take() {
  using namespace detail;
  auto& r = *impl_;
  int pin = -1;
  // Acquire: pairs with a DetachedSample's release (fetch_and after its kPinFree store): a
  // pin whose bit is clear is free in shared memory too, and our store below comes after.
  const std::uint32_t detached = r.ledger->detached.load(std::memory_order_acquire);
  for (int i = 0; i < kMaxPins; ++i) {
    if (!r.pin_gen[i] && (detached & (std::uint32_t{1} << i)) == 0) {
      pin = i;
      break;
    }
  }
  if (pin < 0) {
    throw Error(Errc::invalid_argument,
                "Reader::take: too many pins (kMaxPins samples alive)");
  }
  const std::uint64_t dropped_before = r.drops;
  // Bound: after case b at most N+1 iterations per generation; a few generation hops.
  const std::uint64_t budget = 4 * std::uint64_t{r.cur->seg->geo.slot_count} + 64;
  for (std::uint64_t iter = 0; iter < budget; ++iter) {
    if (r.cur->seg->faulted()) {
      if (std::chrono::steady_clock::now() >= r.retry_at && r.follow_fault()) continue;
      break;
    }
    const Segment& s = *r.cur->seg;
    const std::uint64_t n = s.geo.slot_count;
    const std::uint64_t w = s.hdr->write_seq.load(std::memory_order_acquire);
    if (w <= r.next) {  // case a (w < next only if the header was tampered with)
      if (r.try_follow()) continue;
      break;
    }
    if (w - r.next > n) {  // case b
      r.drops += w - n - r.next;
      r.next = w - n;
    }
    const std::uint64_t d = s.desc(static_cast<std::uint32_t>(r.next % n))
                                .load(std::memory_order_acquire);
    const std::uint32_t slot = desc_slot(d);
    if (desc_seq(d) != r.next || slot >= n) {  // case c
      ++r.drops;
      ++r.next;
      continue;
    }
    auto& pin_word = r.cur->sub().pins[pin];
    pin_word.store(r.next, std::memory_order_seq_cst);  // case d
    const SlotHeader& sh = s.slot(slot);
    std::uint64_t sq = sh.seq.load(std::memory_order_seq_cst);
    for (int spin = 0; sq == kSlotWriting && spin < kWritingSpins; ++spin) {
      cpu_relax();
      sq = sh.seq.load(std::memory_order_seq_cst);
    }
    if (sq == kSlotWriting && locked_by_other(s.lock.get(), kWriterLockByte)) {
      // Case d, Writer alive: preempted (or stopped) inside a probe, or overwriting. Not a
      // drop yet. has_data() says false for 1 ms so an executor sleeps instead of spinning
      // on a stopped Writer; the Writer's next commit wakes it.
      pin_word.store(kPinFree, std::memory_order_release);
      r.retry_at = std::chrono::steady_clock::now() + std::chrono::milliseconds(1);
      break;
    }
    // size is read only once sq == next: the seq load read-from the Writer's release and
    // our pin keeps the slot stable from here on.
    const std::uint64_t size = sq == r.next ? sh.size : 0;
    const std::uint64_t flags = sq == r.next ? sh.flags : 0;  // as size
    if (s.faulted()) {  // truncated while we looked: nothing read here is real
      pin_word.store(kPinFree, std::memory_order_release);
      continue;
    }
    if (sq != r.next || size > s.geo.slot_size) {
      pin_word.store(kPinFree, std::memory_order_release);
      ++r.drops;
      ++r.next;
      continue;
    }
    r.pin_gen[pin] = r.cur;
    const std::uint64_t seq = s.first_global_seq + r.next;
    ++r.next;
    ++r.received;
    r.publish_counters();
    return ReadSample(&r, pin, s.payload(slot), static_cast<std::size_t>(size), seq, flags);
  }
  if (r.drops != dropped_before) r.publish_counters();
  return std::nullopt;
}

bool Reader::has_data() const noexcept {
  const auto& r = *impl_;
  if (r.retry_at != std::chrono::steady_clock::time_point{} &&
      std::chrono::steady_clock::now() < r.retry_at) {
    return false;  // backing off after a failed follow (see try_follow)
  }
  if (r.cur->seg->faulted()) return true;  // take() moves on to the Writer's new file
  const auto& h = *r.cur->seg->hdr;
  if (h.write_seq.load(std::memory_order_acquire) != r.next) return true;
  return !r.dead_end && h.next_generation.load(std::memory_order_acquire) != 0;
}

std::chrono::steady_clock::time_point Reader::retry_at() const noexcept {
  const auto t = impl_->retry_at;
  return t > std::chrono::steady_clock::now() ? t : std::chrono::steady_clock::time_point{};
}

std::uint32_t Reader::armed_readers() const noexcept {
  const auto& r = *impl_;
  if (!r.armed) return 0;
  return static_cast<std::uint32_t>(r.armed->seg->hdr->waiters.load(std::memory_order_relaxed));
}

std::uint64_t Reader::drops() const noexcept { return impl_->drops; }
int Reader::detached() const noexcept {
  return std::popcount(impl_->ledger->detached.load(std::memory_order_acquire));
}
std::uint64_t Reader::detach_refused() const noexcept { return impl_->detach_refused; }
std::uint64_t Reader::received() const noexcept { return impl_->received; }

bool Reader::writer_alive() const {
  const auto& seg = *impl_->cur->seg;
  if (seg.hdr->writer_closed.load(std::memory_order_acquire) != 0) return false;
  return detail::locked_by_other(seg.lock.get(), detail::kWriterLockByte);
}

const std::string& Reader::segment_name() const { return impl_->cur->seg->name; }

WaitToken Reader::arm() {
  auto& r = *impl_;
  disarm();
  r.armed = r.cur;
  auto& h = *r.armed->seg->hdr;
  // seq_cst: Reader side of the waiter Dekker (see writer.cpp); the futex_word load comes
  // after the waiters increment in the single total order. `armed` (after the increment)
  // lets a reclaimer take back the count of a Reader killed while armed.
  h.waiters.fetch_add(1, std::memory_order_seq_cst);
  r.armed->sub().armed.store(1, std::memory_order_release);
  return WaitToken{&h.futex_word, h.futex_word.load(std::memory_order_seq_cst)};
}

void Reader::disarm() noexcept {
  auto& r = *impl_;
  if (!r.armed) return;
  // Whoever resets `armed` from 1 subtracts (a reclaimer only does so for dead Readers).
  if (r.armed->sub().armed.exchange(0, std::memory_order_acq_rel) != 0) {
    r.armed->seg->hdr->waiters.fetch_sub(1, std::memory_order_seq_cst);
  }
  r.armed.reset();
}

}  // namespace lcmx::shm
