#include <arpa/inet.h>
#include <fnmatch.h>
#include <ifaddrs.h>
#include <netinet/in.h>
#include <poll.h>
#include <spdlog/cfg/env.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <set>
#include <utility>
#include <cstdlib>
#include <cstring>
#include <sstream>

#include "internal.hpp"
#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/discovery/identity.hpp"

namespace lcmx {
namespace detail {
namespace {
std::atomic<bool> g_runtime_alive{false};

std::string hex(std::uint64_t v) {
  std::ostringstream s;
  s << std::hex << v;
  return s.str();
}

bool compatible(std::int64_t a, std::int64_t b) { return a == 0 || b == 0 || a == b; }

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

// The port of "a.b.c.d:port", network order; 0 if there is none.
std::uint16_t port_of(const std::string& source) {
  const auto colon = source.rfind(':');
  if (colon == std::string::npos) return 0;
  const long port = std::strtol(source.c_str() + colon + 1, nullptr, 10);
  return port > 0 && port < 65536 ? htons(static_cast<std::uint16_t>(port)) : 0;
}
}  // namespace

RuntimeImpl::RuntimeImpl(RuntimeOptions o)
    : options(std::move(o)), participant_id(discovery::random_participant_id()),
      host(discovery::host_id()) {
  // The name tag mixes the pid namespace into the host id: processes of several pid
  // namespaces sharing /dev/shm may have the same pid, never the same names.
  const std::uint64_t pidns = discovery::pid_namespace();
  const std::uint64_t tag = (host ^ (pidns * 0x9e3779b97f4a7c15ull)) | 1;
  own_shm_prefix = std::string(shm::kPrefix) + hex(tag) + "_";
  shm_base_prefix = own_shm_prefix + std::to_string(::getpid()) + "_";
  for (const auto& glob : options.bridge_carry)
    if (glob.empty() || glob.size() > 255)
      throw Error(Errc::invalid_argument, "bridge_carry: a topic pattern must have 1..255 characters");
  carried = options.bridge_carry;
  for (const auto& glob : options.mirror_channels)
    if (glob.empty() || glob.size() > 255)
      throw Error(Errc::invalid_argument, "mirror_channels: a channel pattern must have 1..255 characters");
  if (options.reclaim_orphans) {
    // Only segments of this pid namespace (name tag): their owners' pids mean something here.
    const auto r = shm::reclaim_orphans(own_shm_prefix);
    if (r.removed > 0) spdlog::info("lcmx: removed {} shared-memory segments of dead processes", r.removed);
  }
}

RuntimeImpl::~RuntimeImpl() {
  shutdown();
  if (rx_wake_fd >= 0) ::close(rx_wake_fd);
}

bool fingerprint_is(std::span<const std::byte> data, std::int64_t fingerprint);

void RuntimeImpl::start_transports() {
  auto open_group = [](const std::string& what, const std::string& url) {
    try {
      auto cfg = udpm::parse_url(url);
      // Our own looped-back packets would only be dropped in on_udp(); dropping them in the
      // kernel spares a wake-up of the receive thread per message sent (it competed for a CPU
      // with the subscribers' threads: ~15 µs per small message on 2 vCPUs).
      cfg.receive_own = false;
      return std::make_shared<udpm::Group>(udpm::Group::open(cfg));
    } catch (const udpm::Error& e) {
      const auto code = e.code() == udpm::Error::Code::invalid_config ||
                                e.code() == udpm::Error::Code::no_such_interface
                            ? Errc::invalid_argument
                            : Errc::transport;
      throw Error(code, what + " '" + url + "': " + e.what());
    }
  };
  local_group = open_group("discovery_url", options.discovery_url);
  host_addresses = local_addresses();
  routes_checked = std::chrono::steady_clock::now();
  if (!options.vehicle_url.empty()) {
    if (options.vehicle_url.find("iface=") == std::string::npos)
      throw Error(Errc::invalid_argument, "vehicle_url '" + options.vehicle_url +
                                              "' names no interface: add &iface=<name>");
    vehicle_group = open_group("vehicle_url", options.vehicle_url);
  }
  rx_wake_fd = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (rx_wake_fd < 0) throw Error(Errc::transport, "eventfd failed");
  rx_epoll = ::epoll_create1(EPOLL_CLOEXEC);
  if (rx_epoll < 0) throw Error(Errc::transport, "epoll_create1 failed");
  epoll_event ev{};
  ev.events = EPOLLIN;
  ev.data.fd = rx_wake_fd;
  if (::epoll_ctl(rx_epoll, EPOLL_CTL_ADD, rx_wake_fd, &ev) != 0)
    throw Error(Errc::transport, "epoll_ctl failed");
  add_udp_waiter(-1);  // the receive thread's own registration

  std::weak_ptr<RuntimeImpl> weak = weak_from_this();
  auto make = [&](std::int8_t scope, std::shared_ptr<udpm::Group> group) {
    discovery::Options d;
    d.shared_group = std::move(group);
    d.scope = scope;
    d.period = options.beacon_period;
    d.lease = options.lease;
    return std::make_unique<discovery::Discovery>(
        d,
        [weak, scope] {
          auto self = weak.lock();
          return self ? self->build_beacon(scope) : lcmx_msgs::beacon_t{};
        },
        [weak, scope](discovery::Change c, const discovery::Participant& p) {
          if (auto self = weak.lock()) self->on_participant(scope, c, p);
        });
  };
  disco = make(lcmx_msgs::beacon_t::SCOPE_HOST, local_group);
  if (vehicle_group) disco_vehicle = make(lcmx_msgs::beacon_t::SCOPE_VEHICLE, vehicle_group);
  rx_thread = std::thread([this] { receive_loop(); });
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
    for (int i = 0; i < n; ++i)
      if (evs[i].data.fd == rx_wake_fd) {
        std::uint64_t v;
        [[maybe_unused]] auto r = ::read(rx_wake_fd, &v, sizeof v);
      }
    if (stopped.load()) break;
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
    std::int64_t participant = 0;
    if (vehicle) {
      auto it = vehicle_sources.find(source);
      if (it != vehicle_sources.end()) participant = it->second;
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
  emit(std::move(events));
  if (targets.empty()) return;
  bytes = make_bytes(m.data);
  for (auto& [sub, stats] : targets) push_intra(*sub, IntraItem{bytes, &raw_type_info(), stats});
}

// The LCM encoding starts with the type's fingerprint, big-endian.
bool fingerprint_is(std::span<const std::byte> data, std::int64_t fingerprint) {
  if (data.size() < 8) return false;
  std::uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | std::to_integer<std::uint8_t>(data[i]);
  return static_cast<std::int64_t>(v) == fingerprint;
}

bool RuntimeImpl::mirrored(const std::string& channel) const {
  if (options.mirror) return true;
  for (const auto& glob : options.mirror_channels)
    if (::fnmatch(glob.c_str(), channel.c_str(), 0) == 0) return true;
  return false;
}

TopicClass RuntimeImpl::class_of(const std::string& channel) const {
  if (auto it = options.topic_class.find(channel); it != options.topic_class.end()) return it->second;
  std::lock_guard lock(carried_mu);
  for (const auto& glob : carried)
    if (::fnmatch(glob.c_str(), channel.c_str(), 0) == 0) return TopicClass::large;
  return TopicClass::automatic;
}

void RuntimeImpl::shutdown() {
  if (stopped.exchange(true)) return;
  if (rx_thread.joinable()) {
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(rx_wake_fd, &one, sizeof one);
    rx_thread.join();
  }
  {
    std::lock_guard lock(rx_epoll_mu);
    if (rx_epoll >= 0) ::close(rx_epoll), rx_epoll = -1;
  }
  // rx_wake_fd stays open until the destructor: an executor may still drain until its node
  // stops (the beacons it would forward are dropped once stopped).
  if (disco_vehicle) disco_vehicle->stop();  // goodbyes
  if (disco) disco->stop();
  std::vector<std::shared_ptr<NodeImpl>> live;
  {
    std::lock_guard lock(mu);
    for (auto& w : nodes)
      if (auto n = w.lock()) live.push_back(std::move(n));
  }
  for (auto& n : live) n->stop();
  g_runtime_alive.store(false);
}

void RuntimeImpl::changed() {
  ++revision;
  if (disco) disco->announce_now();
  if (disco_vehicle) disco_vehicle->announce_now();
}

void RuntimeImpl::emit(std::vector<Event> events) {
  if (events.empty()) return;
  std::function<void(const Event&)> cb;
  {
    std::lock_guard lock(event_mu);
    cb = on_event;
  }
  for (const auto& e : events) {
    if (e.kind == Event::Kind::type_mismatch || e.kind == Event::Kind::error)
      spdlog::error("lcmx: {}", e.message);
    else
      spdlog::debug("lcmx: {}", e.message);
    // The user's callback runs on lcmx's threads: what it throws must not end them.
    try {
      if (cb) cb(e);
    } catch (const std::exception& x) {
      spdlog::error("lcmx: the on_event callback threw: {}", x.what());
    } catch (...) {
      spdlog::error("lcmx: the on_event callback threw");
    }
  }
}

void RuntimeImpl::add_node(const std::shared_ptr<NodeImpl>& node) {
  {
    std::lock_guard lock(mu);
    std::erase_if(nodes, [](const auto& w) { return w.expired(); });
    nodes.push_back(node);
  }
  changed();
}

void RuntimeImpl::report_mismatch_locked(std::uint64_t local_endpoint,
                                         std::uint64_t remote_participant,
                                         std::uint64_t remote_endpoint,
                                         const std::string& channel, const std::string& text,
                                         std::vector<std::string>& errors,
                                         std::vector<Event>& events) {
  if (!mismatches_reported.insert({local_endpoint, remote_participant, remote_endpoint}).second)
    return;
  errors.push_back(text);
  events.push_back({Event::Kind::type_mismatch, channel, text});
}

void RuntimeImpl::match_local_locked(PublisherImpl& pub, SubscriberCore& sub,
                                     std::vector<Event>& events) {
  if (pub.channel() != sub.channel()) return;
  if (options.bridge && !sub.options().from_bridges) return;  // our own republished messages
  if (!compatible(pub.type.fingerprint, sub.type().fingerprint)) {
    const std::string text = "type mismatch on channel '" + sub.channel() + "': publisher (node '" +
                             pub.node->name + "') has " + pub.type.name + ", subscriber (node '" +
                             sub.state->node_name + "') wants " + sub.type().name +
                             "; not matched";
    {
      std::lock_guard lock(sub.state->mu);
      report_mismatch_locked(sub.id, participant_id, pub.id, sub.channel(), text,
                             sub.state->errors, events);
    }
    report_mismatch_locked(pub.id, participant_id, sub.id, pub.channel(), text, pub.errors,
                           events);
    return;
  }
  auto m = std::make_shared<Match>();
  m->publisher_participant = participant_id;
  m->publisher_endpoint = pub.id;
  m->path = Path::intra;
  pub.add_intra(std::static_pointer_cast<SubscriberCore>(subs.at(sub.id)), m->stats);
  {
    std::lock_guard lock(sub.state->mu);
    sub.state->matches.push_back(m);
    ++sub.state->version;
    sub.state->matched_cv.notify_all();
  }
  events.push_back({Event::Kind::publisher_matched, sub.channel(),
                    "channel '" + sub.channel() + "': node '" + sub.state->node_name +
                        "' receives from node '" + pub.node->name + "' (intra)"});
}

// Brings one local subscriber's shm matches in line with what the other participants of
// this host publish: opens readers for new publishers, drops those that went away.
void RuntimeImpl::sync_remote_locked(SubscriberCore& sub, std::vector<Event>& events) {
  auto& st = *sub.state;
  std::set<std::pair<std::uint64_t, std::uint64_t>> wanted;
  std::vector<std::shared_ptr<Match>> added;
  struct Candidate {
    const lcmx_msgs::beacon_t* b;
    const lcmx_msgs::endpoint_t* e;
    Path path;
  };
  std::vector<Candidate> candidates;
  for (const auto* scope_map : {&remotes, &vehicle_remotes})
  for (const auto& [pid, b] : *scope_map) {
    const Path path = scope_map == &remotes ? Path::shm : Path::udp;
    const bool from_bridge = (b.flags & lcmx_msgs::beacon_t::FLAG_BRIDGE) != 0;
    if (from_bridge && !sub.options().from_bridges) continue;
    for (const auto& e : b.endpoints) {
      if (e.kind != lcmx_msgs::endpoint_t::KIND_PUBLISHER || e.topic != sub.channel()) continue;
      if (!compatible(e.fingerprint, sub.type().fingerprint)) {
        const std::string text = "type mismatch on channel '" + sub.channel() +
                                 "': publisher (process " + b.process_name + " pid " +
                                 std::to_string(b.pid) + ", node '" + e.node + "') has " +
                                 e.type_name + ", subscriber (node '" + st.node_name +
                                 "') wants " + sub.type().name + "; not matched";
        std::lock_guard lock(st.mu);
        report_mismatch_locked(sub.id, static_cast<std::uint64_t>(b.participant_id),
                               static_cast<std::uint64_t>(e.id), sub.channel(), text, st.errors,
                               events);
        continue;
      }
      if (path == Path::shm && e.shm_segment.empty()) continue;  // bridges' segments too
      wanted.insert({static_cast<std::uint64_t>(b.participant_id), static_cast<std::uint64_t>(e.id)});
      candidates.push_back({&b, &e, path == Path::shm && from_bridge ? Path::bridge : path});
    }
  }
  std::lock_guard lock(st.mu);
  const auto before = st.matches.size();
  std::size_t revived = 0;
  std::vector<std::shared_ptr<Match>> removed;
  std::erase_if(st.matches, [&](const std::shared_ptr<Match>& m) {
    if (m->path == Path::intra || m->foreign || m->retiring) return false;
    if (wanted.count({m->publisher_participant, m->publisher_endpoint})) return false;
    removed.push_back(m);
    if (m->reader) {  // keep it until the executor has read what was committed
      m->retiring = true;
      return false;
    }
    return true;
  });
  for (const auto& [b, e, path] : candidates) {
    const auto key = std::make_pair(static_cast<std::uint64_t>(b->participant_id),
                                    static_cast<std::uint64_t>(e->id));
    const auto same = [&](const std::shared_ptr<Match>& m) {
      return m->publisher_participant == key.first && m->publisher_endpoint == key.second;
    };
    if (std::any_of(st.matches.begin(), st.matches.end(),
                    [&](const auto& m) { return !m->retiring && same(m); }))
      continue;
    // The publisher is back (e.g. it was stopped past its lease): its retiring match is still
    // registered in its segment and has every message since, so it carries on. A second
    // Reader would deliver what the first still holds twice, and lose what was committed
    // between the two.
    if (auto it = std::find_if(st.matches.begin(), st.matches.end(),
                               [&](const auto& m) { return m->retiring && same(m); });
        it != st.matches.end()) {
      (*it)->retiring = false;
      std::erase_if(removed, [&](const auto& m) { return m == *it; });
      ++revived;
      events.push_back({Event::Kind::publisher_matched, sub.channel(),
                        "channel '" + sub.channel() + "': node '" + st.node_name +
                            "' receives again from process " + b->process_name + " pid " +
                            std::to_string(b->pid) + " node '" + e->node + "' (" +
                            to_string((*it)->path) + ")"});
      continue;
    }
    auto m = std::make_shared<Match>();
    m->publisher_participant = key.first;
    m->publisher_endpoint = key.second;
    m->path = path;
    if (path == Path::shm || path == Path::bridge) {
      const auto fkey = std::make_tuple(sub.id, key.first, key.second);
      try {
        m->reader = std::make_unique<shm::Reader>(shm::Reader::open(e->shm_segment));
        open_failures.erase(fkey);
      } catch (const shm::Error& err) {
        // The publisher may be gone or be creating a new generation: retried on its next
        // beacon. Failing on several beacons in a row is no transient: an error Event, once.
        spdlog::debug("lcmx: channel '{}': cannot open {} yet: {}", sub.channel(), e->shm_segment,
                      err.what());
        if (open_failures.size() >= 4096) open_failures.clear();  // bounded
        if (++open_failures[fkey] == kOpenFailuresReported)
          events.push_back({Event::Kind::error, sub.channel(),
                            "channel '" + sub.channel() + "': node '" + st.node_name +
                                "' cannot open the shared memory '" + e->shm_segment +
                                "' of process " + b->process_name + " pid " +
                                std::to_string(b->pid) + ": " + err.what() +
                                "; not matched (retried on its next beacons)"});
        continue;
      }
    }
    st.matches.push_back(m);
    events.push_back({Event::Kind::publisher_matched, sub.channel(),
                      "channel '" + sub.channel() + "': node '" + st.node_name +
                          "' receives from process " + b->process_name + " pid " +
                          std::to_string(b->pid) + " node '" + e->node + "' (" +
                          to_string(path) + ")"});
  }
  for (auto& m : removed)
    events.push_back({Event::Kind::publisher_unmatched, sub.channel(),
                      "channel '" + sub.channel() + "': node '" + st.node_name +
                          "' lost a shm publisher (participant " +
                          std::to_string(m->publisher_participant) + ")"});
  if (st.matches.size() != before || !removed.empty() || revived > 0) {
    ++st.version;
    st.matched_cv.notify_all();
  }
  if (!removed.empty() || st.matches.size() != before) {
    if (st.node) st.node->ring();
  }
}

// Counts subscribers of other processes that report a match with `pub` (they opened its
// segment), and reports remote subscribers of another type.
void RuntimeImpl::count_remote_locked(PublisherImpl& pub, std::vector<Event>& events) {
  std::size_t counts[2] = {0, 0};  // shm (this host), udp (other hosts)
  for (const auto* scope_map : {&remotes, &vehicle_remotes})
  for (const auto& [pid, b] : *scope_map) {
    auto& n = counts[scope_map == &remotes ? 0 : 1];
    for (const auto& e : b.endpoints) {
      if (e.kind != lcmx_msgs::endpoint_t::KIND_SUBSCRIBER || e.topic != pub.channel()) continue;
      if (!compatible(e.fingerprint, pub.type.fingerprint)) {
        const std::string text = "type mismatch on channel '" + pub.channel() +
                                 "': publisher (node '" + pub.node->name + "') has " +
                                 pub.type.name + ", subscriber (process " + b.process_name +
                                 " pid " + std::to_string(b.pid) + ", node '" + e.node +
                                 "') wants " + e.type_name + "; not matched";
        report_mismatch_locked(pub.id, static_cast<std::uint64_t>(b.participant_id),
                               static_cast<std::uint64_t>(e.id), pub.channel(), text, pub.errors,
                               events);
        continue;
      }
      for (const auto& m : e.matches)
        if (static_cast<std::uint64_t>(m.publisher_participant) == participant_id &&
            static_cast<std::uint64_t>(m.publisher_endpoint) == pub.id)
          ++n;
    }
  }
  pub.set_remote_subscribers(counts[0], counts[1]);
}

void RuntimeImpl::add_publisher(PublisherImpl* pub) {
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    pubs[pub->id] = pub;
    for (auto& [id, sub] : subs) match_local_locked(*pub, *sub, events);
    count_remote_locked(*pub, events);
  }
  changed();
  emit(std::move(events));
}

void RuntimeImpl::remove_publisher(PublisherImpl* pub) {
  {
    std::lock_guard lock(mu);
    pubs.erase(pub->id);
    rates.erase(pub->id * 2), rates.erase(pub->id * 2 + 1);
    for (auto& [id, sub] : subs) {
      auto& st = *sub->state;
      std::lock_guard l2(st.mu);
      const auto n = std::erase_if(st.matches, [&](const auto& m) {
        return m->path == Path::intra && m->publisher_endpoint == pub->id;
      });
      if (n) {
        ++st.version;
        st.matched_cv.notify_all();
      }
    }
  }
  changed();
}

void RuntimeImpl::add_subscriber(const std::shared_ptr<SubscriberCore>& sub) {
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    subs[sub->id] = sub;
    for (auto& [id, pub] : pubs) match_local_locked(*pub, *sub, events);
    sync_remote_locked(*sub, events);
  }
  changed();
  emit(std::move(events));
}

void RuntimeImpl::remove_subscriber(const SubscriberCore* sub) {
  {
    std::lock_guard lock(mu);
    for (auto& [id, pub] : pubs) pub->remove_intra(sub);
    subs.erase(sub->id);
    rates.erase(sub->id * 2), rates.erase(sub->id * 2 + 1);
  }
  changed();
}

// Scopes (DESIGN.md "Discovery"): a host-scope beacon comes from a participant of this host
// (shm path); a vehicle-scope beacon from another host's participant (udp path). Vehicle
// beacons of this host's participants are ignored: they are known through the host scope.
void RuntimeImpl::on_participant(std::int8_t scope, discovery::Change change,
                                 const discovery::Participant& p) {
  const auto& b = p.beacon;
  const bool vehicle = scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE;
  const bool same_host = static_cast<std::uint64_t>(b.host_id) == host;
  if (!vehicle && !same_host && change == discovery::Change::joined) report_neighbour(b);
  if (vehicle == same_host) return;
  auto& scope_map = vehicle ? vehicle_remotes : remotes;
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    // Sources: which UDP sender is which participant.
    auto forget_sources = [&](std::map<std::string, std::int64_t>& m) {
      std::erase_if(m, [&](const auto& kv) { return kv.second == b.participant_id; });
    };
    forget_sources(vehicle ? vehicle_sources : host_sources);
    if (!vehicle) std::erase_if(host_ports, [&](const auto& kv) { return kv.second == b.participant_id; });
    const std::string where = vehicle ? " on host " + std::to_string(b.host_id) : "";
    if (change == discovery::Change::left) {
      scope_map.erase(b.participant_id);
      events.push_back({Event::Kind::participant_left, "",
                        "participant " + b.process_name + " pid " + std::to_string(b.pid) + where + " left"});
    } else {
      if (change == discovery::Change::joined)
        events.push_back({Event::Kind::participant_joined, "",
                          "participant " + b.process_name + " pid " + std::to_string(b.pid) + where +
                              " joined"});
      scope_map[b.participant_id] = b;
      if (vehicle) {
        if (!b.vehicle_source.empty()) vehicle_sources[b.vehicle_source] = b.participant_id;
      } else {
        if (!b.local_source.empty()) host_sources[b.local_source] = b.participant_id;
        if (const auto port = port_of(b.local_source); port != 0) host_ports[port] = b.participant_id;
        if (!b.vehicle_source.empty()) host_sources[b.vehicle_source] = b.participant_id;
      }
      // Its messages may have arrived before its beacon and been taken for a stock LCM
      // sender's: now that we know who it is, that foreign match goes (its real one, if its
      // type matches, comes from the beacon).
      std::vector<std::string> sources = {b.local_source, b.vehicle_source};
      if (!vehicle)  // its mirror: the local_source port from any address of this host
        if (const auto port = port_of(b.local_source); port != 0)
          for (const auto a : host_addresses)
            sources.push_back(udpm::to_string(udpm::Source{a, port}));
      for (const auto& src : sources) {
        if (src.empty()) continue;
        const auto key = std::hash<std::string>{}(src);
        for (auto& [id, sub] : subs) {
          auto& st = *sub->state;
          std::lock_guard l2(st.mu);
          if (std::erase_if(st.matches, [&](const auto& m) {
                return m->foreign && m->publisher_endpoint == key;
              })) {
            ++st.version;
            st.matched_cv.notify_all();
            announce_pending = true;
          }
        }
      }
    }
    // Any change of our matches is announced at once: publishers count subscribers by the
    // matches subscribers announce (versions only grow, so their sum tells).
    const auto match_versions = [&] {
      std::uint64_t v = 0;
      for (auto& [id, sub] : subs) {
        std::lock_guard l2(sub->state->mu);
        v += sub->state->version;
      }
      return v;
    };
    const auto v0 = match_versions();
    if (!vehicle) update_bridges_locked();
    for (auto& [id, sub] : subs) sync_remote_locked(*sub, events);
    for (auto& [id, pub] : pubs) count_remote_locked(*pub, events);
    if (match_versions() != v0) ++revision, announce_pending = true;
  }
  if (announce_pending.exchange(false)) {
    if (disco) disco->announce_now();
    if (disco_vehicle) disco_vehicle->announce_now();
  }
  // A participant of this host that vanished without a goodbye may have left shared memory.
  if (!vehicle && change == discovery::Change::left && options.reclaim_orphans) {
    const auto r = shm::reclaim_orphans(own_shm_prefix);
    if (r.removed > 0)
      spdlog::info("lcmx: removed {} shared-memory segments of {} pid {}", r.removed,
                   b.process_name, b.pid);
  }
  emit(std::move(events));
}

