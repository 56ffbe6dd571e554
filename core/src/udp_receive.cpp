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
#include "lcmx/lcmtypes/envelope.hpp"
#include "lcmx_msgs/history_t.hpp"

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

// Serial number order (RFC 1982) of LCM's 32-bit sequence numbers: a comes before b.
bool serial_before(std::uint32_t a, std::uint32_t b) { return static_cast<std::int32_t>(a - b) < 0; }

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
      {
        std::lock_guard lock(recv_mu);
        refresh_routes();
        // A drain also expires partial messages past their reassembly timeout: with no datagram
        // arriving after them (a sender whose large messages never complete), nothing else would.
        drain_locked(true);
        check_group_drops(*local_group, local_drops, "host-local");
        if (vehicle_group) check_group_drops(*vehicle_group, vehicle_drops, "vehicle");
      }
      if (!stopped.load()) run_housekeeping();
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

void RuntimeImpl::drain_locked(bool handle_beacons) {
  if (handle_beacons) {
    // Beacons other threads drained first: they arrived before anything drained now.
    auto pending = std::move(forwarded);
    forwarded.clear();
    for (const auto& f : pending) {
      const udpm::Message m{f.channel, f.data, f.source, f.sequence, f.lost_before, nullptr};
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
        if (!handle_beacons && m.channel == discovery::kBeaconChannel) {
          // Beacons repeat every period: dropping some when the receive thread lags (or has
          // stopped) loses nothing for good, and keeps this bounded.
          if (stopped.load() || forwarded.size() >= 256) return;
          forwarded.push_back({scope, std::string(m.channel), {m.data.begin(), m.data.end()},
                               m.source, m.sequence, m.lost_before});
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
    // Loss accounting needs every beacon's sequence: decoded a second time (small, a few per
    // second per participant).
    if (auto b = discovery::decode_beacon(m.data)) settle_loss(scope, udpm::to_string(m.source), *b, m.lost_before);
    return;
  }
  const auto& group = vehicle ? vehicle_group : local_group;
  if (group->is_own(m.source)) return;  // our own, looped back
  if (m.channel == kHistoryChannel) {
    on_history(m);
    return;
  }
  const std::string source = udpm::to_string(m.source);
  std::uint32_t foreign_lost = 0;
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
    if (m.lost_before > 0) {
      // A participant's gap is settled at its next beacon (some of it may be beacons); a stock
      // LCM sender has no channel list: its loss cannot be given to a pair.
      if (participant != 0) loss_of(scope, source).pending += m.lost_before;
      else foreign_lost = m.lost_before;
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
      {  // keep last N: see on_history
        auto& src = st.udp_source(source, static_cast<std::uint64_t>(participant));
        if (src.replay_floor && serial_before(m.sequence, *src.replay_floor)) continue;
        if (!src.first_live) src.first_live = m.sequence;
      }
      targets.push_back({sub, match->stats});
    }
  }
  if (announce_pending.exchange(false)) {
    if (disco) disco->announce_now();
    if (disco_vehicle) disco_vehicle->announce_now();
  }
  emit(std::move(events));
  if (foreign_lost > 0 && !targets.empty()) log_foreign_loss(scope, source, foreign_lost);
  if (targets.empty()) return;
  // A reassembled message is handed over in its reassembly buffer; a single datagram's bytes
  // live in the socket's receive slot, reused by the next read: copied.
  std::shared_ptr<const void> owner = m.buffer;
  if (!owner) owner = make_bytes(m.data);
  const auto bytes = m.buffer ? m.data : std::span<const std::byte>(*std::static_pointer_cast<const Bytes>(owner));
  for (auto& [sub, stats] : targets) {
    if (sub->udp_inline && !sub->state->removed.load()) {
      RetainSource src;
      src.owner = owner;
      src.pair = stats.get();
      if (sub->udp_inline(RawMessage{sub->channel(), bytes, &src})) {
        stats->received.fetch_add(1, std::memory_order_relaxed);
        sub->delivered.fetch_add(1, std::memory_order_relaxed);
        continue;
      }
    }
    push_intra(*sub, IntraItem{owner, &raw_type_info(), stats, bytes});
  }
}

// Sends the queued keep-last-N replays (count_remote_locked). mu not held: each publisher's
// kept messages are read under mu (the publisher cannot go away meanwhile) and its
// publish_mu, then sent on the subscriber's group from this participant's socket.
void RuntimeImpl::send_replays() {
  std::vector<ReplayJob> jobs;
  {
    std::lock_guard lock(mu);
    jobs.swap(replay_jobs);
  }
  for (const auto& j : jobs) {
    lcmx_msgs::history_t h{};
    {
      std::lock_guard lock(mu);
      auto it = pubs.find(j.publisher);
      if (it == pubs.end()) continue;
      for (auto& k : it->second->kept_for_udp(j.vehicle)) {
        lcmx_msgs::history_message_t x{};
        x.sent = k.sequence ? 1 : 0;
        x.sequence = static_cast<std::int32_t>(k.sequence.value_or(0));
        x.data.assign(reinterpret_cast<const std::uint8_t*>(k.encoded->data()),
                      reinterpret_cast<const std::uint8_t*>(k.encoded->data()) + k.encoded->size());
        x.size = static_cast<std::int32_t>(x.data.size());
        h.messages.push_back(std::move(x));
      }
      h.channel = it->second->channel();
    }
    if (h.messages.empty()) continue;
    h.publisher_participant = static_cast<std::int64_t>(participant_id);
    h.publisher_endpoint = static_cast<std::int64_t>(j.publisher);
    h.subscriber_participant = j.participant;
    h.subscriber_endpoint = j.endpoint;
    h.num_messages = static_cast<std::int32_t>(h.messages.size());
    std::vector<std::byte> buf(static_cast<std::size_t>(h.getEncodedSize()));
    h.encode(buf.data(), 0, static_cast<int>(buf.size()));
    try {
      if (j.vehicle && vehicle_group)
        vehicle_group->publish(kHistoryChannel, buf);
      else if (!j.vehicle)
        local_group->publish_routed(kHistoryChannel, buf);
      spdlog::debug("lcmx: channel '{}': sent the last {} messages to a subscriber that matched late ({} group)",
                    h.channel, h.num_messages, j.vehicle ? "vehicle" : "host-local");
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: channel '{}': cannot send the last {} messages to a subscriber that matched late: {}",
                   h.channel, h.num_messages, e.what());
    }
  }
}

