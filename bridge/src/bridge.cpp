// The Message Bridge daemon's engine. Map (docs/bridge.md has the why):
//
//   control thread  : control ROUTER (pings from peers -> pongs, their demand/offers/hello),
//                     one control DEALER per (peer, link) (our pings, their pongs), link states
//                     and the active link per peer, local discovery view, shm subscriptions of
//                     what peers want (Served), republishers, status.
//   channel threads : one per channel: the channel's ROUTER (data from peers -> republish into
//                     shm) and one DEALER per peer connected to the peer's active link (data to
//                     peers, from the bounded per-peer queues).
//   node executors  : one Node per channel runs that channel's shm subscriptions: the callback
//                     copies the slot once into a zmq::message_t and queues a refcounted copy
//                     per wanting peer (drop policy, counted), then wakes the channel thread.
//
// Lock order: Served::mu and PeerChannel::mu are leaves; Impl::view_mu -> repub_mu.
// A Served's callback takes only Served::mu, PeerChannel::mu and nothing else, so the
// control thread may destroy a subscription (which waits for its running callback) while
// holding no lock.
#include "lcmx/bridge/bridge.hpp"

#include <fnmatch.h>
#include <sched.h>
#include <sys/eventfd.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <map>
#include <mutex>
#include <random>
#include <set>
#include <thread>
#include <zmq.hpp>

#include <spdlog/spdlog.h>

#include "lcmx/bridge/detail/wire.hpp"
#include "lcmx/core.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "lcmx_msgs/beacon_t.hpp"

namespace lcmx::bridge {
namespace {

using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

constexpr auto kDemandRefresh = std::chrono::seconds(1);  // full ping at least this often
constexpr std::int64_t kMaxDataMessage = (64ll << 20) + 4096;  // = PublisherOptions default + slack
constexpr std::size_t kRecvBatch = 64;

std::int64_t now_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
}

std::string hex64(std::uint64_t v) {
  char b[20];
  std::snprintf(b, sizeof b, "%016llx", static_cast<unsigned long long>(v));
  return b;
}

// Lowers the calling thread's scheduling priority by `nice` (Linux: per-thread niceness).
// Raising it would need CAP_SYS_NICE; lowering never fails for lack of rights.
void set_thread_nice(int nice) {
  if (nice <= 0) return;
  const auto tid = static_cast<id_t>(::syscall(SYS_gettid));
  ::setpriority(PRIO_PROCESS, tid, nice);
}

// Wakes a thread blocked in zmq::poll (the eventfd is one of its poll items).
class Wake {
 public:
  Wake() : fd_(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC)) {
    if (fd_ < 0) throw BridgeError(std::string("eventfd: ") + std::strerror(errno));
  }
  ~Wake() { ::close(fd_); }
  Wake(const Wake&) = delete;
  Wake& operator=(const Wake&) = delete;
  void ring() {
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(fd_, &one, sizeof one);
  }
  void drain() {
    std::uint64_t v;
    [[maybe_unused]] auto n = ::read(fd_, &v, sizeof v);
  }
  int fd() const { return fd_; }

 private:
  int fd_;
};

// Rate-limited logging: at most one line per `period` per limiter.
struct RateLimit {
  Clock::time_point last{};
  bool allow(Clock::duration period = 5s) {
    const auto now = Clock::now();
    if (last != Clock::time_point{} && now - last < period) return false;
    last = now;
    return true;
  }
};

struct Outgoing {
  std::shared_ptr<const std::string> topic;
  zmq::message_t payload;  // a refcounted copy (zmq_msg_copy) of the one copy of the slot
};

}  // namespace

// ---------------------------------------------------------------------------------------------
struct Bridge::Impl {
  struct Link {
    EndpointConfig cfg;
    std::unique_ptr<zmq::socket_t> ctl;  // control DEALER (control thread)
    // control thread:
    bool up = false;
    Clock::time_point last_pong{}, up_since{};
    bool answered = false;
    // read by status():
    std::atomic<std::int64_t> last_pong_ns{-1};
    std::atomic<std::int32_t> rtt_us{-1};
    std::atomic<bool> up_flag{false};
    std::atomic<std::uint64_t> bytes_sent{0}, bytes_received{0};
  };

  struct PeerChannel {
    std::mutex mu;  // guards queue
    std::deque<Outgoing> queue;
    std::atomic<std::uint64_t> sent_msgs{0}, sent_bytes{0}, drops{0}, recv_msgs{0}, recv_bytes{0}, lost{0};
    std::atomic<std::int32_t> queued{0};
    // channel thread:
    std::unique_ptr<zmq::socket_t> dealer;
    int connected_link = -1;
    std::uint64_t seq = 0;
    std::uint64_t rx_instance = 0, rx_seq = 0;
    bool rx_any = false;
    std::uint64_t drops_logged = 0;
    RateLimit drop_log;
  };

  struct Peer {
    PeerConfig cfg;
    std::vector<std::unique_ptr<Link>> links;
    std::vector<std::unique_ptr<PeerChannel>> chans;
    std::atomic<int> active{-1};  // index into links, -1: none up
    std::atomic<std::uint64_t> failovers{0};
    // control thread:
    std::uint64_t instance = 0;
    std::uint64_t hello_checked_instance = 0;
    bool was_up = false;
    // What our last full ping (demand) to it said, and when/where/to which instance of it.
    std::set<std::string> sent_want, sent_offer;
    Clock::time_point full_sent_at{};
    int full_sent_link = -1;
    std::uint64_t full_sent_instance = 0;
    // guarded by view_mu:
    std::set<std::string> wants, offers;
    Clock::time_point demand_at{};
    std::set<std::string> served;  // what we forward to it now
  };

  // One shm subscription: a topic some peer wants and a local non-bridge participant publishes.
  struct Served {
    std::string topic;
    std::shared_ptr<const std::string> topic_ptr;
    std::size_t channel = 0;
    std::atomic<bool> large{false};
    std::mutex mu;              // guards peers
    std::vector<std::size_t> peers;
    RawSubscriber sub;
  };

