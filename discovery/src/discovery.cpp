#include "lcmx/discovery/discovery.hpp"

#include <poll.h>
#include <sys/eventfd.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <map>
#include <mutex>
#include <thread>

#include <spdlog/spdlog.h>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/discovery/identity.hpp"

namespace lcmx::discovery {

using Clock = std::chrono::steady_clock;

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

  mutable std::mutex mutex;  // guards peers, peer_bytes, table_bytes and counters
  std::map<std::int64_t, Participant> peers;
  std::map<std::int64_t, std::size_t> peer_bytes;  // encoded size of each peer's beacon
  std::size_t table_bytes = 0;                      // their sum (Options::max_table_bytes)
  Counters counters;
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
    {
      std::lock_guard lock(mutex);
      ++counters.beacons_received;
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
    if (on_change) on_change(change, copy);
  }

  void expire_leases() {
    std::vector<Participant> gone;
    {
      std::lock_guard lock(mutex);
      const auto now = Clock::now();
      for (auto it = peers.begin(); it != peers.end();) {
        const auto lease = std::chrono::milliseconds(std::max(it->second.beacon.lease_ms, 1));
        if (now - it->second.last_seen > lease) {
          forget_bytes(it->first);
          gone.push_back(std::move(it->second));
          it = peers.erase(it);
          ++counters.leases_expired;
        } else {
          ++it;
        }
      }
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
      pollfd fds[2] = {{wake_fd, POLLIN, 0}, {receive ? group->fd() : -1, POLLIN, 0}};
      const int r = ::poll(fds, 2, static_cast<int>(wait.count()));
      if (r > 0 && (fds[0].revents & POLLIN)) {
        std::uint64_t v;
        [[maybe_unused]] auto n = ::read(wake_fd, &v, sizeof v);
      }
      if (r > 0 && (fds[1].revents & POLLIN)) {
        try {
          group->drain([this](const udpm::Message& m) { on_datagram(m); });
        } catch (const std::exception& e) {
          spdlog::warn("lcmx discovery: receive failed: {}", e.what());
        }
      }
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
  // A query asks us to beacon now: wake the thread if on_datagram set want_announce.
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
