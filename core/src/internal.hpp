// core internals: runtime registry, node executors, per-subscriber state.
// Lock order (never take them the other way round):
//   RuntimeImpl::recv_mu -> (discovery: Discovery::Impl::deliver_mutex, held while it calls
//   on_participant) -> RuntimeImpl::mu -> SubscriberState::mu -> NodeImpl::mu
//   PublisherImpl::publish_mu -> PublisherImpl::intra_mu -> SubscriberState::mu
//   RuntimeImpl::recv_mu -> ClientCore::mu (a service client's SubscriberCore::udp_inline runs
//   in on_udp; nothing under ClientCore::mu takes recv_mu)
#pragma once

#include <atomic>
#include <condition_variable>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <thread>
#include <tuple>
#include <vector>

#include "lcmx/core/runtime.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "lcmx/shm/liveness.hpp"
#include "lcmx/shm/segment.hpp"

namespace lcmx::detail {

class NodeImpl;
class RuntimeImpl;

// One publisher as seen by one subscriber.
struct Match {
  std::uint64_t publisher_participant = 0;
  std::uint64_t publisher_endpoint = 0;
  Path path = Path::intra;
  std::shared_ptr<PairCounters> stats = std::make_shared<PairCounters>();
  std::unique_ptr<shm::Reader> reader;  // shm path; used by the executor only
  // Samples found not intact (ReadSample::intact): counted in stats->drops with the
  // reader's. Executor only (the subscriber's `busy` held).
  std::uint64_t torn = 0;
  bool foreign = false;                 // udp from a non-lcmx sender (stock LCM program)
  // The publisher left: the executor reads what it committed, then drops the match.
  std::atomic<bool> retiring{false};
};

struct SubscriberState {
  // Strong: the node lives while a subscriber does. The cycle node->subs->state->node is
  // broken by remove_subscriber() (the Subscriber handle's destructor).
  std::shared_ptr<NodeImpl> node;
  std::string node_name;

  std::mutex mu;                        // guards queue, matches, version, errors
  std::condition_variable matched_cv;   // matches changed (wait_for_publishers)
  std::deque<IntraItem> queue;          // intra-process messages waiting for the executor
  // Keep last N over UDP (RuntimeImpl::on_history), per sender socket ("ip:port", whether
  // its participant is known yet or not): the sequence number of the first message delivered
  // live, and one past the newest sent message a replay delivered (live messages below it
  // came in the replay). At most kMaxUdpSources (cleared beyond: a replay may then repeat
  // what came live before).
  struct UdpSource {
    std::optional<std::uint32_t> first_live, replay_floor;
    // The participant sending from that address (0: not known yet). Another one there (a
    // restart on the same port, a stock program) starts the entry over.
    std::uint64_t participant = 0;
    void sender(std::uint64_t who) {
      if (participant != 0 && participant != who) *this = {};
      if (who != 0) participant = who;
    }
  };
  std::map<std::string, UdpSource> udp_sources;
  static constexpr std::size_t kMaxUdpSources = 4096;
  // The entry of `source` ("ip:port"), sent from by `participant` (0: unknown). `mu` held.
  UdpSource& udp_source(const std::string& source, std::uint64_t participant) {
    if (udp_sources.size() >= kMaxUdpSources && !udp_sources.count(source)) udp_sources.clear();
    auto& s = udp_sources[source];
    s.sender(participant);
    return s;
  }
  // !queue.empty(), written under `mu` (release), read by the executor without it (acquire),
  // so a wake-up with nothing queued and no match change takes no lock (NodeImpl::poll_one).
  std::atomic<bool> queued{false};
  std::vector<std::shared_ptr<Match>> matches;
  std::atomic<std::uint64_t> version{0};  // +1 whenever matches change (written under `mu`)
  std::vector<std::string> errors;
  std::uint64_t retired_drops = 0;      // drops of matches already forgotten