  struct Republisher {
    RawPublisher pub;
    Clock::time_point last_message{};
  };

  struct Channel {
    ChannelConfig cfg;
    std::size_t index = 0;
    int nice = 0;
    std::unique_ptr<Wake> wake;
    std::unique_ptr<zmq::socket_t> router;
    std::thread thread;
    std::optional<Node> node;  // executor for this channel's subscriptions
  };

  Config cfg;
  RuntimeOptions rt_options;
  std::uint64_t instance = 0;
  std::atomic<bool> stopping{false};
  std::atomic<std::uint64_t> bad_frames{0};
  RateLimit bad_log;

  zmq::context_t ctx;
  std::optional<Runtime> runtime;
  std::optional<Node> status_node, repub_node;
  std::optional<Publisher<lcmx_msgs::bridge_status_t>> status_pub;
  std::unique_ptr<discovery::Discovery> observer;
  std::atomic<bool> view_dirty{true};

  std::vector<std::unique_ptr<Peer>> peers;
  std::map<std::string, std::size_t> peer_by_name;
  std::vector<std::unique_ptr<Channel>> channels;

  std::unique_ptr<zmq::socket_t> ctl_router;
  std::unique_ptr<Wake> ctl_wake;
  std::thread ctl_thread;

  std::unique_ptr<zmq::socket_t> zap;
  std::thread zap_thread;

  // Local view (guarded by view_mu).
  mutable std::mutex view_mu;
  std::set<std::string> demand;                 // topics local non-bridge participants subscribe to
  std::map<std::string, bool> published;        // topic -> some local non-bridge publisher is large
  std::set<std::string> sticky_large;           // topics once seen large (never go back)

  // Control thread only.
  std::map<std::string, std::unique_ptr<Served>> served;
  std::set<std::string> no_channel_logged;

  std::mutex repub_mu;
  std::map<std::string, std::shared_ptr<Republisher>> repubs;

  Impl(Config c, RuntimeOptions o)
      : cfg(check_limits(std::move(c))), rt_options(std::move(o)), ctx(static_cast<int>(cfg.channels.size()) + 1) {
    std::random_device rd;
    instance = (std::uint64_t{rd()} << 32) ^ rd() ^ static_cast<std::uint64_t>(now_ns());
    if (instance == 0) instance = 1;
  }

  // ---- setup -------------------------------------------------------------------------------

