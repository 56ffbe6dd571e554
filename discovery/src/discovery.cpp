#include "lcmx/discovery/discovery.hpp"

#include <poll.h>
#include <sys/eventfd.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <set>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/discovery/identity.hpp"

namespace lcmx::discovery {

using Clock = std::chrono::steady_clock;

// Lease expiry (Impl::expire_leases) reads what is queued first; a check made this long after
// that read began (the process was stopped, or starved of a CPU, in between) reads again, at
// most kMaxReads times.
constexpr auto kStall = std::chrono::milliseconds(100);
constexpr int kMaxReads = 3;

#ifndef SYS_pidfd_open
#define SYS_pidfd_open 434
#endif

struct Discovery::Impl {
  Options options;
  LocalFn local;
  ChangeFn on_change;
  std::shared_ptr<udpm::Group> group;
  bool receive = true;  // false with a shared group: the owner calls deliver()
  int wake_fd = -1;  // eventfd: announce_now()/query()/stop() wake the thread
  std::atomic<bool> want_announce{true};
  std::atomic<bool> want_query{false};
  std::atomic<bool> stopping{false};
  std::thread thread;
  std::int64_t sequence = 0;
  std::atomic<std::uint64_t> self_id{0};  // our participant id, to ignore our own echo

  // Orders what on_change is told: taken around a change of the table *and* its callback, so
  // the callbacks see the changes in the table's order. Without it a beacon's "updated",
  // told by the receiving thread, could reach the owner after the discovery thread had told
  // "left" (lease expired, process exited): the owner then kept a participant the table no
  // longer had, for good (the runtime tried to open a dead publisher's segment forever).
  // Lock order: deliver_mutex, then mutex; on_change may take the owner's locks, so the owner
  // must never call into this Discovery's deliver() while holding a lock on_change takes.
  std::mutex deliver_mutex;
  mutable std::mutex mutex;  // guards peers, peer_bytes, table_bytes, counters, exited
  std::map<std::int64_t, Participant> peers;
  std::map<std::int64_t, std::size_t> peer_bytes;  // encoded size of each peer's beacon
  std::size_t table_bytes = 0;                      // their sum (Options::max_table_bytes)
  Counters counters;
  // Participants whose process was seen to exit (pidfd): their late beacons are ignored.
  // Bounded: the oldest are forgotten first.
  std::set<std::int64_t> exited;
  std::deque<std::int64_t> exited_order;

  // Process watches (discovery thread only): a pidfd per peer of this host in our pid
  // namespace, polled with the group; readable = the process exited.
  struct Watch {
    int fd = -1;           // -1: cannot be watched (other pid namespace, no pidfd): lease only
    std::int32_t pid = 0;
    std::int64_t start_time = 0;
  };
  std::map<std::int64_t, Watch> watches;
  static constexpr std::size_t kMaxWatches = 1024;  // pidfds open at most
  std::size_t open_watches = 0;
  const std::uint64_t own_pid_namespace = pid_namespace();
  const std::uint64_t own_start_time = process_start_time(static_cast<int>(::getpid()));
  std::atomic<bool> want_watch_sync{false};
  Clock::time_point last_malformed_log{};
  Clock::time_point last_refused_log{};
  Clock::time_point last_send_error_log{};  // discovery thread only

  Impl(Options o, LocalFn l, ChangeFn c)
      : options(std::move(o)), local(std::move(l)), on_change(std::move(c)),
        group(options.shared_group ? options.shared_group
                                   : std::make_shared<udpm::Group>(udpm::Group::open(options.group))),
        receive(!options.shared_group) {
    wake_fd = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    if (wake_fd < 0) throw std::runtime_error("discovery: eventfd failed");
  }
  ~Impl() {
    for (auto& [id, w] : watches)
      if (w.fd >= 0) ::close(w.fd);
    if (wake_fd >= 0) ::close(wake_fd);
  }