  // Executor side. `busy` is held (true) while one executor thread polls this subscriber:
  // it serialises callbacks and guards `snapshot`.
  std::atomic<bool> busy{false};
  std::atomic<bool> removed{false};
  std::atomic<std::thread::id> running_on{};  // thread running a callback now (for self-removal)
  std::vector<std::shared_ptr<Match>> snapshot;
  std::uint64_t snapshot_version = ~0ull;
};

class NodeImpl : public std::enable_shared_from_this<NodeImpl> {
 public:
  NodeImpl(std::shared_ptr<RuntimeImpl> rt, std::string name, NodeOptions options);
  ~NodeImpl();
  void start();
  void stop();

  void add(const std::shared_ptr<SubscriberCore>& sub);
  void remove(const SubscriberCore* sub);
  // Something arrived or changed: wake an executor thread.
  void ring();
  // Makes the current (or next) run_once() return 0 as soon as it has run what is ready.
  // For a manual node run by lcmx's own thread (service clients), which has more to do.
  void interrupt() {
    interrupted.store(true, std::memory_order_seq_cst);
    ring();
  }
  bool stopped() const { return stopping.load(std::memory_order_acquire); }
  // Runs ready callbacks, waiting up to `timeout` for some. Returns callbacks run.
  std::size_t run_once(std::chrono::nanoseconds timeout);

  const std::shared_ptr<RuntimeImpl> runtime;
  const std::string name;
  const NodeOptions options;
  const std::uint64_t uid;  // unique in the process, never reused (unlike the address)

  // A fault the executor survived (an exception on its thread): log + Event::Kind::error.
  void report_fault(const std::string& what) noexcept;
  std::uint64_t fault_count() const {
    std::lock_guard lock(fault_mu);
    return faults;
  }

 private:
  mutable std::mutex fault_mu;
  std::uint64_t faults = 0;
  std::chrono::steady_clock::time_point last_fault_report{};
  std::size_t poll_all(std::vector<std::shared_ptr<SubscriberCore>>& subs);
  std::size_t poll_one(SubscriberCore& sub);
  std::size_t poll_intra(SubscriberCore& sub);
  void refresh(std::vector<std::shared_ptr<SubscriberCore>>& local, std::uint64_t& version);

  std::mutex mu;
  std::vector<std::shared_ptr<SubscriberCore>> subs;
  std::atomic<std::uint64_t> subs_version{0};
  // Blocks in epoll on the UDP sockets + wake_fd instead of futex_waitv (see run_once).
  // Returns false if this thread cannot (another thread of the node waits so already).
  bool wait_udp(std::uint32_t bell, std::chrono::steady_clock::time_point deadline);

  std::atomic<std::uint32_t> doorbell{0};
  std::atomic<int> sleepers{0};      // threads blocked (futex or epoll) after reading doorbell
  std::atomic<int> fd_sleepers{0};   // of which in epoll: ring() must write wake_fd
  std::atomic<bool> stopping{false};
  std::atomic<bool> interrupted{false};
  // WaitStrategy::adaptive: steady_clock time (ns since its epoch) when a run_once() pass last
  // handled a message; relaxed (a stale value only shortens or lengthens one spin).
  std::atomic<std::int64_t> last_work_ns{0};
  std::vector<std::thread> threads;
  // UDP waiting (one thread of the node at a time, `fd_waiter` held): an eventfd for ring()
  // and an epoll set with it and the runtime's group sockets. Created on first use.
  std::atomic<bool> fd_waiter{false};
  int wake_fd = -1;
  int epoll_fd = -1;
};

class PublisherImpl;

// Node::subscribe_channels: the filter and the per-channel raw subscribers made from it.
struct ChannelSubscriptionCore {
  std::function<bool(const std::string&)> filter;
  std::shared_ptr<const std::function<void(const RawMessage&)>> callback;
  SubscriberOptions options;
  std::size_t max_channels = 0;
  std::shared_ptr<NodeImpl> node;  // strong, like SubscriberState::node
  // Guarded by RuntimeImpl::mu.
  std::map<std::string, std::shared_ptr<SubscriberCore>> children;
  std::set<std::string> declined;  // names the filter refused (a cache, cleared when large)
  std::uint64_t refused = 0;       // accepted but over max_channels
  bool removed = false;
};

class RuntimeImpl : public std::enable_shared_from_this<RuntimeImpl> {
 public:
  explicit RuntimeImpl(RuntimeOptions options);
  ~RuntimeImpl();
  // Opens the groups, starts discovery (both scopes) and the UDP receive thread.
  void start_transports();
  // Goodbye, then stop every node's executor. Idempotent. Endpoints become inert.
  void shutdown();

