// Private: the Message Bridge daemon's engine, Bridge::Impl, and what its parts share.
// The engine's member functions live in files named by responsibility:
//   bridge.cpp    Bridge (public API), start/stop, sockets and their options
//   control.cpp   the control thread: its loop, pings (heartbeat + demand) to every link of
//                 every peer, pings from peers (their demand) and our pongs, the hello check
//   failover.cpp  links and failover: pongs, link up/down, the active link per peer
//                 (the decisions themselves: failover.hpp)
//   demand.cpp    peers and demand: the local view (discovery), what each peer is served
//                 (shm subscriptions) and the republishers' lifetime
//   channels.cpp  data channels: the shm callback queueing to peers, the channel threads
//                 (send, receive, republish into shm) (queue and sequence rules: channels.hpp)
//   security.cpp  who may connect (with or without CURVE): the ZAP thread and the User-Id
//                 check of every message's claimed name (the decision: security.hpp)
//   status.cpp    the status snapshot (lcmx_msgs::bridge_status_t)
//
// Threads (docs/bridge.md has the why):
//   ZAP thread      : answers every ROUTER's connection requests (security.cpp), with or
//                     without CURVE: a connection is admitted only from a configured peer.
//   control thread  : control ROUTER (pings from peers -> pongs, their demand/offers/hello),
//                     one control DEALER per (peer, link) (our pings, their pongs), link states
//                     and the active link per peer, local discovery view, shm subscriptions of
//                     what peers want (Served), republishers, status.
//   channel threads : one per channel: the channel's ROUTER (data from peers -> republish into
//                     shm) and one DEALER per peer connected to the peer's active link (data to
//                     peers, from the bounded per-peer queues).
//   node executors  : one Node per channel runs that channel's shm subscriptions: the callback
//                     makes one zmq::message_t of the slot (zero-copy, or one copy) and, per
//                     wanting peer, sends a refcounted copy on the peer's dealer itself when
//                     nothing is queued for it, or queues it (drop policy, counted) and wakes
//                     the channel thread (PeerChannel::sock_mu has the rule).
//
// Lock order: Served::mu is a leaf; PeerChannel::sock_mu -> PeerChannel::mu (the other way
// by try_lock only); Impl::view_mu -> repub_mu.
// A Served's callback takes only Served::mu, PeerChannel::mu and sock_mu, so the
// control thread may destroy a subscription (which waits for its running callback) while
// holding no lock.
#pragma once

#include <sys/eventfd.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "channels.hpp"
#include "lcmx/bridge/bridge.hpp"
#include "lcmx/bridge/detail/wire.hpp"
#include "lcmx/core.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "lcmx_msgs/beacon_t.hpp"

namespace lcmx::bridge {

using Clock = std::chrono::steady_clock;

inline constexpr auto kDemandRefresh = std::chrono::seconds(1);  // full ping at least this often
inline constexpr std::int64_t kMaxDataMessage = (64ll << 20) + 4096;  // = PublisherOptions default + slack
inline constexpr std::size_t kRecvBatch = 64;
inline constexpr int kControlRcvHwm = 16;  // messages per connection on control sockets

inline std::int64_t now_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
}

// Text from the network for a log line: bytes outside printable ASCII as \xNN (a routing id
// is any bytes; a terminal reading the log must not get escape sequences from a peer).
inline std::string printable(std::string_view s, std::size_t max = 64) {
  std::string o;
  for (std::size_t i = 0; i < s.size() && i < max; ++i) {
    const auto c = static_cast<unsigned char>(s[i]);
    if (c >= 0x20 && c < 0x7f && c != '\\') {
      o += static_cast<char>(c);
    } else {
      char b[8];
      std::snprintf(b, sizeof b, "\\x%02x", c);
      o += b;
    }
  }
  if (s.size() > max) o += "...";
  return o;
}

inline std::string hex64(std::uint64_t v) {
  char b[20];
  std::snprintf(b, sizeof b, "%016llx", static_cast<unsigned long long>(v));
  return b;
}

// A DEALER's routing id: "<prefix>/<16 hex random digits>", new for every socket. The receiver
// reads only the name before the first '/' (routing_name) and checks it against the connection's
// peer (User-Id); the random part is what makes the routing id unguessable, so that another
// peer cannot connect with it and take this socket's connection over (ZMQ_ROUTER_HANDOVER:
// docs/bridge.md "Trust"). It is never sent in a message, only in the ZMTP handshake.
std::string routing_id(const std::string& prefix);
// The bridge name a routing id claims (up to its first '/').
inline std::string_view routing_name(std::string_view id) { return id.substr(0, id.find('/')); }