// A host-scope beacon (this network namespace) from a participant with another host id: it
// sees another /dev/shm (another container) or has LCMX_HOST_ID set. No shared memory with
// it: it is another host, reached over the vehicle group if there is one. Said once per
// participant: an error Event when there is no vehicle group (nothing can reach it), a log
// line otherwise.
void RuntimeImpl::report_neighbour(const lcmx_msgs::beacon_t& b) {
  {
    std::lock_guard lock(mu);
    if (neighbours_reported.size() >= 1024) neighbours_reported.clear();  // bounded
    if (!neighbours_reported.insert(b.participant_id).second) return;
  }
  const std::string text = "participant " + b.process_name + " pid " + std::to_string(b.pid) +
                           " shares this network namespace but not this host's identity "
                           "(another /dev/shm, e.g. another container, or LCMX_HOST_ID): no "
                           "shared memory with it; " +
                           (vehicle_group ? std::string("it is reached over the vehicle group")
                                          : std::string("no vehicle group is configured "
                                                        "(vehicle_url), so nothing reaches it"));
  if (vehicle_group) spdlog::info("lcmx: {}", text);
  else emit({Event{Event::Kind::error, "", text}});
}

// The bridges of this host (DESIGN.md "Message Bridge"): while one runs, large topics reach
// other hosts only through it, and the topics it carries besides the large class become large
// here (sticky, announced).
void RuntimeImpl::update_bridges_locked() {
  bool seen = false;
  std::vector<std::string> globs = options.bridge_carry;
  for (const auto& [pid, b] : remotes) {
    if (!(b.flags & lcmx_msgs::beacon_t::FLAG_BRIDGE)) continue;
    seen = true;
    for (const auto& g : b.carried)
      if (!g.empty() && std::find(globs.begin(), globs.end(), g) == globs.end()) globs.push_back(g);
  }
  if (seen != bridge_seen.exchange(seen))
    spdlog::info("lcmx: {} Message Bridge on this host", seen ? "a" : "no");
  {
    std::lock_guard lock(carried_mu);
    carried = std::move(globs);
  }
  for (auto& [id, pub] : pubs)
    if (!pub->large() && class_of(pub->channel()) == TopicClass::large) {
      pub->mark_large();
      ++revision;
      announce_pending = true;
    }
}

