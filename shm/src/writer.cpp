// Writer: single publisher of a segment (and of its later generations).
//
// Publish protocol (invariant: a slot whose seq a live Reader has pinned is never written):
//   1. choose slot s round-robin; old = its current seq (writer's private copy);
//   2. slot[s].seq = WRITING (seq_cst store);
//   3. scan pins (seq_cst loads) of subscriber entries [0, sub_high_water) for `old`;
//      pinned => slot[s].seq = old (nothing was written) and try the next slot.
//      Dekker with the Reader (pin store seq_cst; then slot.seq load seq_cst): in the single
//      total order S of seq_cst operations, either the Reader's slot.seq load comes after our
//      WRITING store (it sees WRITING or a later value != its seq: it unpins and drops), or it
//      comes before, hence its pin store precedes our WRITING store and our pin loads: we see
//      the pin and skip the slot. Exactly one side backs off; never both proceed.
//   4. write payload (caller), slot.size, slot.seq = m (release), desc[m % N] = pack(m, s)
//      (release), write_seq = m+1 (release), futex_word += 1 (seq_cst), then FUTEX_WAKE only
//      if waiters > 0 (seq_cst load). Dekker with Reader::arm (waiters += 1 seq_cst; then
//      futex_word load seq_cst; then has_data): either we see waiters > 0 and wake, or the
//      Reader's futex_word load comes after our increment, so its expected value includes it
//      (and, reading from our RMW, it also sees write_seq = m+1: has_data() is true).
//   A writer dying between 2 and 4 leaves seq = WRITING: that message is never delivered.
//
// Slot bound: every live Reader pins at most kMaxPins slots, so with
// slot_count >= kMaxPins * live_readers + 1 a free slot always exists. Below that bound (the
// default: 8 slots, up to 32 Readers) every slot may be pinned: after reclaiming dead
// Readers' pins, loan() then hands out a private drop buffer; committing it takes the next
// seq without a slot (desc = pack(m, slot_count), an index no Reader accepts), so every
// Reader counts that message as a drop, and Writer::dropped() counts it here. Never throws.
#include <unistd.h>

#include <algorithm>
#include <climits>
#include <cstring>
#include <ctime>
#include <utility>

#include "impl.hpp"
#include "lcmx/shm/futex.hpp"

