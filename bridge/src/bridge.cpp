// The Message Bridge: the public class, the engine's start and stop, and its sockets and their
// options. The engine's parts: engine.hpp (the map of files, threads and locks).
#include "engine.hpp"

#include <algorithm>
#include <random>

#include <spdlog/spdlog.h>

namespace lcmx::bridge {

using namespace std::chrono_literals;

Bridge::Impl::Impl(Config c, RuntimeOptions o)
    : cfg(check_limits(std::move(c))), rt_options(std::move(o)), ctx(static_cast<int>(cfg.channels.size()) + 1) {
  std::random_device rd;
  instance = (std::uint64_t{rd()} << 32) ^ rd() ^ static_cast<std::uint64_t>(now_ns());
  if (instance == 0) instance = 1;
}

std::string routing_id(const std::string& prefix) {
  static thread_local std::mt19937_64 rng{std::random_device{}() ^ static_cast<std::uint64_t>(now_ns())};
  std::uint64_t r = rng();
  if (r == 0) r = 1;
  return prefix + "/" + hex64(r);
}

// A Config built in code (not by load_config) gets the same limits.
Config Bridge::Impl::check_limits(Config c) {
  if (c.channels.empty() || c.channels.size() > kMaxChannels)
    throw BridgeError("bridge: 1 to " + std::to_string(kMaxChannels) + " channels required (got " +
                      std::to_string(c.channels.size()) + ")");
  if (c.peers.size() > kMaxPeers)
    throw BridgeError("bridge: at most " + std::to_string(kMaxPeers) + " peers (got " + std::to_string(c.peers.size()) + ")");
  return c;
}

// ZMTP heartbeats only clean up connections nobody talks on any more (e.g. a peer's, after
// it failed over): link liveness comes from our own pings, and unacknowledged data on a dead
// link is cut by TCP_MAXRT. So they are slow, and cost the link almost nothing.
void Bridge::Impl::common_options(zmq::socket_t& s) {
  const int ivl = static_cast<int>(std::max<std::int64_t>(1000, 2 * cfg.link_timeout.count()));
  s.set(zmq::sockopt::linger, 0);
  s.set(zmq::sockopt::heartbeat_ivl, ivl);
  s.set(zmq::sockopt::heartbeat_timeout, 3 * ivl);
  s.set(zmq::sockopt::heartbeat_ttl, 3 * ivl);
}

void Bridge::Impl::client_options(zmq::socket_t& s, const Peer& p) {
  common_options(s);
  s.set(zmq::sockopt::immediate, 1);
  s.set(zmq::sockopt::reconnect_ivl, static_cast<int>(std::min<std::int64_t>(100, cfg.heartbeat.count())));
  s.set(zmq::sockopt::reconnect_ivl_max, static_cast<int>(cfg.link_timeout.count()));
  // A SYN into a dead link would otherwise wait for the kernel's retransmissions (1 s, 3 s,
  // 7 s...) and notice a link that came back only seconds later.
  s.set(zmq::sockopt::connect_timeout, static_cast<int>(cfg.link_timeout.count()));
  // Unacknowledged data on a dead link: give up on the connection like the heartbeat does.
  s.set(zmq::sockopt::tcp_maxrt, static_cast<int>(cfg.link_timeout.count()));
  if (cfg.security.curve) {
    s.set(zmq::sockopt::curve_serverkey, p.cfg.public_key);
    s.set(zmq::sockopt::curve_publickey, cfg.security.public_key);
    s.set(zmq::sockopt::curve_secretkey, cfg.security.secret_key);
  }
}

void Bridge::Impl::server_options(zmq::socket_t& s) {
  common_options(s);
  s.set(zmq::sockopt::router_handover, 1);
  s.set(zmq::sockopt::router_mandatory, 1);
  // Every connection is put to the ZAP handler (zap_loop), with or without CURVE: with a ZAP
  // domain set, libzmq asks it under the NULL mechanism too, before the connection may carry a
  // message. That is where a connection from an address that is no configured peer's is
  // refused, and where each admitted one gets its peer's name (User-Id) that every message's
  // claimed name is checked against (docs/bridge.md "Trust").
  s.set(zmq::sockopt::zap_domain, "lcmx-bridge");
  if (cfg.security.curve) {
    s.set(zmq::sockopt::curve_server, 1);
    s.set(zmq::sockopt::curve_secretkey, cfg.security.secret_key);
  }
}

void Bridge::Impl::bind_all(zmq::socket_t& s, int port) {
  for (const auto& a : cfg.listen) {
    const std::string ep = "tcp://" + a + ":" + std::to_string(port);
    try {
      s.bind(ep);
    } catch (const zmq::error_t& e) {
      throw BridgeError(cfg.file.string() + ": cannot listen on " + ep + ": " + e.what() +
                        (e.num() == EADDRNOTAVAIL ? " (is " + a + " an address of this host?)" : ""));
    }
  }
}

void Bridge::Impl::start() {
  if (cfg.security.curve && !curve_available())
    throw BridgeError("security.curve = true but this libzmq has no CURVE support");
  // A keyed vehicle (docs/keyed-groups.md "The Message Bridge"): its UDP traffic is
  // authenticated, so its bridges must not be the open door over TCP. Without CURVE a bridge
  // admits its peers by address only (a LAN machine that takes a peer's address is let in):
  // refused; CURVE keys (`lcmx bridge keygen`) authenticate the peers by key and address.
  if (!rt_options.vehicle_key.empty() && !cfg.security.curve)
    throw BridgeError(cfg.file.string() + ": the vehicle group is keyed (vehicle_key, LCMX_VEHICLE_KEY = " +
                      rt_options.vehicle_key +
                      "), and a bridge on a keyed vehicle runs only with CURVE: set security.curve = true with "
                      "this bridge's and its peers' keys (lcmx bridge keygen; docs/bridge.md \"Who may connect, and "
                      "CURVE\", docs/keyed-groups.md \"The Message Bridge\")");

  // The participant.
  rt_options.bridge = true;
  rt_options.bridge_carry = cfg.carry;
  rt_options.vehicle_url.clear();
  runtime.emplace(Runtime::create(rt_options));
  status_node.emplace(runtime->create_node("bridge_status"));
  repub_node.emplace(runtime->create_node("bridge_republish"));
  status_pub.emplace(status_node->advertise<lcmx_msgs::bridge_status_t>(kStatusChannel));

  // Peers and channels.
  int max_prio = 0;
  for (const auto& c : cfg.channels) max_prio = std::max(max_prio, c.priority);
  for (std::size_t i = 0; i < cfg.channels.size(); ++i) {
    auto ch = std::make_unique<Channel>();
    ch->cfg = cfg.channels[i];
    ch->index = i;
    ch->nice = max_prio - ch->cfg.priority;
    ch->wake = std::make_unique<Wake>();
    channels.push_back(std::move(ch));
  }
  for (std::size_t i = 0; i < cfg.peers.size(); ++i) {
    auto p = std::make_unique<Peer>();
    p->cfg = cfg.peers[i];
    for (const auto& e : p->cfg.endpoints) {
      auto l = std::make_unique<Link>();
      l->cfg = e;
      p->links.push_back(std::move(l));
    }
    for (std::size_t c = 0; c < channels.size(); ++c) {
      // Held while a gap may still fill from another link's socket: at most max(hwm, 4)
      // messages (the channel's own bound, as its RCVHWM), for at most link_timeout (what an
      // up link takes to answer).
      auto pc = std::make_unique<PeerChannel>(std::max<std::size_t>(channels[c]->cfg.hwm, 4), cfg.link_timeout);
      pc->dealers.resize(p->links.size());
      p->chans.push_back(std::move(pc));
    }
    peer_by_name[p->cfg.name] = i;
    peers.push_back(std::move(p));
  }

  // ZAP first: every ROUTER asks it about every connection (server_options). Bound before any
  // ROUTER exists, so no connection is ever admitted without it.
  zap = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::rep);
  zap->set(zmq::sockopt::linger, 0);
  zap->set(zmq::sockopt::rcvhwm, 1000);
  zap->bind("inproc://zeromq.zap.01");
  zap_thread = std::thread([this] { zap_loop(); });

