#include <sched.h>
#include <spdlog/spdlog.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <map>

#include "internal.hpp"
#include "lcmx/shm/futex.hpp"

namespace lcmx {

const char* to_string(Path p) {
  switch (p) {
    case Path::intra: return "intra";
    case Path::shm: return "shm";
    case Path::udp: return "udp";
    case Path::bridge: return "bridge";
  }
  return "?";
}

const char* to_string(Event::Kind k) {
  switch (k) {
    case Event::Kind::type_mismatch: return "type_mismatch";
    case Event::Kind::publisher_matched: return "publisher_matched";
    case Event::Kind::publisher_unmatched: return "publisher_unmatched";
    case Event::Kind::participant_joined: return "participant_joined";
    case Event::Kind::participant_left: return "participant_left";
    case Event::Kind::error: return "error";
  }
  return "?";
}

namespace detail {

// ---------------------------------------------------------------- NodeImpl / executor

namespace {
// Set by run_once() when a fan-out commit woke this thread (see there); poll_one() yields
// once after the next shm callback.
thread_local bool t_fanout_yield = false;
}  // namespace

namespace {
std::atomic<std::uint64_t> g_next_node_uid{1};

// The kernel's struct sched_attr (SCHED_ATTR_SIZE_VER1). Declared here: <linux/sched/types.h>
// clashes with glibc's <sched.h>, and glibc 2.36 has no sched_setattr wrapper.
struct SchedAttr {
  std::uint32_t size;
  std::uint32_t sched_policy;
  std::uint64_t sched_flags;
  std::int32_t sched_nice;
  std::uint32_t sched_priority;
  std::uint64_t sched_runtime, sched_deadline, sched_period;
  std::uint32_t sched_util_min, sched_util_max;
};
static_assert(sizeof(SchedAttr) == 56, "SCHED_ATTR_SIZE_VER1");

// Asks for `slice` as the calling thread's scheduler slice (ExecutorOptions::slice). Keeps the
// thread's policy and nice value; leaves a thread under another policy than SCHED_OTHER or
// SCHED_BATCH alone. Returns "" when the kernel took it (read back), else why not.
std::string request_slice(std::chrono::microseconds slice) {
  SchedAttr a{};
  if (::syscall(SYS_sched_getattr, 0, &a, sizeof a, 0) != 0) return std::string("sched_getattr: ") + std::strerror(errno);
  if (a.sched_policy != SCHED_OTHER && a.sched_policy != SCHED_BATCH) return "the thread's policy is not SCHED_OTHER";
  const auto want = static_cast<std::uint64_t>(std::chrono::nanoseconds(slice).count());
  a.size = sizeof a;
  a.sched_flags = 0;
  a.sched_runtime = want;
  if (::syscall(SYS_sched_setattr, 0, &a, 0) != 0) return std::string("sched_setattr: ") + std::strerror(errno);
  SchedAttr b{};
  if (::syscall(SYS_sched_getattr, 0, &b, sizeof b, 0) != 0) return std::string("sched_getattr: ") + std::strerror(errno);
  if (b.sched_runtime != want) return "this kernel has no custom slices (Linux 6.12 or later)";
  return {};
}
}  // namespace

NodeImpl::NodeImpl(std::shared_ptr<RuntimeImpl> rt, std::string n, NodeOptions o)
    : runtime(std::move(rt)), name(std::move(n)), options(o), uid(g_next_node_uid.fetch_add(1)) {
  if (name.empty()) throw Error(Errc::invalid_argument, "node name is empty");
  if (options.executor.threads < 1)
    throw Error(Errc::invalid_argument, "node '" + name + "': executor.threads must be >= 1");
  const auto slice = options.executor.slice;
  if (slice.count() != 0 && (slice < std::chrono::microseconds(100) || slice > std::chrono::milliseconds(100)))
    throw Error(Errc::invalid_argument, "node '" + name + "': executor.slice must be 0 (the kernel's default) or " +
                                            "100 us .. 100 ms, not " + std::to_string(slice.count()) + " us");
}

NodeImpl::~NodeImpl() {
  stop();
  if (epoll_fd >= 0) ::close(epoll_fd);
  if (wake_fd >= 0) ::close(wake_fd);
}

void NodeImpl::start() {
  if (options.executor.kind != ExecutorKind::own_threads) return;
  // Each executor thread holds the node only while it runs run_once(): when the last other
  // owner lets go meanwhile (e.g. a callback drops the last handle), the node is destroyed
  // here, after run_once() returned, never under it; its destructor detaches this thread,
  // which then finds the node gone and ends.
  for (int i = 0; i < options.executor.threads; ++i)
    threads.emplace_back([weak = weak_from_this(), slice = options.executor.slice, name = name] {
      if (slice.count() > 0) {
        const auto why = request_slice(slice);
        if (!why.empty())
          spdlog::debug("lcmx: node '{}': executor slice of {} us not applied: {}", name, slice.count(), why);
      }
      for (;;) {
        const auto self = weak.lock();
        if (!self || self->stopping.load(std::memory_order_acquire)) return;
        try {
          self->run_once(std::chrono::seconds(1));
        } catch (const std::exception& e) {
          // Nothing may end an executor thread but stop(): report and carry on (after a
          // pause, so that a lasting fault does not spin a CPU).
          self->report_fault(std::string("executor: ") + e.what());
          std::this_thread::sleep_for(std::chrono::milliseconds(1));
        } catch (...) {
          self->report_fault("executor: unknown exception");
          std::this_thread::sleep_for(std::chrono::milliseconds(1));
        }
      }
    });
}

// Logs (at most once per 5 s per node) and emits an Event::Kind::error for a fault the
// executor survived. Never throws (a throwing on_event callback is logged).
void NodeImpl::report_fault(const std::string& what) noexcept {
  try {
    const auto now = std::chrono::steady_clock::now();
    {
      std::lock_guard lock(fault_mu);
      ++faults;
      if (last_fault_report != std::chrono::steady_clock::time_point{} &&
          now - last_fault_report < std::chrono::seconds(5))
        return;
      last_fault_report = now;
    }
    runtime->emit({Event{Event::Kind::error, "", "node '" + name + "': " + what}});  // logs it
  } catch (const std::exception& e) {
    spdlog::error("lcmx: node '{}': reporting a fault failed: {}", name, e.what());
  } catch (...) {
  }
}

void NodeImpl::stop() {
  stopping.store(true, std::memory_order_release);
  ring();
  for (auto& t : threads) {
    if (!t.joinable()) continue;
    if (t.get_id() == std::this_thread::get_id()) t.detach();  // last owner let go in a callback
    else t.join();
  }
  threads.clear();
}

void NodeImpl::ring() {
  // Dekker with run_once(): it increments `sleepers` and then re-reads `doorbell` before
  // sleeping; we bump `doorbell` and then read `sleepers` (both seq_cst), so either it sees
  // the new doorbell value or we see it sleeping and wake it.
  // The same holds for a thread in wait_udp() with `fd_sleepers`: it is woken by wake_fd.
  doorbell.fetch_add(1, std::memory_order_seq_cst);
  if (sleepers.load(std::memory_order_seq_cst) > 0) {
    shm::futex_wake_all_private(&doorbell);  // waited on as process_private (run_once)
    if (fd_sleepers.load(std::memory_order_seq_cst) > 0) {
      const std::uint64_t one = 1;
      [[maybe_unused]] auto n = ::write(wake_fd, &one, sizeof one);
    }
  }
}

// Waits in epoll for the node's wake_fd (ring) or a datagram on the runtime's UDP sockets,
// until `deadline` (at most 1 s). A datagram is drained here and dispatched to every
// subscriber's queue (ours and other nodes'), so the caller's next poll_all() runs our
// callbacks with no second wake-up. EPOLLEXCLUSIVE: one waiting thread is woken per datagram,
// executors before the runtime's receive thread.
bool NodeImpl::wait_udp(std::uint32_t bell, std::chrono::steady_clock::time_point deadline) {
  if (fd_waiter.exchange(true, std::memory_order_acquire)) return false;
  struct Release {
    std::atomic<bool>& f;
    ~Release() { f.store(false, std::memory_order_release); }
  } release{fd_waiter};
  if (epoll_fd < 0) {
    // wake_fd is written by ring() only while fd_sleepers > 0, which needs epoll_fd.
    wake_fd = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    const int ep = ::epoll_create1(EPOLL_CLOEXEC);
    epoll_event ev{};
    ev.events = EPOLLIN;
    ev.data.fd = wake_fd;
    if (wake_fd < 0 || ep < 0 || ::epoll_ctl(ep, EPOLL_CTL_ADD, wake_fd, &ev) != 0) {
      spdlog::warn("lcmx: node '{}': cannot wait on UDP sockets ({}); the receive thread "
                   "delivers", name, std::strerror(errno));
      if (ep >= 0) ::close(ep);
      return false;  // epoll_fd stays -1: tried again next time
    }
    try {
      runtime->add_udp_waiter(ep);
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: node '{}': {}", name, e.what());
    }
    epoll_fd = ep;
  }
  using Clock = std::chrono::steady_clock;
  const auto left = std::min<Clock::duration>(deadline - Clock::now(), std::chrono::seconds(1));
  const int ms = static_cast<int>(
      std::max<std::int64_t>(std::chrono::ceil<std::chrono::milliseconds>(left).count(), 0));
  sleepers.fetch_add(1, std::memory_order_seq_cst);
  fd_sleepers.fetch_add(1, std::memory_order_seq_cst);
  epoll_event evs[4];
  int n = 0;
  if (doorbell.load(std::memory_order_seq_cst) == bell) n = ::epoll_wait(epoll_fd, evs, 4, ms);
  fd_sleepers.fetch_sub(1, std::memory_order_seq_cst);
  sleepers.fetch_sub(1, std::memory_order_seq_cst);
  bool udp = false;
  for (int i = 0; i < n; ++i) {
    if (evs[i].data.fd == wake_fd) {
      std::uint64_t v;
      [[maybe_unused]] auto r = ::read(wake_fd, &v, sizeof v);
    } else {
      udp = true;
    }
  }
  if (udp) runtime->drain_udp();
  return true;
}

void NodeImpl::add(const std::shared_ptr<SubscriberCore>& sub) {
  {
    std::lock_guard lock(mu);
    subs.push_back(sub);
    subs_version.fetch_add(1);
  }
  ring();
}

void NodeImpl::remove(const SubscriberCore* sub) {
  {
    std::lock_guard lock(mu);
    std::erase_if(subs, [&](const auto& s) { return s.get() == sub; });
    subs_version.fetch_add(1);
  }
  ring();
}

void NodeImpl::refresh(std::vector<std::shared_ptr<SubscriberCore>>& local,
                       std::uint64_t& version) {
  const auto v = subs_version.load();
  if (v == version) return;
  std::lock_guard lock(mu);
  local = subs;
  version = subs_version.load();
}

// Takes the intra-process queue and refreshes the snapshot of matches, under st.mu. Out of
// line: the common shm wake-up (nothing queued, no match change) skips it and its deque.
// `busy` must be held.
[[gnu::noinline]] std::size_t NodeImpl::poll_intra(SubscriberCore& sub) {
  auto& st = *sub.state;
  std::deque<IntraItem> items;
  {
    std::lock_guard lock(st.mu);
    items.swap(st.queue);
    st.queued.store(false, std::memory_order_relaxed);
    if (st.snapshot_version != st.version.load(std::memory_order_relaxed)) {
      st.snapshot = st.matches;
      st.snapshot_version = st.version.load(std::memory_order_relaxed);
    }
  }
  std::size_t n = 0;
  while (!items.empty() && !st.removed.load()) {
    // Moved out first: the message is released as soon as its callback returns, so a
    // publisher reusing its object does not find lcmx still holding it.
    IntraItem item = std::move(items.front());
    items.pop_front();
    item.pair->received.fetch_add(1, std::memory_order_relaxed);
    if (sub.deliver_intra(item)) {
      sub.delivered.fetch_add(1, std::memory_order_relaxed);
      ++n;
    }
  }
  return n;
}

// Polls one subscriber: intra-process queue first, then each shm reader (bounded batch per
// reader so one busy publisher cannot starve the others). `busy` must be held.
std::size_t NodeImpl::poll_one(SubscriberCore& sub) {
  auto& st = *sub.state;
  std::size_t n = 0;
  st.running_on = std::this_thread::get_id();
  // `queued` and `version` are stored under st.mu (release / seq_cst RMW) after the queue or
  // the matches changed; these acquire loads see them, or the change is newer than this poll
  // and its ring() (doorbell, Dekker in ring()) makes the executor poll again.
  if (st.queued.load(std::memory_order_acquire) ||
      st.version.load(std::memory_order_acquire) != st.snapshot_version)
    n += poll_intra(sub);
  constexpr int kBatch = 64;
  for (auto& m : st.snapshot) {
    if (!m->reader) continue;
    for (int i = 0; i < kBatch && !st.removed.load(); ++i) {
      std::optional<shm::ReadSample> s;
      try {
        s = m->reader->take();
      } catch (const shm::Error& e) {
        spdlog::warn("lcmx: channel '{}': shared-memory read failed: {}", sub.channel(), e.what());
        break;
      }
      if (!s) break;
      m->stats->received.fetch_add(1, std::memory_order_relaxed);
      bool torn = false;
      if (sub.deliver_bytes({s->data(), s->size()}, &*s, &torn, m->stats.get())) {
        sub.delivered.fetch_add(1, std::memory_order_relaxed);
        ++n;
      }
      if (torn) ++m->torn;
      if (t_fanout_yield) {
        t_fanout_yield = false;
        ::sched_yield();
      }
    }
    m->stats->drops.store(m->reader->drops() + m->torn, std::memory_order_relaxed);
  }
  // Publishers that left: once everything they committed has been read and their writer is
  // gone (closed, or its process dead), forget them. A writer whose process lives on (e.g.
  // stopped past its lease) keeps its match registered: when it is back, the runtime revives
  // the match (sync_remote_locked), so nothing it commits meanwhile is lost uncounted.
  const auto over = [](const Match& m) {
    return m.retiring && m.reader && !m.reader->has_data() && !m.reader->writer_alive();
  };
  bool drained = false;
  for (auto& m : st.snapshot) drained = drained || over(*m);
  if (drained) {
    std::lock_guard lock(st.mu);
    std::erase_if(st.matches, [&](const auto& m) {
      if (!over(*m)) return false;
      st.retired_drops += m->stats->drops.load();
      return true;
    });
    ++st.version;
    st.matched_cv.notify_all();
  }
  st.running_on = std::thread::id{};
  return n;
}

std::size_t NodeImpl::poll_all(std::vector<std::shared_ptr<SubscriberCore>>& local) {
  std::size_t n = 0;
  for (auto& sub : local) {
    auto& st = *sub->state;
    if (st.removed.load() || st.busy.exchange(true, std::memory_order_acquire)) continue;
    try {
      n += poll_one(*sub);
    } catch (const std::exception& e) {
      spdlog::error("lcmx: node '{}', channel '{}': callback threw: {}", name, sub->channel(),
                    e.what());
    }
    st.busy.store(false, std::memory_order_release);
    st.busy.notify_all();
  }
  return n;
}

std::size_t NodeImpl::run_once(std::chrono::nanoseconds timeout) {
  using Clock = std::chrono::steady_clock;
  const auto start = Clock::now();
  const auto deadline = start + timeout;
  // Keyed by the node's unique id, not its address: a node destroyed and another allocated
  // at the same address must not inherit the first one's subscriber list and version.
  thread_local std::vector<std::shared_ptr<SubscriberCore>> local;
  thread_local std::uint64_t local_version = ~0ull;
  thread_local std::uint64_t local_owner = 0;
  if (local_owner != uid) {
    local.clear();
    local_version = ~0ull;
    local_owner = uid;
  }
  // Reused (no allocation per call); `armed` is emptied after every wait.
  thread_local std::vector<shm::WaitToken> tokens;
  thread_local std::vector<std::pair<SubscriberCore*, std::shared_ptr<Match>>> armed;

  for (;;) {
    const std::uint32_t bell = doorbell.load(std::memory_order_seq_cst);
    refresh(local, local_version);
    if (const auto n = poll_all(local); n > 0) {
      if (options.executor.wait == WaitStrategy::adaptive)
        last_work_ns.store(std::chrono::nanoseconds(Clock::now().time_since_epoch()).count(),
                           std::memory_order_relaxed);
      return n;
    }
    // After reading `bell`: an interrupt() after this check changes the doorbell, so the wait
    // below returns at once and the next pass sees it.
    if (interrupted.exchange(false, std::memory_order_seq_cst)) return 0;
    const auto now = Clock::now();
    if (now >= deadline || stopping.load(std::memory_order_acquire)) return 0;
    const auto& ex = options.executor;
    const bool spin =
        ex.wait == WaitStrategy::busy_poll ||
        (ex.wait == WaitStrategy::spin_then_block && now - start < ex.spin) ||
        (ex.wait == WaitStrategy::adaptive &&
         std::chrono::nanoseconds(now.time_since_epoch()).count() -
                 last_work_ns.load(std::memory_order_relaxed) <
             std::chrono::nanoseconds(ex.spin).count());
    if (spin) {
      // Does any subscriber of ours receive over UDP (from another host or a stock LCM
      // program)? Read from the snapshots, under `busy` like poll_one().
      bool udp = false;
      for (auto& sub : local) {
        auto& st = *sub->state;
        if (st.busy.exchange(true, std::memory_order_acquire)) continue;  // another thread has it
        for (auto& m : st.snapshot) udp = udp || (m->path == Path::udp && !m->reader);
        st.busy.store(false, std::memory_order_release);
        st.busy.notify_all();
      }
      if (udp) runtime->drain_udp(/*try_only=*/true);  // spinning covers UDP too
      if (ex.wait == WaitStrategy::adaptive) {
        // Never keep a runnable peer off this CPU (the publisher we wait for may be queued
        // behind us on this vCPU): give way between polls. If another thread ran meanwhile,
        // the CPU is contended and polling only queues us behind the others (a woken sleeper
        // runs sooner): sleep until the next message.
        const auto before = Clock::now();
        sched_yield();
        if (Clock::now() - before > ex.spin) last_work_ns.store(0, std::memory_order_relaxed);
      }
      continue;
    }

    // Block: doorbell (in-process messages, changes) + every shm reader's futex word.
    // A Reader is used by one thread at a time, so arm() and disarm() run with the
    // subscriber's `busy` held, like take(); `armed` keeps the matches alive meanwhile.
    // The same pass notes UDP subscribers (from the snapshots, under `busy` like poll_one).
    bool udp = false;
    tokens.clear();
    armed.clear();
    tokens.push_back({&doorbell, bell, /*process_private=*/true});
    for (auto& sub : local) {
      auto& st = *sub->state;
      if (st.busy.exchange(true, std::memory_order_acquire)) continue;  // another thread has it
      for (auto& m : st.snapshot) {
        if (m->reader) {
          tokens.push_back(m->reader->arm());
          armed.push_back({sub.get(), m});
        } else {
          udp = udp || m->path == Path::udp;
        }
      }
      st.busy.store(false, std::memory_order_release);
      st.busy.notify_all();
    }
    // UDP subscribers and no shm reader to wait for (futex_waitv cannot wait on sockets):
    // receive ourselves, one wake-up from the datagram to the callback.
    if (udp && armed.empty() && wait_udp(bell, deadline)) continue;
    sleepers.fetch_add(1, std::memory_order_seq_cst);
    bool ready = doorbell.load(std::memory_order_seq_cst) != bell;
    // A Reader backing off (a failed generation follow, a truncated file, a Writer seen
    // inside a slot probe) has no commit to wake it: wake up when it may be polled again.
    auto until = deadline;
    for (auto& [sub, m] : armed) {
      ready = ready || m->reader->has_data();
      if (const auto r = m->reader->retry_at(); r != Clock::time_point{}) until = std::min(until, r);
    }
    // The deadline may have passed since the check above: never hand wait_any a negative
    // timeout (which means forever).
    const auto left = std::min<Clock::duration>(until - Clock::now(), std::chrono::seconds(1));
    if (!ready && left > Clock::duration::zero()) {
      try {
        shm::wait_any(tokens, left);
      } catch (const std::exception& e) {
        // Still disarm below; the caller polls again (bounded by its deadline), after a
        // pause so that a lasting fault does not spin a CPU.
        report_fault(std::string("waiting for messages failed: ") + e.what());
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
    }
    sleepers.fetch_sub(1, std::memory_order_seq_cst);
    t_fanout_yield = false;
    for (auto& [sub, m] : armed) {
      auto& st = *sub->state;
      while (st.busy.exchange(true, std::memory_order_acquire)) st.busy.wait(true);
      // Woken by a commit that woke other readers too (other subscribers of the message):
      // after our first callback, yield once so that those sharing our CPU run theirs now
      // rather than after our bookkeeping and sleep (callback-time spread, paper's exp. 3).
      if (!ready && !t_fanout_yield && m->reader->armed_readers() > 1 && m->reader->has_data())
        t_fanout_yield = true;
      m->reader->disarm();
      st.busy.store(false, std::memory_order_release);
      st.busy.notify_all();
    }
    armed.clear();
  }
}

// ---------------------------------------------------------------- free functions

namespace {
// LCM's rules: 1 to 63 bytes, no NUL (the wire format ends the name with one).
void validate_channel(const std::string& channel) {
  if (channel.empty()) throw Error(Errc::invalid_argument, "channel name is empty");
  if (channel.size() > kMaxChannelLength)
    throw Error(Errc::channel_too_long, "channel '" + channel + "' is " +
                                            std::to_string(channel.size()) +
                                            " bytes; LCM allows at most 63");
  if (channel.find('\0') != std::string::npos)
    throw Error(Errc::invalid_argument, "channel name contains a NUL byte");
}
}  // namespace

std::shared_ptr<PublisherCore> create_publisher(NodeImpl& node, std::string channel,
                                                const TypeInfo& type, PublisherOptions options) {
  validate_channel(channel);
  auto pub = std::make_shared<PublisherImpl>(node.shared_from_this(), std::move(channel), type,
                                             options);
  node.runtime->add_publisher(pub.get());
  return pub;
}

void add_subscriber(NodeImpl& node, const std::shared_ptr<SubscriberCore>& sub) {
  validate_channel(sub->channel());
  sub->state = std::make_shared<SubscriberState>();
  sub->state->node = node.shared_from_this();
  sub->state->node_name = node.name;
  sub->state->since_ns = sub->options().since == std::chrono::steady_clock::time_point{}
                            ? shm::monotonic_ns()
                            : static_cast<std::uint64_t>(std::chrono::duration_cast<std::chrono::nanoseconds>(
                                                             sub->options().since.time_since_epoch())
                                                             .count());
  sub->id = node.runtime->new_endpoint_id();
  node.add(sub);
  node.runtime->add_subscriber(sub);
}

void remove_subscriber(const std::shared_ptr<SubscriberCore>& sub) {
  auto& st = *sub->state;
  st.removed.store(true);
  auto node = st.node;
  if (node) {
    node->runtime->remove_subscriber(sub.get());
    node->remove(sub.get());
  }
  // Wait for a callback of this subscriber running on another thread to finish.
  if (st.running_on.load() != std::this_thread::get_id()) {
    while (st.busy.load(std::memory_order_acquire)) st.busy.wait(true);
  }
  std::lock_guard lock(st.mu);
  st.queue.clear();
  st.queued.store(false, std::memory_order_relaxed);
}

SubscriberStats subscriber_stats(const SubscriberCore& core) {
  SubscriberStats s;
  s.delivered = core.delivered.load();
  s.decode_errors = core.decode_errors.load();
  auto& st = *core.state;
  std::lock_guard lock(st.mu);
  s.drops = st.retired_drops;
  for (const auto& m : st.matches) {
    if (m->retiring) {
      s.drops += m->stats->drops.load();
      continue;
    }
    PairStats p;
    p.publisher_participant = m->publisher_participant;
    p.publisher_endpoint = m->publisher_endpoint;
    p.path = m->path;
    p.received = m->stats->received.load();
    p.drops = m->stats->drops.load();
    s.drops += p.drops;
    s.publishers.push_back(p);
  }
  s.errors = st.errors;
  return s;
}

bool wait_for_publishers(const SubscriberCore& core, std::size_t n,
                         std::chrono::milliseconds timeout) {
  auto& st = *core.state;
  std::unique_lock lock(st.mu);
  return st.matched_cv.wait_for(lock, timeout, [&] { return st.matches.size() >= n; });
}

// ---------------------------------------------------------------- raw subscriber

RawSubscriberCore::RawSubscriberCore(std::string channel, SubscriberOptions o,
                                     std::function<void(const RawMessage&)> cb,
                                     const TypeInfo& type)
    : SubscriberCore(std::move(channel), type, o), cb_(std::move(cb)) {
  if (!cb_) throw Error(Errc::invalid_argument, "subscribe_raw: empty callback");
}

bool RawSubscriberCore::deliver_intra(const IntraItem& item) {
  RetainSource src;
  src.pair = item.pair.get();
  if (item.type->carries_bytes()) {
    src.owner = item.object;  // retain() shares the publisher's (or UDP receiver's) buffer
    return deliver(item.bytes, src, nullptr, nullptr);
  }
  // A typed publisher in this process: encode for the raw subscriber.
  scratch_.resize(item.type->encoded_size(item.object.get()));
  item.type->encode(item.object.get(), scratch_.data(), scratch_.size());
  return deliver(scratch_, src, nullptr, nullptr);
}

// Zero-copy: the callback reads the slot itself, so intact() is checked before (a torn view
// is withheld) and after it (the slot was rewritten or truncated during the callback: it may
// have read a torn view; delivered, and counted as a drop). After a retain() the sample lives
// on as a DetachedSample: the check after the callback is made on that.
bool RawSubscriberCore::deliver_bytes(std::span<const std::byte> bytes, shm::ReadSample* sample,
                                      bool* torn, const PairCounters* pair) {
  RetainSource src;
  src.sample = sample;
  src.pair = pair;
  return deliver(bytes, src, sample, torn);
}

bool RawSubscriberCore::deliver(std::span<const std::byte> bytes, RetainSource& src,
                                shm::ReadSample* sample, bool* torn) {
  if (sample != nullptr && !sample->intact()) {
    if (torn != nullptr) *torn = true;
    return false;
  }
  cb_(RawMessage{channel(), bytes, &src});
  if (src.copies != 0) copies_.fetch_add(src.copies, std::memory_order_relaxed);
  if (sample != nullptr && torn != nullptr) {
    const bool ok = src.detached ? src.detached->intact() : sample->intact();
    if (!ok) *torn = true;
  }
  return true;
}

const TypeInfo& raw_type_info() {
  static const TypeInfo info{"", 0, nullptr, nullptr};
  return info;
}

const TypeInfo& announced_type_info(const std::string& name, std::int64_t fingerprint) {
  static std::mutex mu;
  static std::map<std::pair<std::string, std::int64_t>, std::unique_ptr<TypeInfo>> interned;
  std::lock_guard lock(mu);
  auto& slot = interned[{name, fingerprint}];
  if (!slot) slot = std::make_unique<TypeInfo>(TypeInfo{name, fingerprint, nullptr, nullptr});
  return *slot;
}

void remove_channel_subscription(const std::shared_ptr<ChannelSubscriptionCore>& core) {
  for (auto& sub : core->node->runtime->remove_channel_subscription(core.get()))
    remove_subscriber(sub);
  core->node->runtime->changed();  // the beacon's FLAG_CHANNELS may go
}

std::vector<std::pair<std::string, SubscriberStats>> channel_subscription_stats(
    const ChannelSubscriptionCore& core) {
  std::vector<std::pair<std::string, SubscriberStats>> out;
  for (auto& [channel, sub] : core.node->runtime->channel_children(core))
    out.emplace_back(channel, subscriber_stats(*sub));
  return out;
}

std::uint64_t channel_subscription_refused(const ChannelSubscriptionCore& core) {
  return core.node->runtime->channel_refused(core);
}

}  // namespace detail

// ---------------------------------------------------------------- Node

Node::~Node() = default;

RawPublisher Node::advertise_raw(std::string channel, PublisherOptions options) {
  return RawPublisher(
      detail::create_publisher(*impl_, std::move(channel), detail::raw_type_info(), options));
}

RawSubscriber Node::subscribe_raw(std::string channel,
                                  std::function<void(const RawMessage&)> callback,
                                  SubscriberOptions options) {
  auto core = std::make_shared<detail::RawSubscriberCore>(std::move(channel), options,
                                                          std::move(callback));
  detail::add_subscriber(*impl_, core);
  return RawSubscriber(std::move(core));
}

RawSubscriber Node::subscribe_raw(std::string channel, const std::string& type_name,
                                  std::int64_t fingerprint,
                                  std::function<void(const RawMessage&)> callback,
                                  SubscriberOptions options) {
  auto core = std::make_shared<detail::RawSubscriberCore>(
      std::move(channel), options, std::move(callback),
      detail::announced_type_info(type_name, fingerprint));
  detail::add_subscriber(*impl_, core);
  return RawSubscriber(std::move(core));
}

RawPublisher Node::advertise_raw(std::string channel, const std::string& type_name,
                                 std::int64_t fingerprint, PublisherOptions options) {
  return RawPublisher(detail::create_publisher(
      *impl_, std::move(channel), detail::announced_type_info(type_name, fingerprint), options));
}

ChannelSubscription Node::subscribe_channels(std::function<bool(const std::string&)> filter,
                                             std::function<void(const RawMessage&)> callback,
                                             SubscriberOptions options, std::size_t max_channels) {
  if (!filter || !callback)
    throw Error(Errc::invalid_argument, "subscribe_channels: empty filter or callback");
  auto core = std::make_shared<detail::ChannelSubscriptionCore>();
  core->filter = std::move(filter);
  core->callback = std::make_shared<const std::function<void(const RawMessage&)>>(std::move(callback));
  core->options = options;
  core->max_channels = max_channels;
  core->node = impl_;
  core->since_ns = shm::monotonic_ns();
  impl_->runtime->add_channel_subscription(core);
  return ChannelSubscription(std::move(core));
}

std::size_t Node::spin_once(std::chrono::nanoseconds timeout) {
  if (impl_->options.executor.kind != ExecutorKind::manual)
    throw Error(Errc::invalid_argument,
                "spin_once on node '" + impl_->name + "' which runs its own executor threads");
  return impl_->run_once(timeout);
}

const std::string& Node::name() const { return impl_->name; }

}  // namespace lcmx

namespace lcmx {

std::optional<RetainedBytes> RawMessage::retain_zero_copy() const noexcept {
  if (source == nullptr) return std::nullopt;
  auto& src = *source;
  if (src.detached) return RetainedBytes{data, src.detached, true};  // retained before
  if (src.owner) return RetainedBytes{data, src.owner, true};
  if (src.sample != nullptr) {
    if (auto d = src.sample->detach()) {
      try {
        src.detached = std::make_shared<const shm::DetachedSample>(std::move(*d));
      } catch (const std::bad_alloc&) {
        return std::nullopt;  // *d (destroyed here) gave the pin back
      }
      return RetainedBytes{data, src.detached, true};
    }
  }
  return std::nullopt;
}

std::optional<bool> RawMessage::published_large() const noexcept {
  if (source == nullptr || source->sample == nullptr) return std::nullopt;
  const std::uint64_t f = source->sample->flags();  // kept by a detached (retained) sample's shell too
  if ((f & detail::PublisherImpl::kSlotClassSaid) == 0) return std::nullopt;
  return (f & detail::PublisherImpl::kSlotLarge) != 0;
}

RetainedBytes RawMessage::retain() const {
  if (auto r = retain_zero_copy()) return std::move(*r);
  if (source != nullptr && source->copy) {
    return {{source->copy->data(), source->copy->size()}, source->copy, false};
  }
  // No source (a RawMessage made by hand), encoded bytes, or every detachable pin held: copy.
  auto copy = std::make_shared<const detail::Bytes>(data.begin(), data.end());
  std::span<const std::byte> view(copy->data(), copy->size());
  if (source != nullptr) {
    source->copy = copy;
    ++source->copies;
  }
  return {view, std::move(copy), false};
}

}  // namespace lcmx