  // Under mutex: a participant leaves the table.
  void forget_bytes(std::int64_t id) {
    const auto it = peer_bytes.find(id);
    if (it == peer_bytes.end()) return;
    table_bytes -= it->second;
    peer_bytes.erase(it);
  }

  void wake() {
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(wake_fd, &one, sizeof one);
  }

  void send(std::int8_t flags) {
    lcmx_msgs::beacon_t b{};  // value-initialised: lcm-gen leaves scalars uninitialised
    if (options.observer) {
      b.participant_id = static_cast<std::int64_t>(self_id);
      b.pid = static_cast<std::int32_t>(::getpid());
      b.process_name = "lcmx-observer";
      b.num_nodes = 0;
      b.num_endpoints = 0;
    } else {
      b = local();
      self_id = static_cast<std::uint64_t>(b.participant_id);
    }
    b.version = kBeaconVersion;
    b.pid = static_cast<std::int32_t>(::getpid());
    b.start_time = static_cast<std::int64_t>(own_start_time);
    b.pid_namespace = static_cast<std::int64_t>(own_pid_namespace);
    b.sequence = ++sequence;
    b.flags = static_cast<std::int8_t>(b.flags | flags);
    b.lease_ms = static_cast<std::int32_t>(options.lease.count());
    b.scope = options.scope;
    b.timestamp_us = std::chrono::duration_cast<std::chrono::microseconds>(
                         std::chrono::system_clock::now().time_since_epoch())
                         .count();
    const auto bytes = encode_beacon(b);
    try {
      group->publish(kBeaconChannel, bytes);
      std::lock_guard lock(mutex);
      ++counters.beacons_sent;
    } catch (const std::exception& e) {
      // A link or interface that is down: keep trying every period, log at most every 5 s.
      const auto now = Clock::now();
      if (now - last_send_error_log > std::chrono::seconds(5)) {
        last_send_error_log = now;
        spdlog::warn("lcmx discovery: cannot send beacon (will keep trying): {}", e.what());
      }
    }
  }