// A keep-last-N replay (send_replays) for one of our subscribers: its messages go to the
// subscriber's queue, oldest first, except those it received live (sent with a sequence
// number at or after the first it received live from the publisher's socket, known as a
// participant or not yet); live messages that arrive later, already delivered by the replay,
// are dropped (SubscriberState::UdpSource).
void RuntimeImpl::on_history(const udpm::Message& m) {
  lcmx_msgs::history_t h;
  if (!lcmtypes::decode(m.data, h)) return;  // malformed, or a hostile count: refused before sizing anything
  if (h.subscriber_participant != static_cast<std::int64_t>(participant_id)) return;
  std::shared_ptr<SubscriberCore> sub;
  std::shared_ptr<PairCounters> stats;
  std::vector<std::shared_ptr<const Bytes>> deliver;
  {
    std::lock_guard lock(mu);
    auto it = subs.find(static_cast<std::uint64_t>(h.subscriber_endpoint));
    if (it == subs.end() || it->second->channel() != h.channel) return;
    sub = it->second;
    auto& st = *sub->state;
    std::lock_guard l2(st.mu);
    std::shared_ptr<Match> match;
    for (auto& x : st.matches)  // as on_udp picks it: live messages carry no endpoint
      if (x->path == Path::udp && x->publisher_participant == static_cast<std::uint64_t>(h.publisher_participant)) {
        match = x;
        break;
      }
    if (!match) return;  // unmatched since: nothing to hand over
    stats = match->stats;
    // Per socket: what came live before the publisher was known (its beacon not yet here)
    // went to a match of the socket as an unknown LCM sender.
    auto& src = st.udp_source(udpm::to_string(m.source), static_cast<std::uint64_t>(h.publisher_participant));
    for (const auto& x : h.messages) {
      const auto seq = static_cast<std::uint32_t>(x.sequence);
      if (x.sent && src.first_live && !serial_before(seq, *src.first_live)) continue;  // had it live
      if (x.sent && (!src.replay_floor || serial_before(*src.replay_floor, seq + 1))) src.replay_floor = seq + 1;
      deliver.push_back(std::make_shared<const Bytes>(reinterpret_cast<const std::byte*>(x.data.data()),
                                                      reinterpret_cast<const std::byte*>(x.data.data()) + x.data.size()));
    }
  }
  for (auto& b : deliver) {
    const std::span<const std::byte> bytes(*b);
    push_intra(*sub, IntraItem{std::move(b), &raw_type_info(), stats, bytes});
  }
}

