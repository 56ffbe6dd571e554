// UDP receive (docs/ARCHITECTURE.md "UDP receive"): the receive thread and idle executors
// drain the group sockets and dispatch datagrams to the discovery of their scope or to the
// subscribers' queues.
#include <arpa/inet.h>
#include <ifaddrs.h>
#include <netinet/in.h>
#include <spdlog/spdlog.h>
#include <sys/epoll.h>
#include <unistd.h>

#include <cstring>

#include "internal.hpp"
#include "lcmx/discovery/beacon_codec.hpp"

namespace lcmx::detail {

// This host's IPv4 addresses, network order (empty if getifaddrs fails).
std::set<std::uint32_t> local_addresses() {
  std::set<std::uint32_t> out;
  ifaddrs* list = nullptr;
  if (::getifaddrs(&list) != 0) return out;
  for (ifaddrs* i = list; i != nullptr; i = i->ifa_next)
    if (i->ifa_addr != nullptr && i->ifa_addr->sa_family == AF_INET)
      out.insert(reinterpret_cast<const sockaddr_in*>(i->ifa_addr)->sin_addr.s_addr);
  ::freeifaddrs(list);
  return out;
}

// The LCM encoding starts with the type's fingerprint, big-endian.
bool fingerprint_is(std::span<const std::byte> data, std::int64_t fingerprint) {
  if (data.size() < 8) return false;
  std::uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | std::to_integer<std::uint8_t>(data[i]);
  return static_cast<std::int64_t>(v) == fingerprint;
}

// The UDP receive thread: beacons go to discovery, messages to subscribers' queues. An idle
// node executor with UDP matches waits on the same sockets (NodeImpl::wait_udp) and is woken
// first, so it receives and runs its callbacks with no second wake-up; this thread gets the
// datagrams that arrive while no executor waits, and the beacons executors drained.
void RuntimeImpl::receive_loop() {
  while (!stopped.load()) {
    epoll_event evs[4];
    const int n = ::epoll_wait(rx_epoll, evs, 4, 1000);
    if (std::chrono::steady_clock::now() - routes_checked >= std::chrono::seconds(1)) {
      std::lock_guard lock(recv_mu);
      refresh_routes();
    }
    if (n <= 0) continue;
    bool owner_event = false;
    for (int i = 0; i < n; ++i) {
      if (evs[i].data.fd == rx_wake_fd) {
        std::uint64_t v;
        [[maybe_unused]] auto r = ::read(rx_wake_fd, &v, sizeof v);
      }
      if (owner_watch && evs[i].data.fd == owner_watch->fd()) owner_event = true;
    }
    if (stopped.load()) break;
    if (owner_event) on_owner_death();
    std::lock_guard lock(recv_mu);
    drain_locked(true);
  }
}

bool RuntimeImpl::drain_udp(bool try_only) {
  std::unique_lock lock(recv_mu, std::defer_lock);
  if (try_only) {
    if (!lock.try_lock()) return false;
  } else {
    lock.lock();
  }
  drain_locked(false);
  return true;
}

void RuntimeImpl::drain_locked(bool rx_thread) {
  if (rx_thread) {
    // Beacons other threads drained first: they arrived before anything drained now.
    auto pending = std::move(forwarded);
    forwarded.clear();
    for (const auto& f : pending) {
      const udpm::Message m{f.channel, f.data, f.source, f.sequence};
      try {
        on_udp(f.scope, m);
      } catch (const std::exception& e) {
        spdlog::warn("lcmx: beacon handling failed: {}", e.what());
      }
    }
  }
  auto one = [&](udpm::Group& group, std::int8_t scope) {
    try {
      group.drain([&](const udpm::Message& m) {
        if (!rx_thread && m.channel == discovery::kBeaconChannel) {
          // Beacons repeat every period: dropping some when the receive thread lags (or has
          // stopped) loses nothing for good, and keeps this bounded.
          if (stopped.load() || forwarded.size() >= 256) return;
          forwarded.push_back({scope, std::string(m.channel), {m.data.begin(), m.data.end()},
                               m.source, m.sequence});
          const std::uint64_t v = 1;
          [[maybe_unused]] auto r = ::write(rx_wake_fd, &v, sizeof v);
          return;
        }
        on_udp(scope, m);
      });
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: UDP receive failed: {}", e.what());
    }
  };
  one(*local_group, lcmx_msgs::beacon_t::SCOPE_HOST);
  if (vehicle_group) one(*vehicle_group, lcmx_msgs::beacon_t::SCOPE_VEHICLE);
}

// Routes change (a laptop joins a network, a robot's DHCP comes late): stock programs started
// since then join and send where the group routes now. recv_mu held.
void RuntimeImpl::refresh_routes() {
  routes_checked = std::chrono::steady_clock::now();
  local_group->refresh();
  auto addresses = local_addresses();
  std::lock_guard lock(mu);
  if (!addresses.empty()) host_addresses = std::move(addresses);
}

// EPOLLEXCLUSIVE entries are woken in the order they were added to a socket's wait queue,
// skipping epoll sets nobody waits on; re-adding the receive thread's entries puts them last.
void RuntimeImpl::add_udp_waiter(int epfd) {
  std::lock_guard lock(rx_epoll_mu);
  if (rx_epoll < 0) return;
  for (const auto& g : {local_group, vehicle_group}) {
    if (!g) continue;
    epoll_event ev{};
    ev.events = EPOLLIN | EPOLLEXCLUSIVE;
    ev.data.fd = g->fd();
    if (epfd >= 0 && ::epoll_ctl(epfd, EPOLL_CTL_ADD, g->fd(), &ev) != 0)
      throw Error(Errc::transport, std::string("epoll_ctl: ") + std::strerror(errno));
    if (epfd >= 0) ::epoll_ctl(rx_epoll, EPOLL_CTL_DEL, g->fd(), nullptr);
    // A socket already readable wakes the receive thread at once (no datagram is stranded).
    if (::epoll_ctl(rx_epoll, EPOLL_CTL_ADD, g->fd(), &ev) != 0)
      throw Error(Errc::transport, std::string("epoll_ctl: ") + std::strerror(errno));
  }
}

// Exactly one path per pair: UDP messages from a participant of this host are dropped (its
// subscribers here read shared memory), from a matched participant of another host they go
// to the subscribers matched with it, and from senders that are not lcmx participants
// (stock LCM programs) to every subscriber of the channel.
void RuntimeImpl::on_udp(std::int8_t scope, const udpm::Message& m) {
  const bool vehicle = scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE;
  if (m.channel == discovery::kBeaconChannel) {
    (vehicle ? disco_vehicle : disco)->deliver(m);
    return;
  }
  const auto& group = vehicle ? vehicle_group : local_group;
  if (group->is_own(m.source)) return;  // our own, looped back
  const std::string source = udpm::to_string(m.source);
  std::shared_ptr<const Bytes> bytes;
  std::vector<std::pair<std::shared_ptr<SubscriberCore>, std::shared_ptr<PairCounters>>> targets;
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    if (host_sources.count(source)) return;  // a participant of this host: shm path
    if (!vehicle && host_ports.count(m.source.port_be) && host_addresses.count(m.source.address_be))
      return;  // its mirror, sent where the group routes (same port, another address of ours)
    if (!channel_subs.empty()) expand_locked(std::string(m.channel), events);
    std::int64_t participant = 0;
    if (vehicle) {
      auto it = vehicle_sources.find(source);
      if (it != vehicle_sources.end()) participant = it->second;
    } else if (auto it = neighbour_sources.find(source); it != neighbour_sources.end()) {
      participant = it->second;  // a neighbour (this network namespace, another /dev/shm)
    } else if (auto p = neighbour_ports.find(m.source.port_be);
               p != neighbour_ports.end() && host_addresses.count(m.source.address_be)) {
      participant = p->second;  // ... sent where the group routes (another address of ours)
    }
    for (auto& [id, sub] : subs) {
      if (sub->channel() != m.channel) continue;
      auto& st = *sub->state;
      std::lock_guard l2(st.mu);
      std::shared_ptr<Match> match;
      for (auto& x : st.matches) {
        if (x->path != Path::udp) continue;
        if (participant != 0 ? x->publisher_participant == static_cast<std::uint64_t>(participant)
                             : (x->foreign && x->publisher_endpoint == std::hash<std::string>{}(source))) {
          match = x;
          break;
        }
      }
      if (!match && participant != 0) continue;  // not matched (type mismatch, or not yet)
      if (!match && !sub->type().raw() && !fingerprint_is(m.data, sub->type().fingerprint)) {
        // A stock LCM sender of another type on this channel: not delivered, reported once.
        const std::string text = "type mismatch on channel '" + sub->channel() + "': LCM sender " +
                                 source + " sends another type than " + sub->type().name +
                                 "; not delivered";
        report_mismatch_locked(sub->id, 0, std::hash<std::string>{}(source), sub->channel(), text,
                               st.errors, events);
        continue;
      }
      if (!match) {
        match = std::make_shared<Match>();
        match->path = Path::udp;
        match->foreign = true;
        match->publisher_endpoint = std::hash<std::string>{}(source);
        st.matches.push_back(match);
        ++st.version;
        st.matched_cv.notify_all();
        spdlog::info("lcmx: channel '{}': receiving from LCM sender {} ({} group)", sub->channel(),
                     source, vehicle ? "vehicle" : "host-local");
      }
      targets.push_back({sub, match->stats});
    }
  }
  if (announce_pending.exchange(false)) {
    if (disco) disco->announce_now();
    if (disco_vehicle) disco_vehicle->announce_now();
  }
  emit(std::move(events));
  if (targets.empty()) return;
  bytes = make_bytes(m.data);
  for (auto& [sub, stats] : targets) push_intra(*sub, IntraItem{bytes, &raw_type_info(), stats});
}

}  // namespace lcmx::detail