  std::uint64_t new_endpoint_id() { return next_id.fetch_add(1); }
  void add_publisher(PublisherImpl* pub);
  void remove_publisher(PublisherImpl* pub);
  void add_subscriber(const std::shared_ptr<SubscriberCore>& sub);
  void remove_subscriber(const SubscriberCore* sub);
  void add_node(const std::shared_ptr<NodeImpl>& node);
  // Node::subscribe_channels: registers `p` and subscribes every channel known now.
  void add_channel_subscription(const std::shared_ptr<ChannelSubscriptionCore>& p);
  // Unregisters `p`; returns its subscribers (the caller removes them, with no lock held).
  std::vector<std::shared_ptr<SubscriberCore>> remove_channel_subscription(ChannelSubscriptionCore* p);
  std::vector<std::pair<std::string, std::shared_ptr<SubscriberCore>>> channel_children(
      const ChannelSubscriptionCore& p);
  std::uint64_t channel_refused(const ChannelSubscriptionCore& p);
  // Announce now. Takes no lock: publishers call it with publish_mu held, and the beacon
  // builder takes publish_mu under mu.
  void changed();
  void emit(std::vector<Event> events);

  const RuntimeOptions options;
  const std::uint64_t participant_id;
  const std::uint64_t host;
  std::string own_shm_prefix;   // "lcmx_<host id hex>_"
  std::string shm_base_prefix;  // own_shm_prefix + shm::process_tag() + "_" ("<pid>n<pidns>_")
  std::shared_ptr<udpm::Group> local_group;    // host-local group (always)
  std::shared_ptr<udpm::Group> vehicle_group;  // vehicle group (null: single host)
  // Configured class, else large when a bridge of this host carries the channel, else automatic.
  // Takes only carried_mu (a leaf): callable with publish_mu held.
  TopicClass class_of(const std::string& channel) const;
  // A Message Bridge runs on this host (or this participant is one): large topics go to
  // other hosts through it, never as UDP fragments.
  bool bridge_on_host() const { return options.bridge || bridge_seen.load(); }
  // RuntimeOptions::mirror, or a mirror_channels glob matches.
  bool mirrored(const std::string& channel) const;