void RuntimeImpl::settle_loss(std::int8_t scope, const std::string& source, const lcmx_msgs::beacon_t& b,
                              std::uint32_t lost_before) {
  auto& s = loss_of(scope, source);
  struct ForgetOnGoodbye {  // at return: `s` is used until then
    decltype(source_loss)& map;
    std::pair<std::int8_t, std::string> key;
    bool goodbye;
    ~ForgetOnGoodbye() {
      if (goodbye) map.erase(key);
    }
  } forget{source_loss, {scope, source}, (b.flags & lcmx_msgs::beacon_t::FLAG_GOODBYE) != 0};
  s.pending += lost_before;
  if (s.last_beacon >= 0 && b.sequence > s.last_beacon) s.beacon_credit += static_cast<std::uint64_t>(b.sequence - s.last_beacon - 1);
  s.last_beacon = b.sequence;
  const std::uint64_t beacons = std::min(s.pending, s.beacon_credit);
  const std::uint64_t lost = s.pending - beacons;
  s.beacon_credit -= beacons;
  s.pending = 0;
  if (lost == 0) return;
  std::set<std::string> channels;
  for (const auto& e : b.endpoints)
    if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER) channels.insert(e.topic);
  std::vector<std::string> subscribed;  // its channels matched here over UDP
  {
    std::lock_guard lock(mu);
    for (auto& [id, sub] : subs) {
      if (!channels.count(sub->channel())) continue;
      auto& st = *sub->state;
      std::lock_guard l2(st.mu);
      for (auto& x : st.matches) {
        if (x->path != Path::udp || x->publisher_participant != static_cast<std::uint64_t>(b.participant_id)) continue;
        if (channels.size() == 1) x->stats->drops.fetch_add(lost, std::memory_order_relaxed);
        subscribed.push_back(sub->channel());
      }
    }
  }
  if (channels.size() == 1) {
    if (!subscribed.empty())
      spdlog::warn("lcmx: {} message(s) on channel '{}' from {} pid {} ({}) lost on the {} group; counted in its "
                   "subscribers' drops",
                   lost, *channels.begin(), b.process_name, b.pid, source,
                   scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE ? "vehicle" : "host-local");
    return;
  }
  if (subscribed.empty()) return;  // none of its channels is received here: nobody here lost
  s.unattributed += lost;
  const auto now = std::chrono::steady_clock::now();
  if (now - s.logged < std::chrono::seconds(5)) return;
  s.logged = now;
  std::string list;
  for (const auto& c : channels) list += (list.empty() ? "" : ", ") + c;
  spdlog::warn("lcmx: {} message(s) from {} pid {} ({}) lost on the {} group ({} so far); it sends several channels "
               "({}), so the loss cannot be given to one subscription (UDP sequence numbers are per socket)",
               lost, b.process_name, b.pid, source, scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE ? "vehicle" : "host-local",
               s.unattributed, list);
}

// Bounded: a sender that says goodbye is forgotten (settle_loss); one killed without a
// goodbye, or a stock LCM sender, stays until kMaxSources senders were seen, then all start
// over (their pending gaps, at most one beacon period's, and unattributed totals are lost).
RuntimeImpl::SourceLoss& RuntimeImpl::loss_of(std::int8_t scope, const std::string& source) {
  if (source_loss.size() >= kMaxSources && !source_loss.count({scope, source})) source_loss.clear();
  return source_loss[{scope, source}];
}

void RuntimeImpl::check_group_drops(const udpm::Group& group, GroupDrops& last, const char* which) {
  // Not kernel_dropped: the socket's drop count includes this participant's own datagrams,
  // which its socket filter drops by design (udpm/group.cpp drop_own_datagrams).
  const auto& c = group.counters();
  if (c.incomplete_dropped == last.incomplete && c.oversize_dropped == last.oversize) return;
  const auto now = std::chrono::steady_clock::now();
  if (now - last.logged < std::chrono::seconds(5)) return;  // a later check reports the sum
  spdlog::warn("lcmx: {} UDP group: {} incomplete message(s) dropped (fragments lost, e.g. a receive buffer too "
               "small: net.core.rmem_max) and {} over the reassembly limit ({} bytes) since the last report ({} / {} "
               "in all). A subscription counts such a loss only when its sender's next message arrives",
               which, c.incomplete_dropped - last.incomplete, c.oversize_dropped - last.oversize,
               group.config().max_reassembly_bytes, c.incomplete_dropped, c.oversize_dropped);
  last = {c.incomplete_dropped, c.oversize_dropped, now};
}

void RuntimeImpl::log_foreign_loss(std::int8_t scope, const std::string& source, std::uint32_t lost) {
  auto& s = loss_of(scope, source);
  s.unattributed += lost;
  const auto now = std::chrono::steady_clock::now();
  if (now - s.logged < std::chrono::seconds(5)) return;
  s.logged = now;
  spdlog::warn("lcmx: {} message(s) from LCM sender {} lost on the {} group ({} so far); a stock LCM sender "
               "announces no channel list, so the loss cannot be given to one subscription",
               lost, source, scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE ? "vehicle" : "host-local", s.unattributed);
}

}  // namespace lcmx::detail
