// RuntimeImpl: one per process (the participant). It owns the transports and the components
// below and wires them; it holds no pairs, peers or datagrams of its own.
//
//   EventHub     events.hpp        Events to the user's callback and lcmx's taps; housekeeping
//   TopicPolicy  topic_policy.hpp  topic classes, the mirror, this host's bridges
//   PeerTable    peers.hpp         other participants, by scope, as discovery tells them
//   Pairs        pairs.hpp         our endpoints and every pair (path selection, delivery)
//   DeathWatch   death_watch.hpp   writers in other pid namespaces (fast death notice)
//   Replays      replays.hpp       keep-last-N replays we send over UDP
//   FrontDoor    front_door.hpp    the receive side of the groups: source checks, dispatch, receive filters
//   Markers      markers.hpp       the data markers this participant sends (UDP loss per channel)
//   discovery::Discovery (x2)      beacons of the host scope and (with a vehicle group) the vehicle scope
//
// Data flow: a datagram enters the FrontDoor, which takes beacons to discovery and messages to
// Pairs; discovery tells RuntimeImpl::on_participant of changes, which applies them to the
// PeerTable and hands the delta to Pairs. Locks, in order (never the other way round):
//   FrontDoor::recv_mu -> Discovery delivery lock -> Pairs::mu -> SubscriberState::mu -> NodeImpl::mu
//   Pairs::mu -> PublisherImpl::publish_mu -> intra_mu -> SubscriberState::mu
//   leaves: PeerTable, TopicPolicy, DeathWatch, Replays, EventHub, HostAddresses
//   FrontDoor::recv_mu -> ClientCore::mu (a service client's SubscriberCore::udp_inline)
#pragma once

#include <atomic>
#include <memory>
#include <mutex>
#include <set>
#include <string>

#include "death_watch.hpp"
#include "events.hpp"
#include "front_door.hpp"
#include "lcmx/core/runtime.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "markers.hpp"
#include "pairs.hpp"
#include "peers.hpp"
#include "replays.hpp"
#include "topic_policy.hpp"

namespace lcmx::detail {

class RuntimeImpl : public std::enable_shared_from_this<RuntimeImpl> {
 public:
  explicit RuntimeImpl(RuntimeOptions options);
  ~RuntimeImpl();
  // Opens the groups, starts discovery (both scopes) and the receive thread.
  void start_transports();
  // Goodbye, then stop every node's executor. Idempotent. Endpoints become inert.
  void shutdown();

  const RuntimeOptions options;
  const std::uint64_t participant_id;
  const std::uint64_t host;
  const std::uint64_t own_pid_namespace;
  std::string own_shm_prefix;   // "lcmx_<host id hex>_"
  std::string shm_base_prefix;  // own_shm_prefix + shm::process_tag() + "_" ("<pid>n<pidns>_")
  std::shared_ptr<udpm::Group> local_group;    // host-local group (always)
  std::shared_ptr<udpm::Group> vehicle_group;  // vehicle group (null: single host)

  EventHub events;
  TopicPolicy policy;
  PeerTable peers;
  DeathWatch deaths;
  Replays replays;
  Pairs pairs;
  std::unique_ptr<FrontDoor> front_door;  // made by start_transports
  Markers markers{participant_id, host};
  // Whether the vehicle Discovery takes the vehicle group's discovery datagrams (its host's
  // speaker, or no vehicle table to follow: Discovery::listening): the front door's receive
  // filter lets them through while it is true. Set by Options::on_listening.
  std::atomic<bool> vehicle_listening{true};

  // Group keys: a key file that changed (its inode, size or mtime) is read again and the
  // group's keys replaced (rotation without a restart, docs/keyed-groups.md). A file that now
  // cannot be read or is not a key leaves the keys as they were (an error Event). Receive
  // thread (every_second).
  struct KeyWatch {
    std::string file;  // empty: the group is unkeyed
    struct stat_sig {
      unsigned long dev = 0, ino = 0;
      long long size = 0, mtime_ns = 0;
      bool operator==(const stat_sig&) const = default;
    } seen;
    bool failed = false;  // the last read failed (reported once until it reads again)
  };