  std::mutex event_mu;
  std::function<void(const Event&)> on_event;
  // lcmx's own listeners (service clients): called for every event before on_event, on the
  // thread that emits it, with no lcmx lock held except possibly discovery's delivery lock.
  // A tap must be quick and must not call into the runtime (set a flag, interrupt a node).
  // It may still run once after remove_event_tap() returns: capture weak pointers.
  // Whether a participant of another process is known (its beacon not expired) and announces
  // endpoint `endpoint`. Takes mu. For service clients: a remote server whose pair changed
  // path (UDP -> bridge) is still there.
  bool endpoint_announced(std::uint64_t participant, std::uint64_t endpoint);
  // Whether `participant` (this one: a subscriber of this process; another: its beacon, not
  // expired, of either scope or a neighbour's) announces a subscriber of `channel`. Takes mu.
  // For service servers: a reply channel is made only for a client that subscribes to it.
  // Defined in core/src/service_hook.cpp.
  bool subscriber_announced(std::uint64_t participant, const std::string& channel);
  std::uint64_t add_event_tap(std::function<void(const Event&)> tap);
  void remove_event_tap(std::uint64_t id);
  // Housekeeping (service servers forget gone clients): called about once a second on the
  // receive thread with no lcmx lock held, so it may call into the runtime (destroy a
  // publisher). Must be quick. May still run once after remove_housekeeping() returns:
  // capture weak pointers. Guarded by event_mu.
  std::uint64_t add_housekeeping(std::function<void()> job);
  void remove_housekeeping(std::uint64_t id);
  std::map<std::uint64_t, std::shared_ptr<const std::function<void()>>> housekeeping;
  void run_housekeeping();  // receive thread, no lock held
  std::map<std::uint64_t, std::shared_ptr<const std::function<void(const Event&)>>> event_taps;  // event_mu
  std::uint64_t last_tap = 0;  // event_mu

  // UDP receive, shared by the receive thread and idle node executors (see receive_loop).
  // Drains both groups and dispatches what arrived to the subscribers' queues. Beacons are
  // handled on the receive thread only: another thread copies them for it and wakes it.
  // Takes recv_mu (blocking, or only if free when `try_only`); call it with no lock held.
  // Returns false if try_only and another thread was draining.
  bool drain_udp(bool try_only = false);
  // Adds the group sockets to `epfd` (EPOLLEXCLUSIVE: a datagram wakes one waiting thread)
  // ahead of the receive thread, which only gets datagrams when no executor waits for them.
  void add_udp_waiter(int epfd);

 private:
  lcmx_msgs::beacon_t build_beacon(std::int8_t scope);
  void on_participant(std::int8_t scope, discovery::Change change, const discovery::Participant& p);
  void receive_loop();
  void on_udp(std::int8_t scope, const udpm::Message& m);
  // Locked helpers (mu held). They append what happened to `events`.
  void match_local_locked(PublisherImpl& pub, SubscriberCore& sub, std::vector<Event>& events);
  void sync_remote_locked(SubscriberCore& sub, std::vector<Event>& events);
  void count_remote_locked(PublisherImpl& pub, std::vector<Event>& events);
  // Keep last N over UDP (docs/ARCHITECTURE.md "Keep last N"): count_remote_locked queues a
  // replay for each subscriber of another host (or a neighbour) newly matched with a
  // publisher that keeps messages; send_replays() sends them (mu not held); on_history()
  // hands a replay addressed to one of our subscribers to it, without what it got live.
  struct ReplayJob {
    std::uint64_t publisher = 0;
    std::int64_t participant = 0, endpoint = 0;  // the subscriber
    bool vehicle = false;                        // vehicle group, else host-local (neighbour)
  };
  std::vector<ReplayJob> replay_jobs;  // guarded by mu
  void send_replays();
  void on_history(const udpm::Message& m);
  void update_bridges_locked();
  // Channel subscriptions: subscribes `channel` for every one whose filter accepts it and
  // that has no subscriber of it yet. Sets announce_pending when it did.
  void expand_locked(const std::string& channel, std::vector<Event>& events);
  void report_neighbour(const lcmx_msgs::beacon_t& b);  // takes mu
  // Consecutive failures to open a same-host publisher's segment, per (subscriber,
  // participant, endpoint); the error Event goes out at kOpenFailuresReported. Guarded by mu.
  static constexpr int kOpenFailuresReported = 3;
  std::map<std::tuple<std::uint64_t, std::uint64_t, std::uint64_t>, int> open_failures;
  std::set<std::int64_t> neighbours_reported;  // guarded by mu
  // Fast death notice for shm publishers in another pid namespace (a container sharing
  // /dev/shm: no pidfd for them, discovery leaves them to their lease): shm::OwnerWatch on
  // the segment we read, its fd in rx_epoll (receive thread). A publisher whose writer died
  // is "dead": its matches retire at once (publisher_unmatched) and its stale beacon does not
  // match it again. Guarded by mu; owner_watch null if it could not be set up (lease only).
  struct WatchedPublisher {
    std::uint64_t participant = 0, endpoint = 0;
    std::string segment;
  };
  std::unique_ptr<shm::OwnerWatch> owner_watch;
  std::map<std::uint64_t, WatchedPublisher> owner_keys;               // watch key -> publisher
  std::set<std::pair<std::uint64_t, std::uint64_t>> owner_watched;    // (participant, endpoint)
  std::set<std::pair<std::uint64_t, std::uint64_t>> dead_publishers;  // (participant, endpoint)
  const std::uint64_t own_pid_namespace;
  void watch_owner_locked(const lcmx_msgs::beacon_t& b, const lcmx_msgs::endpoint_t& e);
  void forget_owner_locked(std::uint64_t participant);
  void on_owner_death();  // receive thread, no lock held
  void report_mismatch_locked(std::uint64_t local_endpoint, std::uint64_t remote_participant,
                              std::uint64_t remote_endpoint, const std::string& channel,
                              const std::string& text, std::vector<std::string>& errors,
                              std::vector<Event>& events);