namespace lcmx::shm {

std::uint64_t monotonic_ns() noexcept {
  timespec ts{};
  ::clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::uint64_t>(ts.tv_sec) * 1000000000u + static_cast<std::uint64_t>(ts.tv_nsec);
}

namespace detail {
namespace {

bool valid_name_char(char c) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
         c == '_' || c == '-' || c == '.';
}

std::uint64_t initial_slot_size(const WriterOptions& o) {
  return round_up(std::max<std::uint64_t>(o.initial_slot_size, 1), kCacheLine);
}

constexpr std::uint32_t kScratchSlot = ~std::uint32_t{0};

}  // namespace

// Clean exit: every generation gets final_seq, then writer_closed (release), and its
// sleepers are woken. Generations older than the oldest one with a live Reader are
// unlinked; from that one on they stay if it is older than the current one (its Readers
// need the later names to follow, and the kept name of their own generation shows others -
// reclaim_orphans - that they are there). Readers that mapped a generation keep reading it
// after the unlink. What is left is unlinked by the last Reader to need it
// (release_unneeded_generations), or by reclaim_orphans once no live Reader needs it.
WriterImpl::~WriterImpl() {
  if (!seg || ::getpid() != pid) return;  // a fork()ed child's copy must not tear down ours
  const std::uint64_t total = seg->first_global_seq + write_seq;
  std::vector<Segment*> all;
  for (const auto& g : old_gens) all.push_back(g.get());
  all.push_back(seg.get());
  for (Segment* g : all) {
    g->hdr->final_seq.store(total, std::memory_order_relaxed);
    g->hdr->writer_closed.store(1, std::memory_order_release);
    bump_and_wake(*g);
  }
  // Same rule as release_unneeded_generations: keep [oldest generation with a live Reader,
  // current] if that is more than the current one, else unlink everything.
  std::size_t first_kept = all.size();
  for (std::size_t k = 0; k + 1 < all.size(); ++k) {
    if (has_live_subscriber(*all[k])) {
      first_kept = k;
      break;
    }
  }
  for (std::size_t k = 0; k < first_kept; ++k) unlink_segment(all[k]->name);
}

// Dead Readers of the current generation: their pins and waiter counts (a Reader killed
// armed costs a wake syscall per commit) are reclaimed every 256 commits, or at the first
// 16th commit after 1 s.
void WriterImpl::maybe_reclaim() noexcept {
  if ((commits & 15) != 0) return;  // the clock is read every 16th commit only
  const auto now = std::chrono::steady_clock::now();
  if ((commits & 255) != 0 && now < next_reclaim) return;
  next_reclaim = now + std::chrono::seconds(1);
  reclaim_dead_subscribers(*seg);
}

void WriterImpl::release_old_generations(bool reclaim_dead) noexcept {
  while (!old_gens.empty()) {
    const Segment& g = *old_gens.front();
    if (reclaim_dead) reclaim_dead_subscribers(g);
    const std::uint32_t hw =
        std::min(g.hdr->sub_high_water.load(std::memory_order_acquire), g.geo.max_subscribers);
    for (std::uint32_t i = 0; i < hw; ++i) {
      if (sub_state(g.sub(i).state.load(std::memory_order_acquire)) != kSubFree) return;
    }
    unlink_segment(g.name);  // Readers that mapped it keep their mapping
    old_gens.pop_front();
  }
}

void WriterImpl::bump_and_wake(const Segment& s) noexcept {
  // seq_cst RMW, then seq_cst load of waiters: see the Dekker argument at the top.
  s.hdr->futex_word.fetch_add(1, std::memory_order_seq_cst);
  if (s.hdr->waiters.load(std::memory_order_seq_cst) > 0) futex_wake_all(&s.hdr->futex_word);
}

// Keep-last-N carry-over (WriterOptions::keep). Runs inside create_segment, before the new
// generation's magic is published: nobody else can see `to` yet. Reads `from` (ours; no loan
// is outstanding) through the Writer's private slot_seq, never trusting shared memory for
// which slot holds which message: message m (of the last `keep`) is carried only if a slot
// still holds it (slot_seq and the slot's seq word agree) with a size <= its slot size, and
// only a contiguous tail (the carried ones must be exactly the last c messages: their
// global numbers stay first_global_seq + seq). A message taken by the drop buffer (no slot)
// or overwritten because a pinned slot was skipped ends the tail. A truncated file (the
// SIGBUS guard reads zeros) carries nothing: the fault is checked after copying.
std::uint32_t WriterImpl::carry(const Segment& from, Segment& to) const {
  if (opt.keep == 0 || write_seq == 0 || from.faulted()) return 0;
  const std::uint32_t n = from.geo.slot_count;
  const std::uint64_t want = std::min<std::uint64_t>(opt.keep, write_seq);
  // (slot, size) of messages write_seq - 1, - 2, ... (newest first); each size read once.
  std::vector<std::pair<std::uint32_t, std::uint64_t>> tail;
  for (std::uint64_t k = 1; k <= want; ++k) {
    const std::uint64_t m = write_seq - k;
    std::uint32_t s = n;
    for (std::uint32_t i = 0; i < n; ++i) {
      if (slot_seq[i] == m) {
        s = i;
        break;
      }
    }
    if (s == n || from.slot(s).seq.load(std::memory_order_relaxed) != m) break;
    const std::uint64_t size = from.slot(s).size;
    if (size > from.geo.slot_size || size > to.geo.slot_size) break;
    tail.emplace_back(s, size);
  }
  const auto c = static_cast<std::uint32_t>(tail.size());
  for (std::uint32_t i = 0; i < c; ++i) {  // oldest first: new seq i, new slot i
    const auto [s, size] = tail[c - 1 - i];
    if (size != 0) std::memcpy(to.payload(i), from.payload(s), size);
    to.slot(i).size = size;
    to.slot(i).commit_ns.store(from.slot(s).commit_ns.load(std::memory_order_relaxed), std::memory_order_relaxed);
    to.slot(i).flags = from.slot(s).flags;
    to.slot(i).seq.store(i, std::memory_order_relaxed);  // published by the magic release
    to.desc(i).store(pack_desc(i, i), std::memory_order_relaxed);
  }
  if (from.faulted()) {  // truncated while we copied: what we read may be zeros
    for (std::uint32_t i = 0; i < c; ++i) {
      to.slot(i).seq.store(kSlotEmpty, std::memory_order_relaxed);
      to.desc(i).store(kDescEmpty, std::memory_order_relaxed);
    }
    return 0;
  }
  return c;
}

// same_size: the current generation was truncated by another process (its mapping now
// reads zeros): move to a fresh file of the same geometry; Readers follow by name.
// With keep > 0 the new generation starts with the old one's last c <= keep messages
// (carry), so first_global_seq (the global number of its seq 0) is old total - c.
void WriterImpl::grow(std::size_t size, bool same_size) {
  const std::uint64_t old_size = seg->geo.slot_size;
  std::uint64_t want = std::max<std::uint64_t>(round_up(size, 4096), 2 * old_size);
  want = std::min<std::uint64_t>(want, opt.max_message_size);
  want = round_up(std::max<std::uint64_t>(want, size), kCacheLine);
  if (same_size) want = old_size;
  const Geometry geo = make_geometry(seg->geo.slot_count, seg->geo.max_subscribers, want);
  const std::uint64_t gen = seg->generation + 1;
  // first_global_seq is of seq 0: create_segment gets the old total and fill lowers it by
  // the number actually carried, before the magic is published.
  std::uint32_t carried = 0;
  const Segment& from = *seg;
  auto fill = [&](Segment& to) {
    carried = carry(from, to);
    to.first_global_seq = from.first_global_seq + write_seq - carried;
    to.hdr->first_global_seq = to.first_global_seq;
    return carried;
  };
  const std::uint64_t total = seg->first_global_seq + write_seq;
  auto next = create_segment(generation_name(base, gen), geo, gen, total, pid, start_time, created_ns,
                             opt.keep != 0 ? std::function<std::uint32_t(Segment&)>(fill)
                                           : std::function<std::uint32_t(Segment&)>());
  // The new generation is fully initialised (carried messages, write_seq, magic published).
  // Release pairs with the Reader's next_generation.load(acquire): it then sees our final
  // write_seq here too, and (through the new file's magic) the new generation's carried.
  seg->hdr->next_generation.store(gen, std::memory_order_release);
  bump_and_wake(*seg);  // sleeping Readers of the old generation must move on
  // The old name stays while Readers are registered there or earlier (they open the next
  // generation by name); see release_old_generations.
  old_gens.push_back(std::move(seg));
  seg = std::move(next);
  release_old_generations(true);
  slot_seq.assign(geo.slot_count, kSlotEmpty);
  for (std::uint32_t i = 0; i < carried; ++i) slot_seq[i] = i;
  next_slot = carried % geo.slot_count;
  write_seq = carried;
}

bool WriterImpl::pinned(std::uint64_t seq) const noexcept {
  const std::uint32_t hw =
      std::min(seg->hdr->sub_high_water.load(std::memory_order_seq_cst), seg->geo.max_subscribers);
  for (std::uint32_t i = 0; i < hw; ++i) {
    for (const auto& p : seg->sub(i).pins) {
      // seq_cst: the writer side of the Dekker pair (after the WRITING store).
      if (p.load(std::memory_order_seq_cst) == seq) return true;
    }
  }
  return false;
}

// True when every Reader registered here has taken every committed message (and none is
// still in an older generation): then no Reader needs the newest message's slot any more.
// True when at least one Reader is registered and every one has taken every message. (No
// Reader at all: false, so the ring keeps recent messages for a Reader that comes late.)
bool WriterImpl::readers_caught_up() const noexcept {
  if (!old_gens.empty() || write_seq == 0) return false;
  bool any = false;
  const std::uint32_t hw =
      std::min(seg->hdr->sub_high_water.load(std::memory_order_acquire), seg->geo.max_subscribers);
  for (std::uint32_t i = 0; i < hw; ++i) {
    const auto& e = seg->sub(i);
    if (sub_state(e.state.load(std::memory_order_acquire)) == kSubFree) continue;
    if (e.next.load(std::memory_order_relaxed) < write_seq) return false;
    any = true;
  }
  return any;
}

std::optional<std::uint32_t> WriterImpl::acquire_slot() {
  const std::uint32_t n = seg->geo.slot_count;
  // Readers keeping up (the common case): reuse the newest message's slot, still in the
  // cache, instead of the round-robin one (large messages: a cold 6 MB slot costs a copy's
  // worth of cache misses). Its pin check below still protects a Reader reading it now.
  // Not with keep > 0: reusing the newest message's slot would overwrite it (the last
  // `keep` messages must stay readable for late Readers).
  if (opt.keep == 0 && hot_slot && readers_caught_up()) {
    const std::uint32_t hot = desc_slot(seg->desc(static_cast<std::uint32_t>((write_seq - 1) % n))
                                            .load(std::memory_order_relaxed));
    if (hot < n && slot_seq[hot] == write_seq - 1) next_slot = hot;
  }
  for (int round = 0; round < 2; ++round) {
    for (std::uint32_t k = 0; k < n; ++k) {
      const std::uint32_t s = (next_slot + k) % n;
      const std::uint64_t old = slot_seq[s];
      auto& seq = seg->slot(s).seq;
      seq.store(kSlotWriting, std::memory_order_seq_cst);
      // Cases: old is Empty (never delivered, nobody can pin it) => ours; old pinned =>
      // restore (payload untouched, the pinning Reader keeps a valid sample) and try next.
      if (old != kSlotEmpty && pinned(old)) {
        seq.store(old, std::memory_order_seq_cst);
        continue;
      }
      next_slot = (s + 1) % n;
      slot_seq[s] = kSlotWriting;
      // Release: the WRITING store comes before the new commit_ns (and payload) stores for a
      // Reader that reads commit_ns without a pin (reader.cpp commit_time: its acquire fence).
      std::atomic_thread_fence(std::memory_order_release);
      return s;
    }
    // Every slot pinned: clear pins of dead Readers, then one more round.
    if (round == 0 && reclaim_dead_subscribers(*seg) == 0) break;
  }
  return std::nullopt;  // every slot pinned by live Readers: the caller drops the message
}

void WriterImpl::abort_loan(std::uint32_t slot) noexcept {
  if (slot == kScratchSlot) {
    loan_out = false;
    return;
  }
  // The payload may be partly overwritten: the old message is gone (Readers count a drop).
  seg->slot(slot).seq.store(kSlotEmpty, std::memory_order_release);
  slot_seq[slot] = kSlotEmpty;
  loan_out = false;
}

std::uint64_t WriterImpl::commit(std::uint32_t slot, std::size_t size, std::uint64_t flags) {
  const std::uint64_t m = write_seq;
  ++commits;
  if (slot == kScratchSlot) {
    // Dropped: m takes a descriptor with an invalid slot index, so every Reader counts it.
    seg->desc(static_cast<std::uint32_t>(m % seg->geo.slot_count))
        .store(pack_desc(m, seg->geo.slot_count), std::memory_order_release);
    seg->hdr->write_seq.store(m + 1, std::memory_order_release);
    write_seq = m + 1;
    loan_out = false;
    ++dropped;
    bump_and_wake(*seg);
    maybe_reclaim();
    return seg->first_global_seq + m;
  }
  auto& sh = seg->slot(slot);
  sh.size = size;
  sh.commit_ns.store(monotonic_ns(), std::memory_order_relaxed);
  sh.flags = flags;
  // Release: payload + size + commit_ns + flags visible to a Reader whose slot.seq load reads m.
  sh.seq.store(m, std::memory_order_release);
  // Release: pairs with the Reader's desc load (acquire).
  seg->desc(static_cast<std::uint32_t>(m % seg->geo.slot_count))
      .store(pack_desc(m, slot), std::memory_order_release);
  // Release: pairs with the Reader's write_seq load (acquire): desc[m % N] is then visible.
  seg->hdr->write_seq.store(m + 1, std::memory_order_release);
  write_seq = m + 1;
  slot_seq[slot] = m;
  loan_out = false;
  bump_and_wake(*seg);
  if (!old_gens.empty()) release_old_generations(commits % 1024 == 0);
  maybe_reclaim();
  return seg->first_global_seq + m;
}

}  // namespace detail