// Host scope: everything. Vehicle scope: the same endpoints without what only this host can
// use (shm segment names); addresses as "ip:port", never hostnames.
lcmx_msgs::beacon_t RuntimeImpl::build_beacon(std::int8_t scope) {
  const bool vehicle = scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE;
  lcmx_msgs::beacon_t b{};
  b.version = discovery::kBeaconVersion;
  b.scope = scope;
  b.local_source = udpm::to_string(local_group->local_source());
  if (vehicle_group) b.vehicle_source = udpm::to_string(vehicle_group->local_source());
  b.participant_id = static_cast<std::int64_t>(participant_id);
  b.host_id = static_cast<std::int64_t>(host);
  b.pid = static_cast<std::int32_t>(::getpid());
  b.process_name = discovery::process_name();
  b.flags = options.bridge ? lcmx_msgs::beacon_t::FLAG_BRIDGE : 0;
  if (!vehicle) b.carried = options.bridge_carry;
  b.num_carried = static_cast<std::int32_t>(b.carried.size());
  const auto now = std::chrono::steady_clock::now();
  auto rate = [&](std::uint64_t id, std::uint64_t count) {
    auto& r = rates[id * 2 + (vehicle ? 1 : 0)];
    double hz = 0;
    if (r.when != std::chrono::steady_clock::time_point{}) {
      const double dt = std::chrono::duration<double>(now - r.when).count();
      if (dt > 0.05) hz = static_cast<double>(count - r.count) / dt;
      else return 0.0;
    }
    r.count = count;
    r.when = now;
    return hz;
  };
  std::lock_guard lock(mu);
  b.revision = revision.load();
  for (auto& w : nodes)
    if (auto n = w.lock()) b.nodes.push_back(n->name);
  b.num_nodes = static_cast<std::int32_t>(b.nodes.size());
  // Other hosts see neither a bridge's endpoints nor, while a bridge runs here, large
  // publishers: those reach them through the bridges (DESIGN.md "Discovery", scopes).
  if (vehicle && options.bridge) {
    b.num_endpoints = 0;
    return b;
  }
  const bool hide_large = vehicle && bridge_on_host();
  for (auto& [id, pub] : pubs) {
    if (hide_large && pub->large()) continue;
    lcmx_msgs::endpoint_t e{};
    e.id = static_cast<std::int64_t>(id);
    e.kind = lcmx_msgs::endpoint_t::KIND_PUBLISHER;
    e.node = pub->node->name;
    e.topic = pub->channel();
    e.type_name = pub->type.name;
    e.fingerprint = pub->type.fingerprint;
    if (!vehicle) e.shm_segment = pub->segment_name();
    e.large = pub->large() ? 1 : 0;
    e.max_message_size = static_cast<std::int64_t>(pub->options.max_message_size);
    e.messages = static_cast<std::int64_t>(pub->published());
    e.rate_hz = rate(id, pub->published());
    e.errors = pub->errors;
    e.num_errors = static_cast<std::int32_t>(e.errors.size());
    b.endpoints.push_back(std::move(e));
  }
  for (auto& [id, sub] : subs) {
    lcmx_msgs::endpoint_t e{};
    e.id = static_cast<std::int64_t>(id);
    e.kind = lcmx_msgs::endpoint_t::KIND_SUBSCRIBER;
    e.node = sub->state->node_name;
    e.topic = sub->channel();
    e.type_name = sub->type().name;
    e.fingerprint = sub->type().fingerprint;
    e.messages = static_cast<std::int64_t>(sub->delivered.load());
    e.rate_hz = rate(id, sub->delivered.load());
    std::lock_guard l2(sub->state->mu);
    for (const auto& m : sub->state->matches) {
      lcmx_msgs::match_t mt;
      mt.publisher_participant = static_cast<std::int64_t>(m->publisher_participant);
      mt.publisher_endpoint = static_cast<std::int64_t>(m->publisher_endpoint);
      mt.path = to_string(m->path);
      mt.received = static_cast<std::int64_t>(m->stats->received.load());
      mt.drops = static_cast<std::int64_t>(m->stats->drops.load());
      e.drops += mt.drops;
      e.matches.push_back(std::move(mt));
    }
    e.num_matches = static_cast<std::int32_t>(e.matches.size());
    e.errors = sub->state->errors;
    e.num_errors = static_cast<std::int32_t>(e.errors.size());
    b.endpoints.push_back(std::move(e));
  }
  b.num_endpoints = static_cast<std::int32_t>(b.endpoints.size());
  return b;
}

}  // namespace detail