  std::atomic<std::uint64_t> next_id{1};
  std::mutex mu;
  std::map<std::uint64_t, PublisherImpl*> pubs;
  std::map<std::uint64_t, std::shared_ptr<SubscriberCore>> subs;
  std::vector<std::weak_ptr<NodeImpl>> nodes;
  std::vector<std::shared_ptr<ChannelSubscriptionCore>> channel_subs;
  std::map<std::int64_t, lcmx_msgs::beacon_t> remotes;          // same-host participants
  std::map<std::int64_t, lcmx_msgs::beacon_t> vehicle_remotes;  // participants of other hosts
  std::map<std::string, std::int64_t> host_sources;     // "ip:port" of same-host participants
  std::map<std::string, std::int64_t> vehicle_sources;  // "ip:port" -> participant, other hosts
  // Same-host participants' host-local ports: their mirror comes from that port and the address
  // of the interface the group routes to (an address of this host), not from local_source.
  std::map<std::uint16_t, std::int64_t> host_ports;  // network order -> participant
  // Neighbours: participants of this network namespace with another host id (another
  // /dev/shm: no shared memory). Without a vehicle group they are reached over UDP on the
  // host-local group (path udp); with one, over the vehicle group like any other host.
  std::map<std::int64_t, lcmx_msgs::beacon_t> neighbour_remotes;
  std::map<std::string, std::int64_t> neighbour_sources;  // "ip:port" -> participant
  std::map<std::uint16_t, std::int64_t> neighbour_ports;  // network order -> participant
  std::set<std::uint32_t> host_addresses;            // this host's IPv4 addresses (network order)
  // Receive thread (recv_mu held): follows the host-local group's route, re-reads host_addresses.
  void refresh_routes();
  void warn_lcm_default_url() const;  // start_transports
  std::chrono::steady_clock::time_point routes_checked{};
  // Receive thread (recv_mu held), with refresh_routes: warns when a group dropped messages
  // that no sequence gap reports yet - incomplete (fragments lost) or over the reassembly
  // limit - e.g. a stock sender's large messages that never complete.
  struct GroupDrops {
    std::uint64_t incomplete = 0, oversize = 0;  // last logged counters
    std::chrono::steady_clock::time_point logged{};
  };
  GroupDrops local_drops, vehicle_drops;
  void check_group_drops(const udpm::Group& group, GroupDrops& last, const char* which);
  std::set<std::tuple<std::uint64_t, std::uint64_t, std::uint64_t>> mismatches_reported;
  // An endpoint's rate in beacons: messages over at least kRateWindow. Beacons also go out
  // early (a query, a newcomer), and one message over such a short gap read as 7.5-15 Hz for
  // a steady 10 Hz topic.
  static constexpr std::chrono::seconds kRateWindow{2};
  struct RateState {
    std::uint64_t count = 0;                     // at `when`
    std::chrono::steady_clock::time_point when{};
    double hz = 0;                               // over the last whole window
  };
  std::map<std::uint64_t, RateState> rates;
  std::atomic<bool> bridge_seen{false};  // a same-host participant has FLAG_BRIDGE (mu to write)
  mutable std::mutex carried_mu;          // leaf lock, guards carried
  std::vector<std::string> carried;       // globs carried by this host's bridges (and ours)
  std::atomic<std::int64_t> revision{0};  // atomic: changed() is called under publish_mu
  std::atomic<bool> stopped{false};
  std::atomic<bool> announce_pending{false};
  std::unique_ptr<discovery::Discovery> disco;          // host scope
  std::unique_ptr<discovery::Discovery> disco_vehicle;  // vehicle scope (null: single host)
  std::thread rx_thread;
  int rx_wake_fd = -1;
  int rx_epoll = -1;  // rx_wake_fd + the group sockets (EPOLLEXCLUSIVE, last in their queues)
  std::mutex rx_epoll_mu;  // serialises re-registrations of the sockets in rx_epoll
  // Whoever drains holds recv_mu: a Group's receive side is used by one thread at a time, and
  // messages are dispatched in arrival order.
  std::mutex recv_mu;
  struct Forwarded {  // a beacon another thread drained, for the receive thread
    std::int8_t scope;
    std::string channel;
    std::vector<std::byte> data;
    udpm::Source source;
    std::uint32_t sequence;
    std::uint32_t lost_before;
  };
  std::vector<Forwarded> forwarded;  // guarded by recv_mu; handled before anything drained later
  // recv_mu held. `handle_beacons`: the receive thread, or a discovery thread reading what is
  // queued before it expires a lease (discovery::Options::drain_before_expiry); beacons are
  // handled here, and those other threads drained first before them. Executors pass false:
  // their beacons go to `forwarded`.
  void drain_locked(bool handle_beacons);

