// Pairs: this participant's endpoints (nodes, publishers, subscribers, channel subscriptions)
// and every publisher -> subscriber pair they take part in, with its path (docs/ARCHITECTURE.md
// "Path selection"): intra-process pairs, shm pairs with publishers of this host, UDP pairs
// with publishers of other hosts and neighbours, and stock LCM senders ("foreign" matches).
// It also hands the messages the front door received over UDP to the subscribers matched with
// their sender, and keep-last-N replays to the subscriber they are for.
//
// What it reads: the PeerTable (what other participants announce), the TopicPolicy (classes),
// and it asks DeathWatch to watch writers in other pid namespaces and Replays to send a
// publisher's kept messages to a subscriber that matched late.
//
// Threads: every public member is thread-safe and takes mu_. Lock order: mu_ ->
// SubscriberState::mu -> NodeImpl::mu; mu_ -> PublisherImpl::publish_mu (keep last N) /
// intra_mu; PeerTable, TopicPolicy, DeathWatch, Replays locks are leaves taken under mu_.
// Methods that change pairs return an Outcome: the Events to emit and whether this
// participant's announced state changed; the caller emits and announces with mu_ released.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "death_watch.hpp"
#include "lcmx/core/runtime.hpp"
#include "lcmx_msgs/beacon_t.hpp"
#include "lcmx_msgs/history_t.hpp"
#include "peers.hpp"
#include "publisher_impl.hpp"
#include "replays.hpp"
#include "topic_policy.hpp"

namespace lcmx::detail {

// Node::subscribe_channels: the filter and the per-channel raw subscribers made from it.
struct ChannelSubscriptionCore {
  std::function<bool(const std::string&)> filter;
  std::shared_ptr<const std::function<void(const RawMessage&)>> callback;
  SubscriberOptions options;
  std::size_t max_channels = 0;
  std::shared_ptr<NodeImpl> node;  // strong, like SubscriberState::node
  std::uint64_t since_ns = 0;      // shm::monotonic_ns() at subscribe_channels: its children's since
  // Guarded by Pairs::mu_.
  std::map<std::string, std::shared_ptr<SubscriberCore>> children;
  std::set<std::string> declined;  // names the filter refused (a cache, cleared when large)
  std::uint64_t refused = 0;       // accepted but over max_channels
  bool removed = false;
};

class Pairs {
 public:
  struct Outcome {
    std::vector<Event> events;
    bool announce = false;  // our endpoints or matches changed: announce now
  };
  // Everything it needs is fixed at construction and outlives it (the runtime's).
  struct Context {
    const RuntimeOptions& options;
    std::uint64_t participant_id;
    PeerTable& peers;
    TopicPolicy& policy;
    DeathWatch& deaths;
    Replays& replays;
  };
  explicit Pairs(Context context);

  std::uint64_t new_endpoint_id() { return next_id_.fetch_add(1); }

  // ---- this participant's endpoints
  Outcome add_node(const std::shared_ptr<NodeImpl>& node);
  Outcome add_publisher(PublisherImpl* pub);
  Outcome remove_publisher(PublisherImpl* pub);
  Outcome add_subscriber(const std::shared_ptr<SubscriberCore>& sub);
  Outcome remove_subscriber(const SubscriberCore* sub);
  // Node::subscribe_channels: registers `p` and subscribes every channel known now.
  Outcome add_channel_subscription(const std::shared_ptr<ChannelSubscriptionCore>& p);
  // Unregisters `p`; returns its subscribers (the caller removes them, with no lock held).
  std::vector<std::shared_ptr<SubscriberCore>> remove_channel_subscription(ChannelSubscriptionCore* p);
  std::vector<std::pair<std::string, std::shared_ptr<SubscriberCore>>> channel_children(
      const ChannelSubscriptionCore& p);
  std::uint64_t channel_refused(const ChannelSubscriptionCore& p);
  std::vector<std::shared_ptr<NodeImpl>> live_nodes();

  // ---- other participants
  // A peer changed (PeerTable::apply's delta): re-matches the topics it touched, and only
  // those. `sources_local`: whether an address is one of this host's (a peer's mirror).
  Outcome on_peer(const PeerTable::Delta& delta, const lcmx_msgs::beacon_t& now,
                  const std::function<bool(std::uint32_t)>& is_local_address);
  // DeathWatch said these writers died: their publishers are gone now (or, `grew`, moved on).
  Outcome writers_died(const std::vector<DeathWatch::Dead>& dead);