// ---- WriteLoan ----

WriteLoan::WriteLoan(WriteLoan&& o) noexcept
    : writer_(std::exchange(o.writer_, nullptr)), slot_(o.slot_), data_(o.data_),
      capacity_(o.capacity_) {}

WriteLoan& WriteLoan::operator=(WriteLoan&& o) noexcept {
  if (this != &o) {
    if (writer_ != nullptr) writer_->abort_loan(slot_);
    writer_ = std::exchange(o.writer_, nullptr);
    slot_ = o.slot_;
    data_ = o.data_;
    capacity_ = o.capacity_;
  }
  return *this;
}

WriteLoan::~WriteLoan() {
  if (writer_ != nullptr) writer_->abort_loan(slot_);
}

// ---- Writer ----

Writer::Writer(std::unique_ptr<detail::WriterImpl> impl) : impl_(std::move(impl)) {}
Writer::Writer(Writer&&) noexcept = default;
Writer& Writer::operator=(Writer&&) noexcept = default;
Writer::~Writer() = default;

Writer Writer::create(const std::string& base_name, const WriterOptions& options) {
  using namespace detail;
  const std::string prefix = kPrefix;
  if (base_name.size() <= prefix.size() || base_name.compare(0, prefix.size(), prefix) != 0 ||
      base_name.size() > 200 || !std::all_of(base_name.begin(), base_name.end(), valid_name_char)) {
    throw Error(Errc::invalid_argument,
                "Writer: bad base name '" + base_name + "' (needs prefix " + prefix +
                    ", <= 200 chars of [A-Za-z0-9_.-])");
  }
  if (options.slot_count < 2 || options.slot_count > kMaxSlotCount) {
    throw Error(Errc::invalid_argument, "Writer: slot_count must be in [2, 65535]");
  }
  if (options.max_subscribers < 1 || options.max_subscribers > kMaxSubscribersLimit) {
    throw Error(Errc::invalid_argument, "Writer: max_subscribers must be in [1, 4096]");
  }
  if (options.max_message_size == 0 || options.max_message_size > kMaxSlotSize ||
      options.initial_slot_size > options.max_message_size) {
    throw Error(Errc::invalid_argument,
                "Writer: need 0 < initial_slot_size <= max_message_size <= 2^40");
  }
  if (options.keep >= options.slot_count) {
    throw Error(Errc::invalid_argument,
                "Writer: keep (" + std::to_string(options.keep) +
                    ") must be < slot_count (" + std::to_string(options.slot_count) +
                    "): one slot stays free for the message being written");
  }
  // O_EXCL covers one name; a live Writer of the same base may be at a later generation
  // (unless the caller vouches it cannot: WriterOptions::unique_base).
  for (const auto& n : options.unique_base ? std::vector<std::string>{} : list_shm(base_name + "_g")) {
    auto sg = split_generation(n);
    if (!sg || sg->first != base_name) continue;
    if (writer_lock_held(n)) {
      auto info = peek_segment(n, nullptr);
      throw Error(Errc::system, "Writer: base name " + base_name + " is in use by a live " +
                                    "Writer (pid " + std::to_string(info ? info->owner_pid : 0) +
                                    " in its pid namespace, " + n + ")");
    }
  }
  auto impl = std::make_unique<WriterImpl>();
  impl->base = base_name;
  impl->opt = options;
  impl->pid = static_cast<std::int32_t>(::getpid());
  impl->start_time = self_start_time();
  impl->pidns = self_pidns();
  const Geometry geo =
      make_geometry(options.slot_count, options.max_subscribers, initial_slot_size(options));
  impl->created_ns = monotonic_ns();
  impl->seg = create_segment(generation_name(base_name, 0), geo, 0, 0, impl->pid,
                             impl->start_time, impl->created_ns);
  impl->slot_seq.assign(geo.slot_count, kSlotEmpty);
  return Writer(std::move(impl));
}