// Lowers the calling thread's scheduling priority by `nice` (Linux: per-thread niceness).
// Raising it would need CAP_SYS_NICE; lowering never fails for lack of rights.
inline void set_thread_nice(int nice) {
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
  bool allow(Clock::duration period = std::chrono::seconds(5)) {
    const auto now = Clock::now();
    if (last != Clock::time_point{} && now - last < period) return false;
    last = now;
    return true;
  }
};

// Releases of one served topic's zero-copy messages (their pinned slots), signalled from
// ZeroMQ's free callback on whichever thread frees the message; waited on by the topic's
// executor thread (Bridge::Impl::wait_for_pin). Shared with every message in flight, so it
// outlives the Served and the Bridge.
struct PinWatch {
  std::mutex mu;
  std::condition_variable cv;
  std::uint64_t released = 0;                      // guarded by mu
  std::atomic<std::int64_t> last_release_ns{0};    // steady clock; 0: never
  void on_release() {
    last_release_ns.store(std::chrono::steady_clock::now().time_since_epoch().count(), std::memory_order_relaxed);
    {
      std::lock_guard lock(mu);
      ++released;
    }
    cv.notify_all();
  }
};

// A message from a peer on its way into this host's shared memory (republish), possibly held
// a while by the channel's datapath::RxOrder.
struct Incoming {
  std::string topic;
  zmq::message_t payload;
  std::uint32_t keep = 0;  // the topic's keep last N at the origin, capped by the channel's max_keep
};