  // UDP loss per sender socket (issue 15): LCM sequence gaps (udpm::Message::lost_before)
  // count data and beacons alike; the beacon's own sequence tells how many were beacons.
  // Settled at each beacon of the sender: the rest is data it lost, given to the pair when the
  // sender publishes one channel (its beacon's publisher list), else logged as not
  // attributable. Guarded by recv_mu (on_udp runs with it held).
  struct SourceLoss {
    std::uint64_t pending = 0;        // sequence numbers missed since the last settlement
    std::uint64_t beacon_credit = 0;  // beacons known lost, not yet matched by a gap
    std::int64_t last_beacon = -1;    // beacon sequence of the sender's last beacon
    std::uint64_t unattributed = 0;   // data messages lost, sender with several channels
    std::chrono::steady_clock::time_point logged{};
  };
  std::map<std::pair<std::int8_t, std::string>, SourceLoss> source_loss;  // (scope, "ip:port")
  static constexpr std::size_t kMaxSources = 4096;  // source_loss entries (see loss_of)
  SourceLoss& loss_of(std::int8_t scope, const std::string& source);  // recv_mu held
  void settle_loss(std::int8_t scope, const std::string& source, const lcmx_msgs::beacon_t& b,
                   std::uint32_t lost_before);  // recv_mu held, mu not held
  void log_foreign_loss(std::int8_t scope, const std::string& source, std::uint32_t lost);  // recv_mu
};

class PublisherImpl final : public PublisherCore {
 public:
  PublisherImpl(std::shared_ptr<NodeImpl> node, std::string channel, const TypeInfo& type,
                PublisherOptions options);
  ~PublisherImpl() override;