  // Sockets. Binding happens here, on the starting thread, so a bad address fails start().
  ctl_router = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::router);
  server_options(*ctl_router);
  ctl_router->set(zmq::sockopt::affinity, std::uint64_t{1} << channels.size());
  ctl_router->set(zmq::sockopt::maxmsgsize, static_cast<std::int64_t>(wire::kMaxControlFrame));
  // Per connection: a peer pings once per heartbeat per link; what it sends beyond 16 unread
  // pings waits in TCP (at most 16 x 4 MiB per admitted connection).
  ctl_router->set(zmq::sockopt::rcvhwm, kControlRcvHwm);
  bind_all(*ctl_router, cfg.control_port);
  for (auto& ch : channels) {
    ch->router = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::router);
    server_options(*ch->router);
    ch->router->set(zmq::sockopt::affinity, std::uint64_t{1} << ch->index);
    ch->router->set(zmq::sockopt::tos, ch->cfg.priority << 5);
    ch->router->set(zmq::sockopt::rcvhwm, static_cast<int>(std::max<std::size_t>(ch->cfg.hwm, 2)));
    ch->router->set(zmq::sockopt::maxmsgsize, kMaxDataMessage);
    bind_all(*ch->router, ch->cfg.port);
  }
  for (auto& p : peers) {
    for (auto& l : p->links) {
      l->ctl = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::dealer);
      client_options(*l->ctl, *p);
      l->ctl->set(zmq::sockopt::routing_id, routing_id(cfg.name + "/" + l->cfg.link));
      l->ctl->set(zmq::sockopt::sndhwm, 4);
      l->ctl->set(zmq::sockopt::rcvhwm, kControlRcvHwm);  // pongs
      l->ctl->set(zmq::sockopt::maxmsgsize, static_cast<std::int64_t>(wire::kMaxControlFrame));
      l->ctl->set(zmq::sockopt::affinity, std::uint64_t{1} << channels.size());
      l->ctl->connect("tcp://" + l->cfg.address + ":" + std::to_string(cfg.control_port));
    }
  }

  // The local view: which topics this host's participants publish and subscribe to.
  discovery::Options d;
  d.group = rt_options.group_config(false);  // with the host key when the host-local group is keyed
  d.observer = true;
  ctl_wake = std::make_unique<Wake>();  // before the observer: its thread rings it at once
  observer = std::make_unique<discovery::Discovery>(d, nullptr, [this](discovery::Change, const discovery::Participant&) {
    view_dirty = true;
    ctl_wake->ring();
  });
  observer->query();

  for (auto& ch : channels) {
    ch->node.emplace(runtime->create_node("bridge_" + ch->cfg.name));
    Channel* c = ch.get();
    ch->thread = std::thread([this, c] { channel_loop(*c); });
  }
  ctl_thread = std::thread([this] { control_loop(); });

  std::string peers_text;
  for (const auto& p : peers) peers_text += (peers_text.empty() ? "" : ", ") + p->cfg.name;
  spdlog::info("bridge {}: listening on {} (control port {}, {} channel(s)), peers: {}{}", cfg.name,
               fmt_list(cfg.listen), cfg.control_port, channels.size(), peers_text.empty() ? "none" : peers_text,
               cfg.security.curve ? ", CURVE on" : "");
}

