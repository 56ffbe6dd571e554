// The runtime's side of a subscriber: its matches (one per publisher it receives from), the
// queue of intra-process and UDP messages waiting for its executor, and keep-last-N state per
// UDP sender. Owned by SubscriberCore::state. Locks: SubscriberState::mu, taken after
// Pairs::mu and before NodeImpl::mu (docs/ARCHITECTURE.md "Locks").
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

#include "lcmx/core/runtime.hpp"
#include "lcmx/shm/segment.hpp"
#include "lcmx/udpm/udpm.hpp"

namespace lcmx::detail {

class NodeImpl;

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
  udpm::Source foreign_source{};        // foreign: that sender's address
  // foreign: steady_clock time (ns since its epoch) of its last datagram, for expiry.
  std::atomic<std::int64_t> foreign_seen_ns{0};
  // The publisher left: the executor reads what it committed, then drops the match.
  std::atomic<bool> retiring{false};
};

struct SubscriberState {
  // Strong: the node lives while a subscriber does. The cycle node->subs->state->node is
  // broken by remove_subscriber() (the Subscriber handle's destructor).
  std::shared_ptr<NodeImpl> node;
  std::string node_name;
  // shm::monotonic_ns() when the subscription began (a channel subscription's child: when the
  // channel subscription began): a publisher it matches later is read from the messages it
  // committed since then, as far as its ring holds them (the start-up race, Reader::open).
  std::uint64_t since_ns = 0;

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

// Pushes an intra-process item to a subscriber's queue (drop oldest when full) and wakes
// its node.
void push_intra(SubscriberCore& sub, IntraItem item);

}  // namespace lcmx::detail