  void publish_ref(const void* object, std::shared_ptr<const void> (*copy)(const void*)) override;
  void publish_shared(std::shared_ptr<const void> object) override;
  void publish_bytes(std::span<const std::byte> data) override;
  shm::WriteLoan loan(std::size_t size) override;
  void publish_loan(shm::WriteLoan&& loan, std::size_t size) override;
  void drop_loan(shm::WriteLoan&& loan) noexcept override;
  std::size_t subscriber_count() const override;
  bool wait_for_subscribers(std::size_t n, std::chrono::milliseconds timeout) const override;
  std::uint64_t published() const override { return published_.load(); }
  PublisherStats stats() const override {
    return {published_.load(), shm_dropped_.load(std::memory_order_relaxed)};
  }
  const std::string& channel() const override { return channel_; }

  // Runtime side (RuntimeImpl::mu held).
  void add_intra(std::shared_ptr<SubscriberCore> sub, std::shared_ptr<PairCounters> stats);
  void remove_intra(const SubscriberCore* sub);
  // Subscribers of other processes: shm (this host), udp (other hosts, vehicle group),
  // local_udp (neighbours, host-local group); unbridged_udp: of the udp ones, those that have
  // no bridge republisher of the topic matched yet (their beacon lists no "bridge" match).
  void set_remote_subscribers(std::size_t shm, std::size_t udp, std::size_t local_udp,
                              std::size_t unbridged_udp);
  bool large() const { return large_.load(); }
  // Large, a bridge of this host carries it, and every subscriber on other hosts is matched
  // with a bridge republisher: other hosts reach it only through the bridges, so the vehicle
  // beacon leaves it out (DESIGN.md "Discovery", scopes).
  bool bridged_only() const;
  // Keep last N (options.history): the kept encodings for a UDP replay to one late subscriber
  // on the vehicle group (vehicle) or the host-local group (a neighbour), oldest first, with
  // the sequence number each was sent with on that group (if it was). Empty when nothing is
  // kept for UDP (history 0, or a large topic a bridge of this host carries). Takes publish_mu.
  struct KeptUdp {
    std::shared_ptr<const Bytes> encoded;
    std::optional<std::uint32_t> sequence;
  };
  std::vector<KeptUdp> kept_for_udp(bool vehicle) const;
  // Subscribers of other processes already given a UDP replay: (participant, endpoint).
  // Guarded by RuntimeImpl::mu.
  std::set<std::pair<std::int64_t, std::int64_t>> replayed;
  // A bridge of this host now carries the topic: it is large from now on (sticky).
  void mark_large();

  const std::shared_ptr<NodeImpl> node;
  const std::uint64_t id;
  // Service clients: the count of matched subscribers changed -> node->interrupt(), so the
  // client's thread (which runs `node`) probes a new server at once.
  std::atomic<bool> interrupt_on_match{false};
  const TypeInfo& type;
  const PublisherOptions options;
  std::string segment_name() const;
  std::vector<std::string> errors;  // guarded by RuntimeImpl::mu

 private:
  struct IntraTarget {
    std::shared_ptr<SubscriberCore> sub;
    std::shared_ptr<PairCounters> stats;
  };
  using Targets = std::vector<IntraTarget>;
  std::shared_ptr<const Targets> targets() const;
  void deliver_intra(const Targets& t, std::shared_ptr<const void> object);
  void check_size(std::size_t size) const;
  // What send_udp() sent: the LCM sequence number used on each group, if it sent there.
  struct UdpSent {
    std::optional<std::uint32_t> vehicle, local;
  };
  struct Written {
    std::shared_ptr<const Bytes> kept;  // the encoding, when kept for UDP replays (keeps_encoding)
    UdpSent sent;
  };
  Written write_encoded(const void* object, std::size_t size, bool shm, bool udp);  // size: encoded_size
  void note_generation();  // publish_mu held