  // ---- the receive path (front door, recv_mu held)
  using Target = std::pair<std::shared_ptr<SubscriberCore>, std::shared_ptr<PairCounters>>;
  // A message from `sender` (0: not a participant) on the vehicle group or the host-local
  // group: the subscribers matched with it, in `targets`. A stock sender (foreign) is matched
  // with every subscriber of the channel that takes its type, bounded per subscriber.
  Outcome deliver_udp(bool vehicle, std::int64_t sender, const udpm::Source& source,
                      const udpm::Message& m, std::vector<Target>& targets);
  // A keep-last-N replay received from `source`: taken only if addressed to one of our
  // subscribers, matched with its publisher over UDP, and sent from that publisher's socket
  // on that group. Returns what to queue for the subscriber (oldest first).
  std::vector<std::pair<Target, std::shared_ptr<const Bytes>>> accept_history(
      bool vehicle, const udpm::Source& source, const lcmx_msgs::history_t& h);
  // UDP loss of participant `sender` (sequence gaps, settled at its beacon): counted in the
  // drops of our subscribers matched with it over UDP when it publishes one channel. Returns
  // the channels of it we receive.
  std::vector<std::string> charge_loss(std::int64_t sender, const std::set<std::string>& channels,
                                       std::uint64_t lost);
  // Foreign matches (stock LCM senders) silent for `idle`: removed (bounded memory and
  // beacons under a flood of spoofed sources). Returns whether any went.
  Outcome expire_foreign(std::chrono::steady_clock::duration idle);

  // ---- what the receive filters take (FrontDoor::update_filters_locked) and markers list
  struct UdpWants {
    bool all = false;                // a channel-pattern subscription: every channel
    std::set<std::string> channels;  // else: the channels of our subscribers
  };
  UdpWants udp_wants();
  // The channels our publishers send on the vehicle group (`vehicle`) or the host-local group
  // to subscribers of other processes that read them there (udp pairs: other hosts;
  // neighbours).
  std::set<std::string> udp_read_channels(bool vehicle);

  // ---- keep last N over UDP: a publisher's kept encodings for a replay (Replays::send)
  struct Kept {
    std::string channel;
    std::vector<PublisherImpl::KeptUdp> messages;
  };
  std::optional<Kept> kept_for_replay(std::uint64_t publisher, bool vehicle);

  // ---- what this participant announces: nodes, endpoints, matches (build_beacon)
  // Fills b.nodes / b.endpoints / FLAG_CHANNELS for `scope`; `rate(id, count)` gives an
  // endpoint's rate. Statistics are read as they are.
  void describe(bool vehicle, lcmx_msgs::beacon_t& b,
                const std::function<double(std::uint64_t, std::uint64_t)>& rate);

 private:
  // mu_ held in every *_locked helper; they append what happened to `out`.
  void match_local_locked(PublisherImpl& pub, SubscriberCore& sub, Outcome& out);
  void sync_remote_locked(SubscriberCore& sub, Outcome& out);
  void count_remote_locked(PublisherImpl& pub, Outcome& out);
  void update_bridges_locked(Outcome& out);
  void expand_locked(const std::string& channel, Outcome& out);
  void report_mismatch_locked(std::uint64_t local_endpoint, std::uint64_t remote_participant,
                              std::uint64_t remote_endpoint, const std::string& channel,
                              const std::string& text, std::vector<std::string>& errors,
                              Outcome& out);
  std::vector<std::shared_ptr<SubscriberCore>> subscribers_of_locked(const std::string& channel);
  std::vector<PublisherImpl*> publishers_of_locked(const std::string& channel);
  std::uint64_t match_versions_locked();

  const Context ctx_;
  std::atomic<std::uint64_t> next_id_{1};

  std::mutex mu_;  // guards everything below
  std::map<std::uint64_t, PublisherImpl*> pubs_;
  std::map<std::uint64_t, std::shared_ptr<SubscriberCore>> subs_;
  std::multimap<std::string, std::uint64_t> pubs_by_channel_, subs_by_channel_;
  std::vector<std::weak_ptr<NodeImpl>> nodes_;
  std::vector<std::shared_ptr<ChannelSubscriptionCore>> channel_subs_;
  // Consecutive failures to open a same-host publisher's segment, per (subscriber,
  // participant, endpoint); the error Event goes out at kOpenFailuresReported.
  static constexpr int kOpenFailuresReported = 3;
  std::map<std::tuple<std::uint64_t, std::uint64_t, std::uint64_t>, int> open_failures_;
  std::set<std::tuple<std::uint64_t, std::uint64_t, std::uint64_t>> mismatches_reported_;
  // Shm publishers whose writer died (DeathWatch) while their beacon has not expired yet.
  std::set<std::pair<std::uint64_t, std::uint64_t>> dead_publishers_;
  // Foreign (stock LCM) senders matched with a subscriber: at most kMaxForeign per subscriber;
  // their last datagram's time lives in the Match (foreign_seen).
  static constexpr std::size_t kMaxForeign = 64;
  std::uint64_t foreign_refused_ = 0;
  std::chrono::steady_clock::time_point foreign_refused_logged_{};
};

}  // namespace lcmx::detail