  // ---- for publishers, nodes and the public API
  std::uint64_t new_endpoint_id() { return pairs.new_endpoint_id(); }
  TopicClass class_of(const std::string& channel) const { return policy.class_of(channel); }
  bool bridge_on_host() const { return policy.bridge_on_host(); }
  // Whether this process's vehicle Discovery has heard the whole vehicle once
  // (discovery::Discovery::complete): every subscriber of another host that existed is known
  // and matched. False without a vehicle group. Any thread.
  bool vehicle_complete() const { return disco_vehicle_ && disco_vehicle_->complete(); }
  bool mirrored(const std::string& channel) const { return policy.mirrored(channel); }
  // Announce now. Takes no lock: publishers call it with publish_mu held.
  void changed();
  void emit(std::vector<Event> events_) { events.emit(std::move(events_)); }
  // Emits what Pairs said and announces if it asked. No Pairs lock held.
  void settle(Pairs::Outcome outcome);

  void add_node(const std::shared_ptr<NodeImpl>& node) { settle(pairs.add_node(node)); }
  void add_publisher(PublisherImpl* pub) { settle(pairs.add_publisher(pub)); }
  void remove_publisher(PublisherImpl* pub) { settle(pairs.remove_publisher(pub)); }
  void add_subscriber(const std::shared_ptr<SubscriberCore>& sub) { settle(pairs.add_subscriber(sub)); }
  void remove_subscriber(const SubscriberCore* sub) { settle(pairs.remove_subscriber(sub)); }
  void add_channel_subscription(const std::shared_ptr<ChannelSubscriptionCore>& p) {
    settle(pairs.add_channel_subscription(p));
  }
  std::vector<std::shared_ptr<SubscriberCore>> remove_channel_subscription(ChannelSubscriptionCore* p) {
    return pairs.remove_channel_subscription(p);
  }
  std::vector<std::pair<std::string, std::shared_ptr<SubscriberCore>>> channel_children(
      const ChannelSubscriptionCore& p) {
    return pairs.channel_children(p);
  }
  std::uint64_t channel_refused(const ChannelSubscriptionCore& p) { return pairs.channel_refused(p); }

  // ---- for services and actions (core/src/service.cpp, action.cpp)
  // Whether a participant of another process is known (its beacon not expired) and announces
  // endpoint `endpoint`.
  bool endpoint_announced(std::uint64_t participant, std::uint64_t endpoint) {
    return peers.announced(participant, endpoint);
  }
  std::uint64_t add_event_tap(std::function<void(const Event&)> tap) { return events.add_tap(std::move(tap)); }
  void remove_event_tap(std::uint64_t id) { events.remove_tap(id); }
  std::uint64_t add_housekeeping(std::function<void()> job) { return events.add_housekeeping(std::move(job)); }
  void remove_housekeeping(std::uint64_t id) { events.remove_housekeeping(id); }

  // ---- for node executors waiting for UDP (NodeImpl::wait_udp)
  bool drain_udp(bool try_only = false) { return front_door && front_door->drain(false, try_only); }
  void add_udp_waiter(int epfd) {
    if (front_door) front_door->add_udp_waiter(epfd);
  }

 private:
  lcmx_msgs::beacon_t build_beacon(std::int8_t scope);
  void on_participant(std::int8_t scope, discovery::Change change, const discovery::Participant& p);
  void report_neighbour(const lcmx_msgs::beacon_t& b);
  void warn_lcm_default_url() const;
  void every_second();
  void on_death_fd();
  KeyWatch key_watch_[2];  // [0] host-local, [1] vehicle
  void watch_keys();

  std::atomic<std::int64_t> revision_{0};  // atomic: changed() is called under publish_mu
  std::atomic<bool> stopped_{false};
  std::unique_ptr<discovery::Discovery> disco_;          // host scope
  std::unique_ptr<discovery::Discovery> disco_vehicle_;  // vehicle scope (null: single host)

  // An endpoint's rate in beacons: messages over at least kRateWindow. Beacons also go out
  // early (a query, a newcomer), and one message over such a short gap read as 7.5-15 Hz for a
  // steady 10 Hz topic. Discovery threads (build_beacon), rate_mu_.
  static constexpr std::chrono::seconds kRateWindow{2};
  struct RateState {
    std::uint64_t count = 0;  // at `when`
    std::chrono::steady_clock::time_point when{};
    double hz = 0;  // over the last whole window
    bool used = false;
  };
  std::mutex rate_mu_;
  std::map<std::uint64_t, RateState> rates_;  // endpoint id * 2 + (vehicle scope)

  std::mutex neighbours_mu_;
  std::set<std::int64_t> neighbours_reported_;  // logged once each (bounded)
};

}  // namespace lcmx::detail