std::string Bridge::Impl::fmt_list(const std::vector<std::string>& v) {
  std::string s;
  for (const auto& x : v) s += (s.empty() ? "" : ", ") + x;
  return s;
}

void Bridge::Impl::stop() {
  if (stopping.exchange(true)) return;
  if (ctl_wake) ctl_wake->ring();
  for (auto& ch : channels) ch->wake->ring();
  if (ctl_thread.joinable()) ctl_thread.join();
  for (auto& ch : channels)
    if (ch->thread.joinable()) ch->thread.join();
  if (zap_thread.joinable()) zap_thread.join();
  if (observer) observer->stop();
  spdlog::info(
      "bridge {}: stopping; local messages sent zero-copy {}, copied {}; waited for a pin {} times; "
      "handed to peers' sockets by the shm callback {}, from the queues {}; lost before the bridge read them {}; "
      "connections refused {}, bad messages {}",
      cfg.name, zero_copy_msgs.load(), copied_msgs.load(), pin_waits.load(), sent_from_callback.load(),
      sent_from_queue.load(), lost_local.load(), refused.load(), bad_frames.load());
  // Subscriptions first (their callbacks touch peers' queues), then publishers, then the
  // runtime (goodbye).
  for (auto& [t, s] : served) s->sub.reset();
  served.clear();
  {
    std::lock_guard lock(repub_mu);
    repubs.clear();
  }
  status_pub.reset();
  for (auto& ch : channels) ch->node.reset();
  status_node.reset();
  repub_node.reset();
  runtime.reset();
  // Sockets (every thread that used them has been joined).
  for (auto& p : peers) {
    for (auto& l : p->links) l->ctl.reset();
    for (auto& pc : p->chans) {
      pc->dealer = nullptr;
      pc->dealers.clear();
      std::lock_guard lock(pc->mu);
      pc->queue.clear();
    }
  }
  for (auto& ch : channels) ch->router.reset();
  ctl_router.reset();
  zap.reset();
  ctx.close();
  spdlog::info("bridge {}: stopped", cfg.name);
}

void Bridge::Impl::count_bad(const std::string& why) {
  bad_frames.fetch_add(1);
  if (bad_log.allow()) spdlog::warn("bridge {}: dropped a bad message: {} ({} so far)", cfg.name, why, bad_frames.load());
}

// Which link of `p` the address belongs to (-1 if none).
int Bridge::Impl::link_of(const Peer& p, const char* address) {
  if (!address) return -1;
  for (std::size_t i = 0; i < p.links.size(); ++i)
    if (p.links[i]->cfg.address == address) return static_cast<int>(i);
  return -1;
}

const char* Bridge::Impl::peer_address(zmq::message_t& m) {
  try {
    return m.gets("Peer-Address");
  } catch (const zmq::error_t&) {
    return nullptr;
  }
}

// ---------------------------------------------------------------------------------------------

Bridge Bridge::start(Config config, RuntimeOptions runtime) {
  auto impl = std::make_unique<Impl>(std::move(config), std::move(runtime));
  try {
    impl->start();
  } catch (const zmq::error_t& e) {
    impl->stop();
    throw BridgeError(std::string("bridge: ") + e.what());
  } catch (...) {
    impl->stop();
    throw;
  }
  return Bridge(std::move(impl));
}

Bridge::Bridge(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Bridge::Bridge(Bridge&&) noexcept = default;
Bridge& Bridge::operator=(Bridge&& o) noexcept {
  if (this != &o) {
    if (impl_) impl_->stop();
    impl_ = std::move(o.impl_);
  }
  return *this;
}
Bridge::~Bridge() {
  if (impl_) impl_->stop();
}
void Bridge::stop() {
  if (impl_) impl_->stop();
}
lcmx_msgs::bridge_status_t Bridge::status() const { return impl_->status(); }

}  // namespace lcmx::bridge