  void on_datagram(const udpm::Message& m) {
    if (m.channel != kBeaconChannel) return;
    std::string why;
    auto b = decode_beacon(m.data, &why);
    if (!b) {
      bool log = false;
      {
        std::lock_guard lock(mutex);
        ++counters.malformed;
        const auto now = Clock::now();
        if (now - last_malformed_log > std::chrono::seconds(5)) {
          last_malformed_log = now;
          log = true;
        }
      }
      if (log) spdlog::warn("lcmx discovery: ignored a beacon: {}", why);
      return;
    }
    if (static_cast<std::uint64_t>(b->participant_id) == self_id) return;
    if (b->flags & lcmx_msgs::beacon_t::FLAG_QUERY) {
      if (!options.observer) want_announce = true;
    }
    if (b->flags & lcmx_msgs::beacon_t::FLAG_OBSERVER) return;

    Change change = Change::updated;
    Participant copy;
    std::string refused;  // why, when refused and to be logged
    std::lock_guard order(deliver_mutex);  // until on_change has been told
    {
      std::lock_guard lock(mutex);
      ++counters.beacons_received;
      if (exited.count(b->participant_id)) return;  // sent before its process exited
      auto it = peers.find(b->participant_id);
      if (b->flags & lcmx_msgs::beacon_t::FLAG_GOODBYE) {
        if (it == peers.end()) return;
        ++counters.goodbyes;
        copy = std::move(it->second);
        forget_bytes(it->first);
        peers.erase(it);
        change = Change::left;
      } else {
        if (it != peers.end() && b->sequence <= it->second.beacon.sequence && b->pid == it->second.beacon.pid)
          return;  // out-of-order or duplicated beacons from one sender: keep the newest
        const std::size_t bytes = m.data.size();
        const std::size_t old_bytes = it == peers.end() ? 0 : peer_bytes[it->first];
        if (it == peers.end() && peers.size() >= options.max_participants)
          refused = "the table holds max_participants (" + std::to_string(options.max_participants) + ")";
        else if (table_bytes - old_bytes + bytes > options.max_table_bytes)
          refused = "the table would exceed max_table_bytes (" + std::to_string(options.max_table_bytes) + ")";
        if (!refused.empty()) {
          ++counters.refused;
          const auto now = Clock::now();
          if (now - last_refused_log < std::chrono::seconds(5)) return;
          last_refused_log = now;
          refused = "refused a beacon of participant " + std::to_string(b->participant_id) + " (" +
                    b->process_name.substr(0, 64) + " pid " + std::to_string(b->pid) + "): " + refused + "; " +
                    std::to_string(counters.refused) + " refused so far";
        } else {
          if (it == peers.end()) {
            change = Change::joined;
            it = peers.emplace(b->participant_id, Participant{}).first;
          } else {
            change = Change::updated;
          }
          table_bytes += bytes - old_bytes;
          peer_bytes[it->first] = bytes;
          const auto max_lease = static_cast<std::int32_t>(std::min<std::int64_t>(options.max_lease.count(), INT32_MAX));
          if (b->lease_ms > max_lease) b->lease_ms = max_lease;
          it->second.beacon = std::move(*b);
          it->second.last_seen = Clock::now();
          copy = it->second;
        }
      }
    }
    if (!refused.empty()) {
      spdlog::warn("lcmx discovery: {}", refused);
      return;
    }
    // A newcomer learns of us at once, not up to a period later: we beacon now (one beacon
    // per newcomer heard; the newcomer, hearing us for the first time, answers once more,
    // and that answer is no news to anyone). Without this a process that starts beside a
    // quiet participant (a bridge, a server nobody matched yet) would not know of it for up
    // to one period: e.g. a publisher whose topic turns large would send it as UDP fragments
    // though a bridge runs on its host.
    // (deliver() and the discovery thread's loop send it.)
    if (change == Change::joined && !options.observer) want_announce = true;
    // A new peer to watch, or a watch to close: the discovery thread does it.
    if (watching() && change != Change::updated) {
      want_watch_sync = true;
      wake();
    }
    if (on_change) on_change(change, copy);
  }

  bool watching() const {
    return options.watch_processes && options.scope == lcmx_msgs::beacon_t::SCOPE_HOST &&
           !options.observer;
  }

  // Discovery thread. Opens a pidfd for every new peer in our pid namespace (checking its
  // start time, so a reused pid is never watched) and closes those of peers that left. A peer
  // whose process is already gone is declared gone now.
  void sync_watches() {
    if (!watching()) return;
    std::vector<std::tuple<std::int64_t, std::int32_t, std::int64_t, std::int64_t>> current;
    {
      std::lock_guard lock(mutex);
      for (const auto& [id, p] : peers)
        current.emplace_back(id, p.beacon.pid, p.beacon.start_time, p.beacon.pid_namespace);
    }
    std::set<std::int64_t> live;
    std::vector<std::int64_t> gone;
    for (const auto& [id, pid, start, pidns] : current) {
      live.insert(id);
      if (watches.count(id)) continue;
      Watch w;
      w.pid = pid;
      w.start_time = start;
      // Bounded: past kMaxWatches peers (a flood of spoofed beacons), the lease alone.
      if (open_watches < kMaxWatches && pid > 0 && start > 0 && pidns != 0 &&
          static_cast<std::uint64_t>(pidns) == own_pid_namespace) {
        const int fd = static_cast<int>(::syscall(SYS_pidfd_open, pid, 0));
        if (fd < 0 && errno == ESRCH) {
          gone.push_back(id);
        } else if (fd >= 0) {
          // After the open: a matching start time means the pidfd names that very process.
          if (process_start_time(pid) == static_cast<std::uint64_t>(start)) {
            w.fd = fd;
            ++open_watches;
          } else {
            ::close(fd);
            gone.push_back(id);
          }
        }
      }
      watches[id] = w;
    }
    for (auto it = watches.begin(); it != watches.end();) {
      if (live.count(it->first)) {
        ++it;
        continue;
      }
      if (it->second.fd >= 0) ::close(it->second.fd), --open_watches;
      it = watches.erase(it);
    }
    for (auto id : gone) process_exited(id);
  }