  // A Config built in code (not by load_config) gets the same limits.
  static Config check_limits(Config c) {
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
  void common_options(zmq::socket_t& s) {
    const int ivl = static_cast<int>(std::max<std::int64_t>(1000, 2 * cfg.link_timeout.count()));
    s.set(zmq::sockopt::linger, 0);
    s.set(zmq::sockopt::heartbeat_ivl, ivl);
    s.set(zmq::sockopt::heartbeat_timeout, 3 * ivl);
    s.set(zmq::sockopt::heartbeat_ttl, 3 * ivl);
  }

  void client_options(zmq::socket_t& s, const Peer& p) {
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

  void server_options(zmq::socket_t& s) {
    common_options(s);
    s.set(zmq::sockopt::router_handover, 1);
    s.set(zmq::sockopt::router_mandatory, 1);
    if (cfg.security.curve) {
      s.set(zmq::sockopt::curve_server, 1);
      s.set(zmq::sockopt::curve_secretkey, cfg.security.secret_key);
      s.set(zmq::sockopt::zap_domain, "lcmx-bridge");
    }
  }

  void bind_all(zmq::socket_t& s, int port) {
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

  std::unique_ptr<zmq::socket_t> make_data_dealer(const Peer& p, const Channel& ch, const Link& l) {
    auto s = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::dealer);
    client_options(*s, p);
    s->set(zmq::sockopt::routing_id, cfg.name);
    s->set(zmq::sockopt::sndhwm, 2);  // our own queue holds the rest (drop policy)
    s->set(zmq::sockopt::affinity, std::uint64_t{1} << ch.index);
    s->set(zmq::sockopt::tos, ch.cfg.priority << 5);
    s->connect("tcp://" + l.cfg.address + ":" + std::to_string(ch.cfg.port));
    return s;
  }

  void start() {
    if (cfg.security.curve && !curve_available())
      throw BridgeError("security.curve = true but this libzmq has no CURVE support");

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
      for (std::size_t c = 0; c < channels.size(); ++c) p->chans.push_back(std::make_unique<PeerChannel>());
      peer_by_name[p->cfg.name] = i;
      peers.push_back(std::move(p));
    }

    // ZAP first: CURVE servers ask it about every connection.
    if (cfg.security.curve) {
      zap = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::rep);
      zap->set(zmq::sockopt::linger, 0);
      zap->bind("inproc://zeromq.zap.01");
      zap_thread = std::thread([this] { zap_loop(); });
    }

    // Sockets. Binding happens here, on the starting thread, so a bad address fails start().
    ctl_router = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::router);
    server_options(*ctl_router);
    ctl_router->set(zmq::sockopt::affinity, std::uint64_t{1} << channels.size());
    ctl_router->set(zmq::sockopt::maxmsgsize, static_cast<std::int64_t>(wire::kMaxControlFrame));
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
        l->ctl->set(zmq::sockopt::routing_id, cfg.name + "/" + l->cfg.link);
        l->ctl->set(zmq::sockopt::sndhwm, 4);
        l->ctl->set(zmq::sockopt::affinity, std::uint64_t{1} << channels.size());
        l->ctl->connect("tcp://" + l->cfg.address + ":" + std::to_string(cfg.control_port));
      }
    }

    // The local view: which topics this host's participants publish and subscribe to.
    discovery::Options d;
    d.group = udpm::parse_url(rt_options.discovery_url);
    d.observer = true;
    observer = std::make_unique<discovery::Discovery>(d, nullptr, [this](discovery::Change, const discovery::Participant&) {
      view_dirty = true;
      if (ctl_wake) ctl_wake->ring();
    });
    ctl_wake = std::make_unique<Wake>();
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

  static std::string fmt_list(const std::vector<std::string>& v) {
    std::string s;
    for (const auto& x : v) s += (s.empty() ? "" : ", ") + x;
    return s;
  }

  void stop() {
    if (stopping.exchange(true)) return;
    if (ctl_wake) ctl_wake->ring();
    for (auto& ch : channels) ch->wake->ring();
    if (ctl_thread.joinable()) ctl_thread.join();
    for (auto& ch : channels)
      if (ch->thread.joinable()) ch->thread.join();
    if (zap_thread.joinable()) zap_thread.join();
    if (observer) observer->stop();
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
        pc->dealer.reset();
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

  void count_bad(const std::string& why) {
    bad_frames.fetch_add(1);
    if (bad_log.allow()) spdlog::warn("bridge {}: dropped a bad message: {} ({} so far)", cfg.name, why, bad_frames.load());
  }

  // Which link of `p` the address belongs to (-1 if none).
  static int link_of(const Peer& p, const char* address) {
    if (!address) return -1;
    for (std::size_t i = 0; i < p.links.size(); ++i)
      if (p.links[i]->cfg.address == address) return static_cast<int>(i);
    return -1;
  }

  static const char* peer_address(zmq::message_t& m) {
    try {
      return m.gets("Peer-Address");
    } catch (const zmq::error_t&) {
      return nullptr;
    }
  }

  // With CURVE, the authenticated user id (the peer name the ZAP handler assigned) must match.
  bool authentic(zmq::message_t& m, const std::string& claimed) {
    if (!cfg.security.curve) return true;
    try {
      const char* uid = m.gets("User-Id");
      return uid && claimed == uid;
    } catch (const zmq::error_t&) {
      return false;
    }
  }

  // ---- ZAP (CURVE authentication) ----------------------------------------------------------

  void zap_loop() {
    std::map<std::string, RateLimit> refused_log;
    while (!stopping.load()) {
      zmq::pollitem_t item{zap->handle(), 0, ZMQ_POLLIN, 0};
      try {
        if (zmq::poll(&item, 1, std::chrono::milliseconds(100)) <= 0) continue;
      } catch (const zmq::error_t&) {
        continue;
      }
      std::vector<zmq::message_t> req;
      for (;;) {
        zmq::message_t m;
        if (!zap->recv(m, zmq::recv_flags::dontwait)) break;
        const bool more = m.more();
        req.push_back(std::move(m));
        if (!more) break;
      }
      while (req.size() < 7) req.emplace_back();  // malformed: still answered (REP must reply)
      const std::string version = req[0].to_string(), request_id = req[1].to_string(),
                        address = req[3].to_string(), mechanism = req[5].to_string();
      std::string status = "400", text = "not a configured peer", user;
      if (mechanism == "CURVE" && req.size() >= 7 && req[6].size() == 32) {
        char z85[41] = {};
        ::zmq_z85_encode(z85, static_cast<const std::uint8_t*>(req[6].data()), 32);
        for (const auto& p : peers)
          if (p->cfg.public_key == z85) {
            status = "200", text = "OK", user = p->cfg.name;
            break;
          }
        if (status != "200" && refused_log[address].allow())
          spdlog::warn("bridge {}: refused a CURVE connection from {}: public key {} is not a configured peer's",
                       cfg.name, address, z85);
      } else if (refused_log[address].allow()) {
        spdlog::warn("bridge {}: refused a connection from {}: mechanism {} (CURVE required)", cfg.name, address,
                     mechanism);
      }
      try {
        zap->send(zmq::buffer(version), zmq::send_flags::sndmore);
        zap->send(zmq::buffer(request_id), zmq::send_flags::sndmore);
        zap->send(zmq::buffer(status), zmq::send_flags::sndmore);
        zap->send(zmq::buffer(text), zmq::send_flags::sndmore);
        zap->send(zmq::buffer(user), zmq::send_flags::sndmore);
        zap->send(zmq::message_t(), zmq::send_flags::none);
      } catch (const zmq::error_t& e) {
        spdlog::error("bridge {}: ZAP reply failed: {}", cfg.name, e.what());
      }
    }
  }

  // ---- shm subscription callback (node executor thread of the channel) ---------------------

  void on_local_message(Served& s, const RawMessage& m) {
    thread_local int niced = -1;
    const int want_nice = channels[s.channel]->nice;
    if (niced != want_nice) {
      set_thread_nice(want_nice);
      niced = want_nice;
    }
    if (!s.large.load(std::memory_order_relaxed)) {
      if (m.data.size() <= rt_options.udp_limit) return;  // small: UDP carries it
      s.large = true;
      {
        std::lock_guard lock(view_mu);
        sticky_large.insert(s.topic);
      }
      spdlog::info("bridge {}: topic {} is large ({} bytes > udp_limit {}): bridged from now on", cfg.name, s.topic,
                   m.data.size(), rt_options.udp_limit);
    }
    std::size_t targets[kMaxPeers];  // load_config() allows at most kMaxPeers peers
    std::size_t n = 0;
    {
      std::lock_guard lock(s.mu);
      for (auto p : s.peers)
        if (n < std::size(targets)) targets[n++] = p;
    }
    if (n == 0) return;
    zmq::message_t payload(m.data.data(), m.data.size());  // the one copy out of the slot
    Channel& ch = *channels[s.channel];
    for (std::size_t i = 0; i < n; ++i) {
      PeerChannel& pc = *peers[targets[i]]->chans[s.channel];
      Outgoing out{s.topic_ptr, zmq::message_t()};
      out.payload.copy(payload);  // zmq_msg_copy: shares the buffer (refcount), no byte copy
      std::lock_guard lock(pc.mu);
      if (pc.queue.size() >= ch.cfg.hwm) {
        pc.drops.fetch_add(1, std::memory_order_relaxed);
        if (ch.cfg.drop == DropPolicy::newest) continue;
        pc.queue.pop_front();
      }
      pc.queue.push_back(std::move(out));
      pc.queued.store(static_cast<std::int32_t>(pc.queue.size()), std::memory_order_relaxed);
    }
    ch.wake->ring();
  }

  // ---- channel thread ------------------------------------------------------------------------

  void channel_loop(Channel& ch) {
    set_thread_nice(ch.nice);
    std::vector<zmq::pollitem_t> items;
    std::vector<PeerChannel*> polled;
    while (!stopping.load()) {
      // Follow the active links.
      for (auto& p : peers) {
        PeerChannel& pc = *p->chans[ch.index];
        const int want = p->active.load();
        if (want >= 0 && want != pc.connected_link) {
          try {
            pc.dealer = make_data_dealer(*p, ch, *p->links[static_cast<std::size_t>(want)]);
            pc.connected_link = want;
          } catch (const zmq::error_t& e) {
            spdlog::error("bridge {}: channel {}: cannot connect to {}: {}", cfg.name, ch.cfg.name, p->cfg.name, e.what());
          }
        }
      }
      items.clear();
      polled.clear();
      items.push_back({ch.router->handle(), 0, ZMQ_POLLIN, 0});
      items.push_back({nullptr, ch.wake->fd(), ZMQ_POLLIN, 0});
      for (auto& p : peers) {
        PeerChannel& pc = *p->chans[ch.index];
        if (pc.dealer && pc.queued.load(std::memory_order_relaxed) > 0) {
          items.push_back({pc.dealer->handle(), 0, ZMQ_POLLOUT, 0});
          polled.push_back(&pc);
        }
      }
      try {
        zmq::poll(items.data(), items.size(), std::chrono::milliseconds(100));
      } catch (const zmq::error_t& e) {
        if (e.num() == ETERM) break;
        continue;
      }
      if (items[1].revents & ZMQ_POLLIN) ch.wake->drain();
      if (items[0].revents & ZMQ_POLLIN) receive_data(ch);
      for (auto& p : peers) flush(ch, *p);
    }
  }

  void flush(Channel& ch, Peer& p) {
    PeerChannel& pc = *p.chans[ch.index];
    if (!pc.dealer) return;
    const int link = pc.connected_link;
    for (;;) {
      Outgoing out;
      {
        std::lock_guard lock(pc.mu);
        if (pc.queue.empty()) break;
        out = std::move(pc.queue.front());
        pc.queue.pop_front();
        pc.queued.store(static_cast<std::int32_t>(pc.queue.size()), std::memory_order_relaxed);
      }
      unsigned char hdr[wire::kDataHeader];
      wire::encode_header({instance, pc.seq + 1}, hdr);
      const std::size_t bytes = out.topic->size() + out.payload.size();
      bool sent = false;
      try {
        // All parts of a message are queued together once the first is accepted.
        if (pc.dealer->send(zmq::buffer(*out.topic), zmq::send_flags::sndmore | zmq::send_flags::dontwait)) {
          pc.dealer->send(zmq::buffer(hdr, sizeof hdr), zmq::send_flags::sndmore);
          pc.dealer->send(out.payload, zmq::send_flags::none);
          sent = true;
        }
      } catch (const zmq::error_t& e) {
        spdlog::warn("bridge {}: channel {}: send to {} failed: {}", cfg.name, ch.cfg.name, p.cfg.name, e.what());
      }
      if (!sent) {  // would block: put it back at the front, try again when writable
        std::lock_guard lock(pc.mu);
        pc.queue.push_front(std::move(out));
        pc.queued.store(static_cast<std::int32_t>(pc.queue.size()), std::memory_order_relaxed);
        break;
      }
      ++pc.seq;
      pc.sent_msgs.fetch_add(1, std::memory_order_relaxed);
      pc.sent_bytes.fetch_add(bytes, std::memory_order_relaxed);
      if (link >= 0) p.links[static_cast<std::size_t>(link)]->bytes_sent.fetch_add(bytes, std::memory_order_relaxed);
    }
    const auto d = pc.drops.load(std::memory_order_relaxed);
    if (d != pc.drops_logged && pc.drop_log.allow()) {
      spdlog::warn("bridge {}: {} message(s) to {} dropped on channel {} (queue full: hwm {}, drop {}); {} in total",
                   cfg.name, d - pc.drops_logged, p.cfg.name, ch.cfg.name, ch.cfg.hwm,
                   ch.cfg.drop == DropPolicy::oldest ? "oldest" : "newest", d);
      pc.drops_logged = d;
    }
  }

  void receive_data(Channel& ch) {
    for (std::size_t n = 0; n < kRecvBatch; ++n) {
      zmq::message_t parts[4];
      std::size_t count = 0;
      bool got = false, extra = false;
      for (;;) {
        zmq::message_t m;
        std::optional<std::size_t> r;
        try {
          r = ch.router->recv(m, count == 0 ? zmq::recv_flags::dontwait : zmq::recv_flags::none);
        } catch (const zmq::error_t&) {
          return;
        }
        if (!r) break;
        got = true;
        const bool more = m.more();
        if (count < 4) parts[count] = std::move(m);
        else extra = true;
        ++count;
        if (!more) break;
      }
      if (!got) return;
      if (count != 4 || extra) {
        count_bad("channel " + ch.cfg.name + ": " + std::to_string(count) + " frames (expected 4)");
        continue;
      }
      const std::string id = parts[0].to_string();
      auto it = peer_by_name.find(id);
      if (it == peer_by_name.end()) {
        count_bad("channel " + ch.cfg.name + ": data from unknown bridge '" + id.substr(0, 40) + "'");
        continue;
      }
      if (!authentic(parts[3], id)) {
        count_bad("channel " + ch.cfg.name + ": data claiming to be from " + id + " with another peer's key");
        continue;
      }
      Peer& p = *peers[it->second];
      const std::string topic = parts[1].to_string();
      if (!wire::valid_topic(topic) || parts[2].size() != wire::kDataHeader) {
        count_bad("channel " + ch.cfg.name + ": bad topic or header from " + id);
        continue;
      }
      const auto h = wire::decode_header(static_cast<const unsigned char*>(parts[2].data()));
      PeerChannel& pc = *p.chans[ch.index];
      if (!pc.rx_any || h.instance != pc.rx_instance) {
        pc.rx_any = true;
        pc.rx_instance = h.instance;
      } else if (h.seq <= pc.rx_seq) {
        count_bad("channel " + ch.cfg.name + ": stale sequence number from " + id);
        continue;  // never deliver twice or out of order (e.g. late data of an old link)
      } else if (h.seq > pc.rx_seq + 1) {
        pc.lost.fetch_add(h.seq - pc.rx_seq - 1, std::memory_order_relaxed);
      }
      pc.rx_seq = h.seq;
      const std::size_t bytes = topic.size() + parts[3].size();
      pc.recv_msgs.fetch_add(1, std::memory_order_relaxed);
      pc.recv_bytes.fetch_add(bytes, std::memory_order_relaxed);
      if (int l = link_of(p, peer_address(parts[3])); l >= 0)
        p.links[static_cast<std::size_t>(l)]->bytes_received.fetch_add(bytes, std::memory_order_relaxed);
      republish(topic, parts[3]);
    }
  }

  // Channel threads: into this host's shared memory.
  void republish(const std::string& topic, const zmq::message_t& payload) {
    std::shared_ptr<Republisher> r;
    {
      std::lock_guard lock(repub_mu);
      auto it = repubs.find(topic);
      if (it != repubs.end()) r = it->second;
    }
    if (!r) {
      {
        std::lock_guard lock(view_mu);
        if (!demand.count(topic)) return;  // nobody here wants it (any more)
      }
      r = ensure_republisher(topic);
      if (!r) return;
    }
    r->last_message = Clock::now();
    try {
      r->pub.publish(std::span<const std::byte>(static_cast<const std::byte*>(payload.data()), payload.size()));
    } catch (const std::exception& e) {
      spdlog::warn("bridge {}: republishing {} failed: {}", cfg.name, topic, e.what());
      return;
    }
    // The commit woke every subscriber of this host at once. Subscribers woken onto this
    // thread's CPU should all run their callbacks before this thread carries on (its next
    // receive, flush, poll): without this, the scheduler (EEVDF) often picks this thread again
    // between the first and the second subscriber, adding its remaining work (~15 µs) to
    // their callback-time difference. With nothing else runnable here it returns at once.
    ::sched_yield();
  }

  std::shared_ptr<Republisher> ensure_republisher(const std::string& topic) {
    std::lock_guard lock(repub_mu);
    auto& slot = repubs[topic];
    if (!slot) {
      try {
        auto r = std::make_shared<Republisher>();
        r->pub = repub_node->advertise_raw(topic);
        r->last_message = Clock::now();
        slot = std::move(r);
      } catch (const std::exception& e) {
        spdlog::warn("bridge {}: cannot republish {}: {}", cfg.name, topic, e.what());
        repubs.erase(topic);
        return nullptr;
      }
    }
    return slot;
  }

  // ---- control thread ------------------------------------------------------------------------

  void control_loop() {
    auto next_ping = Clock::now();
    auto next_status = Clock::now() + cfg.status_period;
    auto next_view = Clock::now();
    std::size_t status_subs = 0;
    std::vector<zmq::pollitem_t> items;
    std::vector<std::pair<Peer*, Link*>> polled;
    while (!stopping.load()) {
      items.clear();
      polled.clear();
      items.push_back({ctl_router->handle(), 0, ZMQ_POLLIN, 0});
      items.push_back({nullptr, ctl_wake->fd(), ZMQ_POLLIN, 0});
      for (auto& p : peers)
        for (auto& l : p->links) {
          items.push_back({l->ctl->handle(), 0, ZMQ_POLLIN, 0});
          polled.emplace_back(p.get(), l.get());
        }
      const auto wait = std::max<Clock::duration>(0ms, next_ping - Clock::now());
      try {
        zmq::poll(items.data(), items.size(), std::chrono::duration_cast<std::chrono::milliseconds>(wait) + 1ms);
      } catch (const zmq::error_t& e) {
        if (e.num() == ETERM) break;
        continue;
      }
      if (items[1].revents & ZMQ_POLLIN) ctl_wake->drain();
      if (items[0].revents & ZMQ_POLLIN) receive_control();
      for (std::size_t i = 0; i < polled.size(); ++i)
        if (items[i + 2].revents & ZMQ_POLLIN) receive_pongs(*polled[i].first, *polled[i].second);

      const auto now = Clock::now();
      if (view_dirty.exchange(false) || now >= next_view) {
        refresh_view();
        next_view = now + 1s;
      }
      if (now >= next_ping) {
        update_links(now);
        reconcile(now);
        send_pings();
        next_ping += cfg.heartbeat;
        if (next_ping < now) next_ping = now + cfg.heartbeat;
      }
      const std::size_t subs = status_pub->subscriber_count();
      if (now >= next_status || subs > status_subs) {
        try {
          status_pub->publish(status());
        } catch (const std::exception& e) {
          spdlog::warn("bridge {}: status publish failed: {}", cfg.name, e.what());
        }
        next_status = now + cfg.status_period;
      }
      status_subs = subs;
    }
  }

  void refresh_view() {
    std::set<std::string> d;
    std::map<std::string, bool> pubs;
    for (const auto& part : observer->participants()) {
      const auto& b = part.beacon;
      if (b.scope != lcmx_msgs::beacon_t::SCOPE_HOST) continue;
      if (b.flags & (lcmx_msgs::beacon_t::FLAG_BRIDGE | lcmx_msgs::beacon_t::FLAG_OBSERVER)) continue;
      for (const auto& e : b.endpoints) {
        if (!wire::valid_topic(e.topic)) continue;
        if (e.kind == lcmx_msgs::endpoint_t::KIND_SUBSCRIBER) d.insert(e.topic);
        else if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER) pubs[e.topic] = pubs[e.topic] || e.large != 0;
      }
    }
    std::lock_guard lock(view_mu);
    demand = std::move(d);
    published = std::move(pubs);
  }

  bool is_large_locked(const std::string& topic) const {
    auto it = published.find(topic);
    return (it != published.end() && it->second) || sticky_large.count(topic) || cfg.carried(topic);
  }

  // Every heartbeat, on every link of every peer: a ping. On the active link it is marked
  // active (the peer keeps our demand alive) and carries the full state — channels, what this
  // host wants, what we will send it — only when that changed, the link or the peer's
  // instance changed, or a second passed: the idle link carries a few dozen bytes per ping.
  void send_pings() {
    wire::Control c;
    c.kind = wire::Control::Kind::ping;
    c.from = cfg.name;
    c.instance = instance;
    std::set<std::string> want;
    {
      std::lock_guard lock(view_mu);
      want = demand;
    }
    const auto now = Clock::now();
    for (auto& p : peers) {
      const int active = p->active.load();
      std::set<std::string> offer;
      if (active >= 0) {
        std::lock_guard lock(view_mu);
        for (const auto& t : p->served)
          if (is_large_locked(t)) offer.insert(t);
      }
      const bool full = active >= 0 && (want != p->sent_want || offer != p->sent_offer ||
                                        active != p->full_sent_link || p->instance != p->full_sent_instance ||
                                        now - p->full_sent_at >= kDemandRefresh);
      for (std::size_t i = 0; i < p->links.size(); ++i) {
        Link& l = *p->links[i];
        c.link = l.cfg.link;
        c.t_ns = now_ns();
        c.active = static_cast<int>(i) == active;
        c.has_demand = c.active && full;
        c.want.clear();
        c.offer.clear();
        c.channels.clear();
        if (c.has_demand) {
          c.control_port = cfg.control_port;
          for (const auto& ch : cfg.channels) c.channels.emplace_back(ch.name, ch.port);
          c.want = want;
          c.offer = offer;
          p->sent_want = want;
          p->sent_offer = offer;
          p->full_sent_at = now;
          p->full_sent_link = active;
          p->full_sent_instance = p->instance;
        }
        const std::string text = wire::encode(c);
        try {
          if (l.ctl->send(zmq::buffer(text), zmq::send_flags::dontwait))
            l.bytes_sent.fetch_add(text.size(), std::memory_order_relaxed);
        } catch (const zmq::error_t&) {
        }
      }
    }
  }

  // Pings from peers (on our control ROUTER): remember their demand/offers, answer.
  void receive_control() {
    for (std::size_t n = 0; n < kRecvBatch; ++n) {
      zmq::message_t id, body;
      bool extra = false;
      try {
        if (!ctl_router->recv(id, zmq::recv_flags::dontwait)) return;
        if (!id.more()) {
          count_bad("control: a message without body");
          continue;
        }
        (void)ctl_router->recv(body, zmq::recv_flags::none);
        for (bool more = body.more(); more;) {  // drain unexpected parts
          zmq::message_t x;
          (void)ctl_router->recv(x, zmq::recv_flags::none);
          more = x.more();
          extra = true;
        }
      } catch (const zmq::error_t&) {
        return;
      }
      if (extra) {
        count_bad("control: more than one frame");
        continue;
      }
      auto c = wire::decode(std::string_view(static_cast<const char*>(body.data()), body.size()));
      if (!c || c->kind != wire::Control::Kind::ping) {
        count_bad("control: malformed message");
        continue;
      }
      auto it = peer_by_name.find(c->from);
      if (it == peer_by_name.end()) {
        count_bad("control: ping from unknown bridge '" + c->from + "' (not in this bridge's peers)");
        continue;
      }
      if (body.size() > 0 && !authentic(body, c->from)) {
        count_bad("control: ping claiming to be from " + c->from + " with another peer's key");
        continue;
      }
      Peer& p = *peers[it->second];
      if (int l = link_of(p, peer_address(body)); l >= 0)
        p.links[static_cast<std::size_t>(l)]->bytes_received.fetch_add(body.size(), std::memory_order_relaxed);
      if (p.instance != c->instance) {
        if (p.instance != 0)
          spdlog::info("bridge {}: peer {} restarted (instance {} -> {})", cfg.name, p.cfg.name, hex64(p.instance),
                       hex64(c->instance));
        p.instance = c->instance;
        std::lock_guard lock(view_mu);
        p.wants.clear();
        p.offers.clear();
      }
      if (c->has_demand && p.hello_checked_instance != c->instance) {
        p.hello_checked_instance = c->instance;
        check_hello(p, *c);
      }
      if (c->has_demand) {
        std::lock_guard lock(view_mu);
        p.wants = std::move(c->want);
        p.offers = std::move(c->offer);
        p.demand_at = Clock::now();
      } else if (c->active) {
        std::lock_guard lock(view_mu);
        if (p.demand_at != Clock::time_point{}) p.demand_at = Clock::now();  // still wanted
      }
      wire::Control pong;
      pong.kind = wire::Control::Kind::pong;
      pong.from = cfg.name;
      pong.instance = instance;
      pong.link = c->link;
      pong.t_ns = c->t_ns;
      const std::string text = wire::encode(pong);
      try {
        ctl_router->send(id, zmq::send_flags::sndmore | zmq::send_flags::dontwait);
        ctl_router->send(zmq::buffer(text), zmq::send_flags::dontwait);
        if (int l = link_of(p, peer_address(body)); l >= 0)
          p.links[static_cast<std::size_t>(l)]->bytes_sent.fetch_add(text.size(), std::memory_order_relaxed);
      } catch (const zmq::error_t&) {
        // EHOSTUNREACH (ROUTER_MANDATORY): the peer went away meanwhile; it pings again.
      }
    }
  }

  void check_hello(const Peer& p, const wire::Control& c) {
    std::vector<std::pair<std::string, int>> ours;
    for (const auto& ch : cfg.channels) ours.emplace_back(ch.name, ch.port);
    if (c.control_port == cfg.control_port && c.channels == ours) return;
    auto text = [](int control, const std::vector<std::pair<std::string, int>>& v) {
      std::string s = "control:" + std::to_string(control);
      for (const auto& [n, port] : v) s += " " + n + ":" + std::to_string(port);
      return s;
    };
    spdlog::error("bridge {}: peer {} has other channels than this bridge (theirs: {}; ours: {}): every bridge of a "
                  "vehicle must use the same channel names, ports and control_port",
                  cfg.name, p.cfg.name, text(c.control_port, c.channels), text(cfg.control_port, ours));
  }

  void receive_pongs(Peer& p, Link& l) {
    for (std::size_t n = 0; n < kRecvBatch; ++n) {
      zmq::message_t m;
      try {
        if (!l.ctl->recv(m, zmq::recv_flags::dontwait)) return;
        if (m.more()) {  // a pong is one frame: drain and drop the rest
          for (bool more = true; more;) {
            zmq::message_t x;
            (void)l.ctl->recv(x, zmq::recv_flags::none);
            more = x.more();
          }
          count_bad("control: multi-part reply from " + p.cfg.name);
          continue;
        }
      } catch (const zmq::error_t&) {
        return;
      }
      l.bytes_received.fetch_add(m.size(), std::memory_order_relaxed);
      auto c = wire::decode(std::string_view(static_cast<const char*>(m.data()), m.size()));
      if (!c || c->kind != wire::Control::Kind::pong) {
        count_bad("control: malformed reply from " + p.cfg.name + " over " + l.cfg.link);
        continue;
      }
      if (c->from != p.cfg.name) {
        count_bad("control: " + l.cfg.address + " answered as bridge '" + c->from + "', expected " + p.cfg.name);
        continue;
      }
      const auto age = now_ns() - c->t_ns;
      if (age < 0 || age > std::chrono::duration_cast<std::chrono::nanoseconds>(cfg.link_timeout).count())
        continue;  // a stale answer (queued while the link was down) proves nothing
      l.last_pong = Clock::now();
      l.answered = true;
      l.last_pong_ns = now_ns();
      l.rtt_us = static_cast<std::int32_t>(age / 1000);
    }
  }

  void update_links(Clock::time_point now) {
    for (auto& p : peers) {
      for (auto& l : p->links) {
        const bool up = l->answered && now - l->last_pong < cfg.link_timeout;
        if (up != l->up) {
          l->up = up;
          l->up_flag = up;
          if (up) l->up_since = now;
          spdlog::info("bridge {}: link {} to {} ({}) is {}", cfg.name, l->cfg.link, p->cfg.name, l->cfg.address,
                       up ? "up" : "down");
        }
      }
      int best = -1;
      for (std::size_t i = 0; i < p->links.size(); ++i)
        if (p->links[i]->up) {
          best = static_cast<int>(i);
          break;
        }
      const int cur = p->active.load();
      int next = cur;
      if (cur < 0 || !p->links[static_cast<std::size_t>(cur)]->up) next = best;  // fail over at once
      else if (best >= 0 && best < cur && now - p->links[static_cast<std::size_t>(best)]->up_since >= cfg.failback_hold)
        next = best;  // fail back after the hold-down
      if (next != cur) {
        p->active = next;
        if (next >= 0 && cur >= 0) p->failovers.fetch_add(1);
        if (next >= 0)
          spdlog::info("bridge {}: peer {}: active link {} ({}){}", cfg.name, p->cfg.name,
                       p->links[static_cast<std::size_t>(next)]->cfg.link, p->links[static_cast<std::size_t>(next)]->cfg.address,
                       cur >= 0 ? " (was " + p->links[static_cast<std::size_t>(cur)]->cfg.link + ")" : "");
        for (auto& ch : channels) ch->wake->ring();
      }
      const bool is_up = next >= 0;
      if (is_up != p->was_up) {
        p->was_up = is_up;
        if (!is_up) spdlog::warn("bridge {}: peer {} unreachable on every link; retrying", cfg.name, p->cfg.name);
      }
    }
  }

  // Subscriptions (what peers want and this host publishes) and republishers.
  void reconcile(Clock::time_point now) {
    const auto demand_ttl = 2 * cfg.link_timeout + cfg.heartbeat;
    std::map<std::string, std::vector<std::size_t>> want;  // topic -> peers
    std::map<std::string, bool> large;
    std::set<std::string> offered, local_demand;
    {
      std::lock_guard lock(view_mu);
      for (std::size_t i = 0; i < peers.size(); ++i) {
        Peer& p = *peers[i];
        if (p.demand_at != Clock::time_point{} && now - p.demand_at > demand_ttl) {
          p.wants.clear();
          p.offers.clear();
          p.demand_at = {};
        }
        p.served.clear();
        for (const auto& t : p.wants)
          if (published.count(t)) {
            want[t].push_back(i);
            p.served.insert(t);
          }
        if (p.active.load() >= 0) offered.insert(p.offers.begin(), p.offers.end());
      }
      for (const auto& [t, v] : want) large[t] = is_large_locked(t);
      local_demand = demand;
    }
    // Subscribe / update / unsubscribe.
    for (auto it = served.begin(); it != served.end();) {
      if (!want.count(it->first)) {
        it->second->sub.reset();  // waits for a running callback; we hold no lock
        spdlog::debug("bridge {}: no longer serving {}", cfg.name, it->first);
        it = served.erase(it);
      } else {
        ++it;
      }
    }
    for (auto& [t, ps] : want) {
      auto it = served.find(t);
      if (it == served.end()) {
        const auto ch = cfg.channel_of(t);
        if (!ch) {
          if (no_channel_logged.insert(t).second)
            spdlog::warn("bridge {}: topic {} matches no channel's topics: not bridged", cfg.name, t);
          continue;
        }
        auto s = std::make_unique<Served>();
        s->topic = t;
        s->topic_ptr = std::make_shared<const std::string>(t);
        s->channel = *ch;
        s->large = large[t];
        s->peers = ps;
        Served* raw = s.get();
        SubscriberOptions so;
        so.from_bridges = false;
        try {
          s->sub = channels[*ch]->node->subscribe_raw(t, [this, raw](const RawMessage& m) { on_local_message(*raw, m); }, so);
        } catch (const std::exception& e) {
          spdlog::warn("bridge {}: cannot subscribe to {}: {}", cfg.name, t, e.what());
          continue;
        }
        spdlog::debug("bridge {}: serving {} on channel {}", cfg.name, t, channels[*ch]->cfg.name);
        served.emplace(t, std::move(s));
      } else {
        if (large[t]) it->second->large = true;
        std::lock_guard lock(it->second->mu);
        it->second->peers = ps;
      }
    }
    // Republishers: for what an up peer offers and this host wants; gone when unwanted, or
    // neither offered nor used for a while.
    for (const auto& t : offered)
      if (local_demand.count(t)) {
        bool have;
        {
          std::lock_guard lock(repub_mu);
          have = repubs.count(t) > 0;
        }
        if (!have) ensure_republisher(t);
      }
    std::vector<std::shared_ptr<Republisher>> dead;  // destroyed outside the lock
    {
      std::lock_guard lock(repub_mu);
      for (auto it = repubs.begin(); it != repubs.end();) {
        const bool keep = local_demand.count(it->first) &&
                          (offered.count(it->first) || now - it->second->last_message < 3 * cfg.link_timeout + 1s);
        if (keep) {
          ++it;
        } else {
          dead.push_back(std::move(it->second));
          it = repubs.erase(it);
        }
      }
    }
  }

  // ---- status --------------------------------------------------------------------------------

  lcmx_msgs::bridge_status_t status() const {
    lcmx_msgs::bridge_status_t s{};
    s.timestamp_us = std::chrono::duration_cast<std::chrono::microseconds>(
                         std::chrono::system_clock::now().time_since_epoch()).count();
    s.name = cfg.name;
    s.host_id = runtime ? static_cast<std::int64_t>(runtime->host_id()) : 0;
    s.pid = static_cast<std::int32_t>(::getpid());
    s.curve = cfg.security.curve ? 1 : 0;
    s.bad_frames = static_cast<std::int64_t>(bad_frames.load());
    const auto now = now_ns();
    std::lock_guard lock(view_mu);
    for (const auto& p : peers) {
      lcmx_msgs::bridge_peer_status_t ps{};
      ps.name = p->cfg.name;
      const int active = p->active.load();
      ps.up = active >= 0 ? 1 : 0;
      ps.active_link = active >= 0 ? p->links[static_cast<std::size_t>(active)]->cfg.link : "";
      ps.failovers = static_cast<std::int64_t>(p->failovers.load());
      for (std::size_t i = 0; i < p->links.size(); ++i) {
        const Link& l = *p->links[i];
        lcmx_msgs::bridge_link_status_t ls{};
        ls.name = l.cfg.link;
        ls.address = l.cfg.address;
        ls.up = l.up_flag.load() ? 1 : 0;
        ls.active = static_cast<int>(i) == active ? 1 : 0;
        ls.bytes_sent = static_cast<std::int64_t>(l.bytes_sent.load());
        ls.bytes_received = static_cast<std::int64_t>(l.bytes_received.load());
        const auto lp = l.last_pong_ns.load();
        ls.heartbeat_age_ms = lp < 0 ? -1 : (now - lp) / 1000000;
        ls.rtt_us = l.rtt_us.load();
        ps.links.push_back(std::move(ls));
      }
      ps.num_links = static_cast<std::int32_t>(ps.links.size());
      for (std::size_t c = 0; c < channels.size(); ++c) {
        const PeerChannel& pc = *p->chans[c];
        lcmx_msgs::bridge_channel_status_t cs{};
        cs.name = channels[c]->cfg.name;
        cs.messages_sent = static_cast<std::int64_t>(pc.sent_msgs.load());
        cs.bytes_sent = static_cast<std::int64_t>(pc.sent_bytes.load());
        cs.drops = static_cast<std::int64_t>(pc.drops.load());
        cs.queued = pc.queued.load();
        cs.messages_received = static_cast<std::int64_t>(pc.recv_msgs.load());
        cs.bytes_received = static_cast<std::int64_t>(pc.recv_bytes.load());
        cs.lost = static_cast<std::int64_t>(pc.lost.load());
        ps.channels.push_back(std::move(cs));
      }
      ps.num_channels = static_cast<std::int32_t>(ps.channels.size());
      ps.served.assign(p->served.begin(), p->served.end());
      ps.num_served = static_cast<std::int32_t>(ps.served.size());
      ps.wanted.assign(p->wants.begin(), p->wants.end());
      ps.num_wanted = static_cast<std::int32_t>(ps.wanted.size());
      s.peers.push_back(std::move(ps));
    }
    s.num_peers = static_cast<std::int32_t>(s.peers.size());
    s.demand.assign(demand.begin(), demand.end());
    s.num_demand = static_cast<std::int32_t>(s.demand.size());
    return s;
  }
};

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