// ---------------------------------------------------------------- RuntimeOptions

namespace {
long env_number(const char* name, long fallback, long min, long max) {
  const char* v = std::getenv(name);
  if (!v || !*v) return fallback;
  char* end = nullptr;
  errno = 0;
  const long n = std::strtol(v, &end, 10);
  if (errno || end == v || *end || n < min || n > max)
    throw Error(Errc::invalid_argument, std::string(name) + "='" + v + "': expected an integer in [" +
                                            std::to_string(min) + ", " + std::to_string(max) + "]");
  return n;
}
}  // namespace

RuntimeOptions RuntimeOptions::from_env() {
  RuntimeOptions o;
  if (const char* url = std::getenv("LCMX_DISCOVERY_URL"); url && *url) o.discovery_url = url;
  if (const char* url = std::getenv("LCMX_VEHICLE_URL"); url && *url) o.vehicle_url = url;
  if (const char* v = std::getenv("LCMX_VEHICLE_PUBLISH"); v && *v) {
    const std::string s = v;
    if (s == "always") o.vehicle_publish = VehiclePublish::always;
    else if (s == "on_demand") o.vehicle_publish = VehiclePublish::on_demand;
    else throw Error(Errc::invalid_argument, "LCMX_VEHICLE_PUBLISH='" + s + "': expected on_demand or always");
  }
  o.udp_limit = static_cast<std::size_t>(env_number("LCMX_UDP_LIMIT", static_cast<long>(o.udp_limit), 1, 1L << 28));
  if (const char* v = std::getenv("LCMX_MIRROR"); v && *v) {
    const std::string s = v;
    if (s == "1") {
      o.mirror = true;
    } else if (s != "0") {
      o.mirror = false;
      for (std::size_t pos = 0; pos <= s.size();) {
        const auto comma = std::min(s.find(',', pos), s.size());
        auto glob = s.substr(pos, comma - pos);
        glob.erase(0, glob.find_first_not_of(" \t"));
        glob.erase(glob.find_last_not_of(" \t") + 1);
        if (glob.empty() || glob.size() > 255)
          throw Error(Errc::invalid_argument,
                      "LCMX_MIRROR='" + s + "': expected 0, 1 or comma-separated channel patterns "
                      "(e.g. CAM_*,POSE) with no empty entry");
        o.mirror_channels.push_back(glob);
        pos = comma + 1;
      }
    }
  }
  for (auto [var, cls] : {std::pair{"LCMX_LARGE_TOPICS", TopicClass::large},
                          std::pair{"LCMX_SMALL_TOPICS", TopicClass::small}}) {
    const char* v = std::getenv(var);
    if (!v) continue;
    std::string list = v;
    for (std::size_t pos = 0; pos <= list.size();) {
      const auto comma = std::min(list.find(',', pos), list.size());
      const auto name = list.substr(pos, comma - pos);
      if (!name.empty()) {
        if (name.size() > kMaxChannelLength)
          throw Error(Errc::invalid_argument, std::string(var) + ": channel '" + name + "' is longer than 63 bytes");
        o.topic_class[name] = cls;
      }
      pos = comma + 1;
    }
  }
  o.beacon_period = std::chrono::milliseconds(env_number("LCMX_BEACON_PERIOD_MS", o.beacon_period.count(), 10, 60000));
  o.lease = std::chrono::milliseconds(env_number("LCMX_LEASE_MS", o.lease.count(), 50, 600000));
  return o;
}