  // Discovery thread: the peer's process exited. Declares it gone at once.
  void process_exited(std::int64_t id) {
    if (auto it = watches.find(id); it != watches.end()) {
      if (it->second.fd >= 0) ::close(it->second.fd), --open_watches;
      watches.erase(it);
    }
    Participant p;
    std::lock_guard order(deliver_mutex);  // until on_change has been told
    {
      std::lock_guard lock(mutex);
      auto it = peers.find(id);
      if (it == peers.end()) return;
      p = std::move(it->second);
      forget_bytes(it->first);
      peers.erase(it);
      ++counters.exits_seen;
      if (exited.insert(id).second) {
        exited_order.push_back(id);
        if (exited_order.size() > 1024) {
          exited.erase(exited_order.front());
          exited_order.pop_front();
        }
      }
    }
    spdlog::info("lcmx discovery: participant {} ({} pid {}) exited", p.beacon.participant_id,
                 p.beacon.process_name, p.beacon.pid);
    if (on_change) on_change(Change::left, p);
  }

  // Under mutex: has any lease run out?
  bool lease_due(Clock::time_point now) const {
    for (const auto& [id, p] : peers)
      if (now - p.last_seen > std::chrono::milliseconds(std::max(p.beacon.lease_ms, 1))) return true;
    return false;
  }

  // Discovery thread, no lock held: every beacon queued now is read, from our own group or by
  // the owner (Options::drain_before_expiry).
  void drain_queued() {
    try {
      if (receive)
        group->drain([this](const udpm::Message& m) { on_datagram(m); });
      else if (options.drain_before_expiry)
        options.drain_before_expiry();
    } catch (const std::exception& e) {
      spdlog::warn("lcmx discovery: receive failed: {}", e.what());
    }
  }

  void expire_leases() {
    {
      std::lock_guard lock(mutex);
      if (!lease_due(Clock::now())) return;
    }
    std::vector<Participant> gone;
    std::unique_lock order(deliver_mutex, std::defer_lock);  // until on_change has been told
    for (int read = 1;; ++read) {
      // A lease has run out by the clock, but its beacons may be queued still: this process
      // did not run for a while (SIGSTOP, a frozen container) and resumed, or the receive
      // thread lags. Read them first (deliver_mutex not held: reading delivers); then only the
      // participants that really fell silent go.
      const auto read_at = Clock::now();
      drain_queued();
      order.lock();
      {
        std::lock_guard lock(mutex);
        const auto now = Clock::now();
        // Stopped or starved since the read began: the others' beacons of that time are queued
        // again, and `now` would hold that time against them. Read again; after kMaxReads, on a
        // machine that keeps this thread off a CPU that long, the leases decide.
        if (now - read_at <= kStall || read >= kMaxReads) {
          for (auto it = peers.begin(); it != peers.end();) {
            const auto lease = std::chrono::milliseconds(std::max(it->second.beacon.lease_ms, 1));
            if (now - it->second.last_seen > lease) {
              forget_bytes(it->first);
              gone.push_back(std::move(it->second));
              it = peers.erase(it);
              ++counters.leases_expired;
              want_watch_sync = true;
            } else {
              ++it;
            }
          }
          break;  // deliver_mutex stays held until on_change has been told
        }
      }
      order.unlock();
    }
    for (auto& p : gone) {
      spdlog::info("lcmx discovery: participant {} ({} pid {}) lease expired",
                   p.beacon.participant_id, p.beacon.process_name, p.beacon.pid);
      if (on_change) on_change(Change::left, p);
    }
  }