WriteLoan Writer::loan(std::size_t size) {
  auto& w = *impl_;
  if (w.loan_out) {
    throw Error(Errc::invalid_argument, "Writer::loan: a loan is already outstanding");
  }
  if (size > w.opt.max_message_size) {
    throw Error(Errc::too_large, "Writer::loan: " + std::to_string(size) +
                                     " bytes > max_message_size " +
                                     std::to_string(w.opt.max_message_size));
  }
  if (w.seg->faulted()) w.grow(w.seg->geo.slot_size, true);  // truncated by someone else
  if (size > w.seg->geo.slot_size) w.grow(size);
  const auto s = w.acquire_slot();
  w.loan_out = true;
  if (!s) {
    if (w.scratch.size() < w.seg->geo.slot_size) w.scratch.resize(w.seg->geo.slot_size);
    w.loan_slot = detail::kScratchSlot;
    return WriteLoan(&w, detail::kScratchSlot, w.scratch.data(), w.seg->geo.slot_size);
  }
  w.loan_slot = *s;
  return WriteLoan(&w, *s, w.seg->payload(*s), w.seg->geo.slot_size);
}

std::uint64_t Writer::commit(WriteLoan&& loan, std::size_t size, std::uint64_t flags) {
  if (loan.writer_ != impl_.get()) {
    throw Error(Errc::invalid_argument, "Writer::commit: loan of another Writer (or empty)");
  }
  if (size > loan.capacity_) {
    throw Error(Errc::invalid_argument, "Writer::commit: size > loan capacity");
  }
  loan.writer_ = nullptr;
  return impl_->commit(loan.slot_, size, flags);
}