  std::unique_lock<std::mutex> lock_no_loan(const char* what);
  // Keep last N: remembers a published message (publish_mu held). `object`: what the intra
  // path hands over; `encoded`: its encoding when it is kept for UDP replays (else null);
  // `sent`: the sequence numbers it went out with over UDP.
  void keep(std::shared_ptr<const void> object, std::shared_ptr<const Bytes> encoded, UdpSent sent);
  // Whether a message of this size is kept as a private encoding (for UDP replays).
  bool keeps_encoding() const;
  struct Kept {
    std::shared_ptr<const void> object;
    std::shared_ptr<const Bytes> encoded;
    std::optional<std::uint32_t> vehicle_sequence, local_sequence;
  };
  std::deque<Kept> kept_;  // guarded by publish_mu; at most options.history

  std::string channel_;
  mutable std::mutex publish_mu;  // serialises publishers' writes into shm
  // A Loan is out (guarded by publish_mu): other publish calls wait on loan_cv_.
  std::condition_variable loan_cv_;
  bool loan_out_ = false;
  std::thread::id loan_thread_;
  std::optional<shm::Writer> writer_;
  std::string announced_segment_;  // guarded by publish_mu
  mutable std::mutex intra_mu;    // guards intra_, remote_subscribers_
  mutable std::condition_variable subs_cv;
  std::shared_ptr<const Targets> intra_ = std::make_shared<Targets>();
  std::size_t remote_subscribers_ = 0;  // same host (shm) + other hosts (udp)
  std::atomic<std::size_t> udp_subscribers_{0};
  std::atomic<std::size_t> unbridged_udp_subscribers_{0};  // of udp_subscribers_ (set_remote_subscribers)
  std::atomic<std::size_t> local_udp_subscribers_{0};  // neighbours: sent on the host-local group
  std::atomic<bool> large_{false};
  const bool mirrored_;  // RuntimeOptions::mirror / mirror_channels select this channel
  bool warned_large_udp_ = false;        // guarded by publish_mu
  bool warned_mirror_size_ = false;      // guarded by publish_mu
  std::uint64_t udp_send_failures_ = 0;  // guarded by publish_mu
  std::chrono::steady_clock::time_point last_udp_failure_log_{};  // guarded by publish_mu
  std::vector<std::byte> udp_buf_;       // guarded by publish_mu
  // Sends encoded bytes on the vehicle group (and host-local mirror) when wanted.
  UdpSent send_udp(std::span<const std::byte> encoded);
  bool wants_udp(std::size_t size);  // vehicle, mirror or neighbours; publish_mu held
  bool mirrors(std::size_t size);    // the mirror takes a message of this size; publish_mu held
  bool wants_vehicle() const;  // other hosts, over UDP (not while a bridge carries the topic)
  void note_size(std::size_t size);
  std::atomic<std::uint64_t> published_{0};
  // shm::Writer::dropped(): messages no shm subscriber got because every slot was pinned.
  // Written under publish_mu after each shm commit, read by stats() from any thread.
  std::atomic<std::uint64_t> shm_dropped_{0};
};

// The reserved channel of keep-last-N replays (lcmx_msgs::history_t).
inline constexpr const char* kHistoryChannel = "LCMX_HISTORY";
// a comes before b in serial-number order (32-bit LCM sequence numbers). udp_receive.cpp.
bool serial_before(std::uint32_t a, std::uint32_t b);
// Whether an LCM encoding starts with `fingerprint` (big-endian). udp_receive.cpp.
bool fingerprint_is(std::span<const std::byte> data, std::int64_t fingerprint);
// This host's IPv4 addresses, network order (empty if getifaddrs fails). udp_receive.cpp.
std::set<std::uint32_t> local_addresses();

// Pushes an intra-process item to a subscriber's queue (drop oldest when full) and wakes
// its node.
void push_intra(SubscriberCore& sub, IntraItem item);

}  // namespace lcmx::detail