// ---------------------------------------------------------------- Runtime

Runtime Runtime::create(RuntimeOptions options) {
  static std::once_flag log_env;
  std::call_once(log_env, [] { spdlog::cfg::load_env_levels(); });
  if (options.lease <= options.beacon_period)
    throw Error(Errc::invalid_argument, "lease must be longer than beacon_period");
  if (detail::g_runtime_alive.exchange(true))
    throw Error(Errc::already_exists, "a lcmx::Runtime already exists in this process");
  try {
    auto impl = std::make_shared<detail::RuntimeImpl>(std::move(options));
    impl->start_transports();
    return Runtime(std::move(impl));
  } catch (...) {
    detail::g_runtime_alive.store(false);
    throw;
  }
}

Runtime::~Runtime() {
  if (impl_) impl_->shutdown();
}

Node Runtime::create_node(std::string name, NodeOptions options) {
  auto n = std::make_shared<detail::NodeImpl>(impl_, std::move(name), options);
  n->start();
  impl_->add_node(n);
  return Node(std::move(n));
}

void Runtime::on_event(std::function<void(const Event&)> callback) {
  std::lock_guard lock(impl_->event_mu);
  impl_->on_event = std::move(callback);
}

std::uint64_t Runtime::participant_id() const { return impl_->participant_id; }
std::uint64_t Runtime::host_id() const { return impl_->host; }

}  // namespace lcmx
