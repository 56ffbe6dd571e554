// A publisher (core/src/publisher.cpp): its shm Writer, in-process targets, UDP sends and
// keep-last-N. Locks: publish_mu -> intra_mu -> SubscriberState::mu.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>
#include <set>
#include <span>

#include "lcmx/core/runtime.hpp"
#include "lcmx/shm/segment.hpp"
#include "node_impl.hpp"

namespace lcmx::detail {

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
  // no bridge republisher of the topic matched yet (their beacon lists no "bridge" match);
  // unbridged_elsewhere: subscribers of the channel on other hosts with no bridge match,
  // matched with this publisher or not (yet): while there are any, it stays in the vehicle
  // beacon, so that they can find it.
  void set_remote_subscribers(std::size_t shm, std::size_t udp, std::size_t local_udp,
                              std::size_t unbridged_udp, std::size_t unbridged_elsewhere);
  bool large() const { return large_.load(); }
  // Subscribers of other processes that read this publisher over UDP on the vehicle group
  // (`vehicle`: other hosts) or the host-local group (neighbours). Any thread.
  std::size_t udp_readers(bool vehicle) const {
    return vehicle ? udp_subscribers_.load() : local_udp_subscribers_.load();
  }
  // The bits committed with each message into its shared memory (shm::Writer::commit's
  // `flags`): this publisher's class of that very message, which the Message Bridges of this
  // host follow (RawMessage::published_large; docs/bridge.md "One class per message").
  static constexpr std::uint64_t kSlotClassSaid = 1;  // the publisher says (older writers: 0)
  static constexpr std::uint64_t kSlotLarge = 2;      // large: other hosts get it through the bridges
  std::uint64_t slot_flags() const { return kSlotClassSaid | (large_.load() ? kSlotLarge : 0); }
  // Large, a bridge of this host carries it, and every subscriber of the channel on other
  // hosts is matched with a bridge republisher: other hosts reach it only through the bridges,
  // so the vehicle beacon leaves it out (DESIGN.md "Discovery", scopes). A subscriber that
  // starts later on a host without a bridge brings it back (it could not find it otherwise).
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
  // size: encoded_size, already checked and classified (check_size, note_size) by the caller.
  Written write_encoded(const void* object, std::size_t size, bool shm, bool udp);
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
  std::atomic<std::size_t> unbridged_elsewhere_{0};  // set_remote_subscribers
  std::atomic<std::size_t> local_udp_subscribers_{0};  // neighbours: sent on the host-local group
  // Its UDP readers on that group grew: a data marker goes before its next message there, so
  // the new reader counts its loss from it (Markers::baseline). Set by set_remote_subscribers.
  std::atomic<bool> vehicle_marker_due_{false}, local_marker_due_{false};
  std::atomic<bool> large_{false};
  const bool mirrored_;  // RuntimeOptions::mirror / mirror_channels select this channel
  bool warned_large_udp_ = false;        // guarded by publish_mu
  bool warned_unbridged_udp_ = false;    // guarded by publish_mu
  bool warned_mirror_size_ = false;      // guarded by publish_mu
  std::uint64_t udp_send_failures_ = 0;  // guarded by publish_mu
  std::chrono::steady_clock::time_point last_udp_failure_log_{};  // guarded by publish_mu
  std::vector<std::byte> udp_buf_;       // guarded by publish_mu
  // Sends encoded bytes on the vehicle group (and host-local mirror) when wanted.
  UdpSent send_udp(std::span<const std::byte> encoded);
  bool wants_udp(std::size_t size);  // vehicle, mirror or neighbours; publish_mu held
  bool mirrors(std::size_t size);    // the mirror takes a message of this size; publish_mu held
  // Other hosts, over UDP (not while a bridge carries the topic), for a message of `size`.
  bool wants_vehicle(std::size_t size);
  // The start-up window (the publisher's first lease, at least 2 s): subscribers that exist already may not
  // have matched it yet, since its first beacon is on its way. Meanwhile every message is
  // written into its shm ring (a subscriber that matches takes what was committed after its
  // own creation: Reader::open's since), small ones go to the vehicle group too (taken as from
  // a stock sender's socket until its record arrives: Pairs::deliver_udp), and larger ones
  // once a subscriber of another host is known. Costs nothing after. publish_mu held.
  bool in_startup();
  bool startup_ = true;                                    // guarded by publish_mu
  std::chrono::steady_clock::time_point startup_until_{};  // set at construction
  void note_size(std::size_t size);
  std::atomic<std::uint64_t> published_{0};
  // shm::Writer::dropped(): messages no shm subscriber got because every slot was pinned.
  // Written under publish_mu after each shm commit, read by stats() from any thread.
  std::atomic<std::uint64_t> shm_dropped_{0};
};

// The reserved channel of keep-last-N replays (lcmx_msgs::history_t).
inline constexpr const char* kHistoryChannel = "LCMX_HISTORY";
// a comes before b in serial-number order (32-bit LCM sequence numbers). front_door.cpp.
bool serial_before(std::uint32_t a, std::uint32_t b);
// Whether an LCM encoding starts with `fingerprint` (big-endian). front_door.cpp.
bool fingerprint_is(std::span<const std::byte> data, std::int64_t fingerprint);

}  // namespace lcmx::detail