  Clock::time_point next_expiry() const {
    std::lock_guard lock(mutex);
    auto t = Clock::time_point::max();
    for (const auto& [id, p] : peers)
      t = std::min(t, p.last_seen + std::chrono::milliseconds(std::max(p.beacon.lease_ms, 1)) +
                          std::chrono::milliseconds(1));
    return t;
  }

  void run() {
    auto next_periodic = Clock::now();
    std::vector<pollfd> fds;
    std::vector<std::int64_t> watched;  // participant of fds[2 + i]
    while (!stopping.load()) {
      const auto now = Clock::now();
      if (!options.observer && (want_announce.exchange(false) || now >= next_periodic)) {
        send(0);
        next_periodic = Clock::now() + options.period;
      }
      if (want_query.exchange(false)) send(lcmx_msgs::beacon_t::FLAG_QUERY |
                                           lcmx_msgs::beacon_t::FLAG_OBSERVER);
      expire_leases();

      // Sleep until the next beacon, the next lease to expire, a datagram, or a wake-up.
      auto until = options.observer ? Clock::now() + std::chrono::seconds(1) : next_periodic;
      until = std::min(until, next_expiry());
      auto wait = std::chrono::ceil<std::chrono::milliseconds>(until - Clock::now());
      wait = std::clamp(wait, std::chrono::milliseconds(0), std::chrono::milliseconds(1000));
      fds.resize(2);
      fds[0] = {wake_fd, POLLIN, 0};
      fds[1] = {receive ? group->fd() : -1, POLLIN, 0};
      watched.clear();
      for (const auto& [id, w] : watches)
        if (w.fd >= 0) {
          fds.push_back({w.fd, POLLIN, 0});
          watched.push_back(id);
        }
      const int r = ::poll(fds.data(), fds.size(), static_cast<int>(wait.count()));
      if (r > 0 && (fds[0].revents & POLLIN)) {
        std::uint64_t v;
        [[maybe_unused]] auto n = ::read(wake_fd, &v, sizeof v);
      }
      if (r > 0 && (fds[1].revents & POLLIN)) drain_queued();  // our own group (receive)
      if (r > 0)
        for (std::size_t i = 2; i < fds.size(); ++i)
          if (fds[i].revents & (POLLIN | POLLHUP | POLLERR)) process_exited(watched[i - 2]);
      if (want_watch_sync.exchange(false)) sync_watches();
    }
    if (!options.observer) send(lcmx_msgs::beacon_t::FLAG_GOODBYE);
  }
};

Discovery::Discovery(Options options, LocalFn local, ChangeFn on_change)
    : impl_(std::make_unique<Impl>(std::move(options), std::move(local), std::move(on_change))) {
  if (impl_->options.observer) {
    impl_->self_id = random_participant_id();
    impl_->want_query = true;
  }
  impl_->thread = std::thread([this] { impl_->run(); });
}

Discovery::~Discovery() { stop(); }

void Discovery::announce_now() {
  impl_->want_announce = true;
  impl_->wake();
}

void Discovery::query() {
  impl_->want_query = true;
  impl_->wake();
}

void Discovery::deliver(const udpm::Message& message) {
  const bool wake = !impl_->options.observer && !impl_->want_announce.load();
  impl_->on_datagram(message);
  // A query or a newcomer asks us to beacon now: wake the thread if on_datagram set
  // want_announce.
  if (wake && impl_->want_announce.load()) impl_->wake();
}

void Discovery::stop() {
  if (!impl_ || !impl_->thread.joinable()) return;
  impl_->stopping = true;
  impl_->wake();
  impl_->thread.join();
}

std::vector<Participant> Discovery::participants() const {
  std::lock_guard lock(impl_->mutex);
  std::vector<Participant> out;
  out.reserve(impl_->peers.size());
  for (const auto& [id, p] : impl_->peers) out.push_back(p);
  return out;
}

Counters Discovery::counters() const {
  std::lock_guard lock(impl_->mutex);
  return impl_->counters;
}

const Options& Discovery::options() const { return impl_->options; }

}  // namespace lcmx::discovery