std::uint64_t Writer::write(const void* data, std::size_t size, std::uint64_t flags) {
  WriteLoan l = loan(size);
  if (size != 0) std::memcpy(l.data(), data, size);
  return commit(std::move(l), size, flags);
}

const std::string& Writer::segment_name() const { return impl_->seg->name; }

std::uint64_t Writer::published() const noexcept {
  return impl_->seg->first_global_seq + impl_->write_seq;
}

std::uint32_t Writer::live_readers() const noexcept {
  const auto& seg = *impl_->seg;
  const std::uint32_t hw =
      std::min(seg.hdr->sub_high_water.load(std::memory_order_acquire), seg.geo.max_subscribers);
  std::uint32_t n = 0;
  for (std::uint32_t i = 0; i < hw; ++i) n += detail::subscriber_alive(seg, i) ? 1 : 0;
  return n;
}

std::uint64_t Writer::dropped() const noexcept { return impl_->dropped; }

// Counts the current generation and the older ones still kept: a Reader registered in an
// older generation has not followed yet but will read this one's messages, so they must be
// written (counting only the current generation lost messages right after growth).
std::uint32_t Writer::registered_readers() const noexcept {
  auto count = [](const detail::Segment& seg) {
    const std::uint32_t hw =
        std::min(seg.hdr->sub_high_water.load(std::memory_order_acquire), seg.geo.max_subscribers);
    std::uint32_t n = 0;
    for (std::uint32_t i = 0; i < hw; ++i)
      if (detail::sub_state(seg.sub(i).state.load(std::memory_order_acquire)) ==
          detail::kSubActive) {
        ++n;
      }
    return n;
  };
  std::uint32_t n = count(*impl_->seg);
  for (const auto& old : impl_->old_gens) n += count(*old);
  return n;
}

void Writer::set_hot_slot(bool allowed) noexcept { impl_->hot_slot = allowed; }

}  // namespace lcmx::shm