struct Outgoing {
  std::shared_ptr<const std::string> topic;
  // A refcounted copy (zmq_msg_copy) of the message made by retained_payload(): the pinned
  // slot itself, or one copy of it.
  zmq::message_t payload;
  std::uint32_t keep = 0;  // the topic's keep last N at the origin (DataHeader::keep)
};

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

  // One peer on one channel. Sending (channels.cpp): a message goes straight to the dealer
  // from the shm callback (node executor thread) when nothing is queued before it, else into
  // `queue`, which the channel thread sends in order when the dealer is writable.
  struct PeerChannel {
    // `hold_cap`, `hold`: the receiving order's bounds (RxOrder: at most max(hwm, 4) messages
    // held, for at most link_timeout).
    PeerChannel(std::size_t hold_cap, Clock::duration hold) : rx(hold_cap, hold) {}
    std::mutex mu;  // guards queue
    std::deque<Outgoing> queue;
    std::atomic<std::uint64_t> sent_msgs{0}, sent_bytes{0}, drops{0}, recv_msgs{0}, recv_bytes{0}, lost{0};
    std::atomic<std::int32_t> queued{0};
    std::atomic<std::int64_t> last_sent_ns{0};  // steady clock of the last message the socket took; 0: never
    // Guards dealer, dealers, connected_link and seq: held by the channel thread while it
    // (re)connects and flushes, and taken with try_lock by on_local_message (under mu, with
    // the queue empty) to send directly. The only use of the dealer without it is the channel
    // thread's zmq::poll for POLLOUT, which it makes only while the queue is not empty, and
    // only the channel thread empties the queue: then on_local_message queues and never
    // touches it. Lock order: mu -> sock_mu by try_lock only; the channel thread takes
    // sock_mu -> mu.
    std::mutex sock_mu;
    // One DEALER per link of the peer (index: link), made when the link first becomes active
    // and kept until the bridge stops: after a switch the old one still sends what it was
    // handed (a planned fail-back loses nothing: the receiver's RxOrder puts the two sockets'
    // messages back in order), and a link that comes back finds its socket reconnected.
    std::vector<std::unique_ptr<zmq::socket_t>> dealers;
    zmq::socket_t* dealer = nullptr;  // the active link's, dealers[connected_link]
    int connected_link = -1;
    std::uint64_t seq = 0;  // per (peer, channel), over every link's socket
    // channel thread:
    datapath::RxOrder<Incoming> rx;
    std::uint64_t stale = 0;  // messages not delivered: late data of a link given up on
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
    std::set<std::string> sent_want, sent_offer, sent_have;
    std::map<std::string, std::uint32_t> sent_keep;
    std::map<std::string, wire::Control::TopicType> sent_types;
    Clock::time_point full_sent_at{};
    int full_sent_link = -1;
    std::uint64_t full_sent_instance = 0;
    // guarded by view_mu:
    std::set<std::string> wants, offers;
    // When its host began to want each of `wants` (our clock: the ping's arrival less the age
    // it gave; kept while wanted, so later pings do not move it).
    std::map<std::string, Clock::time_point> want_since;
    std::map<std::string, std::uint32_t> keeps;  // keep last N of offered topics (0: absent)
    std::map<std::string, wire::Control::TopicType> types;  // of its offered/catalogued topics
    std::set<std::string> has;     // its catalogue: the large topics its host publishes
    Clock::time_point demand_at{};
    std::set<std::string> served;  // what we forward to it now
  };

  // One shm subscription: a topic some peer wants and a local non-bridge participant publishes.
  struct Served {
    std::string topic;
    std::shared_ptr<const std::string> topic_ptr;
    std::size_t channel = 0;
    std::atomic<bool> large{false};
    std::atomic<std::uint32_t> keep{0};  // largest history of the local publishers (reconcile)
    std::mutex mu;              // guards peers
    std::vector<std::size_t> peers;
    std::shared_ptr<PinWatch> pins = std::make_shared<PinWatch>();
    RawSubscriber sub;
    // executor thread (on_local_message): a message its publisher classes small although this
    // bridge would have bridged it (over udp_limit, or carried) was logged.
    bool small_said_logged = false;
    // control thread (note_local_drops): the subscription's drops counted into lost_local,
    // and logged so far.
    std::uint64_t drops_counted = 0, drops_logged = 0;
    RateLimit drop_log;
  };

  struct Republisher {
    RawPublisher pub;
    std::uint32_t history = 0;  // PublisherOptions::history: the peers' keep, capped by max_keep
    wire::Control::TopicType type;  // announced; {0, ""}: raw bytes
    // Clock ticks of the last message republished: written by channel threads (republish),
    // read by the control thread (reconcile), neither holding a lock for it.
    std::atomic<Clock::rep> last_message{0};
    void touch() { last_message.store(Clock::now().time_since_epoch().count(), std::memory_order_relaxed); }
    Clock::time_point last() const {
      return Clock::time_point(Clock::duration(last_message.load(std::memory_order_relaxed)));
    }
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
  std::atomic<std::uint64_t> refused{0};  // connections the ZAP handler refused
  // Local messages queued for peers: sent straight from their pinned slot / copied out of it.
  std::atomic<std::uint64_t> zero_copy_msgs{0}, copied_msgs{0};
  std::atomic<std::uint64_t> pin_waits{0};  // on_local_message waited for a pin (link moving)
  // Local messages the served subscriptions lost before the bridge read them (their publisher's
  // shared-memory ring lapped the bridge), summed by note_local_drops.
  std::atomic<std::uint64_t> lost_local{0};
  // Messages to peers handed to ZeroMQ by the shm callback itself / by the channel thread
  // from a peer's queue (PeerChannel).
  std::atomic<std::uint64_t> sent_from_callback{0}, sent_from_queue{0};
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
  // topic -> when this bridge first saw `demand` hold it (refresh_view): its age goes with
  // each "want" line (wire::Control::want_age_ms).
  std::map<std::string, Clock::time_point> demand_began;
  std::map<std::string, bool> published;        // topic -> some local non-bridge publisher is large
  std::map<std::string, std::uint32_t> kept;     // topic -> largest PublisherOptions::history of them
  // topic -> the lcm-gen type its local non-bridge publishers announce, when they all announce
  // the same one (raw publishers and conflicting types: absent).
  std::map<std::string, wire::Control::TopicType> typed;
  std::set<std::string> sticky_large;           // topics once seen large (never go back)
  bool channel_subscribers = false;             // a local participant has FLAG_CHANNELS

  // Control thread only.
  std::map<std::string, std::unique_ptr<Served>> served;
  std::set<std::string> no_channel_logged;
  // Topic -> when a peer's host began to want it (reconcile; control thread): the earliest
  // Peer::want_since of the peers that want it. A topic served later, once a publisher of
  // this host appears, is read from that time on (SubscriberOptions::since): the publisher's
  // first messages, published before the demand reached this bridge, still go. Never before
  // what an earlier subscription of the topic read (served_end) or before this bridge
  // started (a restarted bridge's predecessor forwarded those): no message goes twice.
  std::map<std::string, Clock::time_point> wanted_since;
  std::map<std::string, Clock::time_point> served_end;  // topic -> when its subscription ended
  const Clock::time_point started = Clock::now();
  std::set<std::int64_t> other_bridges_warned;  // participant ids of other bridges on this host
  bool catalogue_cut_logged = false, announce_cut_logged = false, demand_cut_logged = false;

  std::mutex repub_mu;
  std::map<std::string, std::shared_ptr<Republisher>> repubs;

  Impl(Config c, RuntimeOptions o);

  // A Config built in code (not by load_config) gets the same limits.
  static Config check_limits(Config c);
  // ZMTP heartbeats only clean up connections nobody talks on any more (e.g. a peer's, after
  // it failed over): link liveness comes from our own pings, and unacknowledged data on a dead
  // link is cut by TCP_MAXRT. So they are slow, and cost the link almost nothing.
  void common_options(zmq::socket_t& s);
  void client_options(zmq::socket_t& s, const Peer& p);
  void server_options(zmq::socket_t& s);
  void bind_all(zmq::socket_t& s, int port);
  std::unique_ptr<zmq::socket_t> make_data_dealer(const Peer& p, const Channel& ch, const Link& l);
  void start();
  static std::string fmt_list(const std::vector<std::string>& v);
  void stop();
  void count_bad(const std::string& why);
  // Which link of `p` the address belongs to (-1 if none).
  static int link_of(const Peer& p, const char* address);
  static const char* peer_address(zmq::message_t& m);
  // The connection's authenticated user id (the peer name the ZAP handler assigned, with or
  // without CURVE) is `claimed`. False when it differs or the message has none.
  bool authentic(zmq::message_t& m, const std::string& claimed);
  // That user id for a log line ("?" when none).
  static std::string user_of(zmq::message_t& m);
  // The largest keep last N a republisher of `topic` takes from peers: the max_keep of its
  // channel (0 when no channel carries it).
  std::uint32_t max_keep_of(const std::string& topic) const;
  void zap_loop();
  void on_local_message(Served& s, const RawMessage& m);
  zmq::message_t retained_payload(Served& s, const RawMessage& m, const std::size_t* targets, std::size_t n);
  std::optional<RetainedBytes> wait_for_pin(PinWatch& w, const RawMessage& m);
  void channel_loop(Channel& ch);
  void flush(Channel& ch, Peer& p);
  // Sends one message on pc's dealer without blocking (pc.sock_mu held, dealer set). Returns
  // false when the socket would block or failed (logged): the caller queues it again.
  bool send_now(Channel& ch, Peer& p, PeerChannel& pc, Outgoing& out);
  void receive_data(Channel& ch);
  // Channel thread: republishes what pc's receiving order released and counts what it gave up on.
  void deliver_received(Channel& ch, PeerChannel& pc, datapath::RxOrder<Incoming>::Out& out);
  // Channel thread: gives up on held messages whose hold is due, or whose gap's link is down.
  // Returns the earliest time a hold of this channel is due (Clock::time_point::max(): none).
  Clock::time_point expire_held(Channel& ch, Clock::time_point now);
  // Channel threads: into this host's shared memory.
  void republish(const std::string& topic, const zmq::message_t& payload, std::uint32_t keep);
  // Makes the topic's republisher with keep last `history`, or remakes it when the type the
  // peers give the topic (type_of_locked) differs, or (`remake_for_history`) its keep differs;
  // a remade one keeps its keep otherwise. view_mu, repub_mu not held.
  std::shared_ptr<Republisher> ensure_republisher(const std::string& topic, std::uint32_t history,
                                                  bool remake_for_history);
  std::uint32_t keep_of_locked(const std::string& topic) const;  // view_mu held: peers' keep
  // view_mu held: the type up peers give the topic; {0, ""} (raw) when none does or they differ.
  wire::Control::TopicType type_of_locked(const std::string& topic) const;
  void control_loop();
  void refresh_view();
  bool is_large_locked(const std::string& topic) const;
  // Our catalogue (sent to every peer): the large topics local non-bridge participants publish
  // that some channel carries; the first wire::kMaxCatalogue by name. view_mu held.
  std::set<std::string> catalogue_locked();
  // Every heartbeat, on every link of every peer: a ping. On the active link it is marked
  // active (the peer keeps our demand alive) and carries the full state — channels, what this
  // host wants, what we will send it, our catalogue — only when that changed, the link or the peer's
  // instance changed, or a second passed: the idle link carries a few dozen bytes per ping.
  void send_pings();
  // Pings from peers (on our control ROUTER): remember their demand/offers, answer.
  void receive_control();
  void check_hello(const Peer& p, const wire::Control& c);
  void receive_pongs(Peer& p, Link& l);
  void update_links(Clock::time_point now);
  // Subscriptions (what peers want and this host publishes) and republishers.
  void reconcile(Clock::time_point now);
  // Control thread: adds what `s`'s subscription dropped since the last call to lost_local and
  // warns of it (at most once per 5 s per topic; at once with `final`, before it goes).
  void note_local_drops(Served& s, bool final);
  lcmx_msgs::bridge_status_t status() const;
};

}  // namespace lcmx::bridge
