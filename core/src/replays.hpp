// Replays: keep last N over UDP, the sending side (docs/ARCHITECTURE.md "Keep last N"). When a
// subscriber of another host (or a neighbour) first matches a publisher of ours that keeps
// messages, Pairs queues a replay; send() sends them (lcmx_msgs::history_t on LCMX_HISTORY,
// from the publisher's socket on the subscriber's group). The receiving side is
// Pairs::accept_history.
//
// Trust (DESIGN.md "Trust"): beacons are not authenticated, and a forged beacon listing many
// subscriber endpoints (or rotating their ids) would make a publisher multicast its history
// again and again. So a subscriber endpoint gets at most one replay of a publisher per lease
// (a repeat is refused and counted), and a publisher sends at most kMaxPerLease replays per
// lease: the others wait (at most kMaxPending, the oldest dropped and counted beyond) and go
// out in later leases (tick(), once a second), so a program with many subscribers of one
// topic still gets its history, and a flood of forged ones costs at most kMaxPerLease
// multicasts per lease. Refusals are logged at most every 5 s.
//
// Threads: every member is thread-safe; the lock is a leaf (queue() runs under Pairs::mu).
#pragma once

#include <chrono>
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <tuple>
#include <vector>

#include "lcmx/udpm/udpm.hpp"

namespace lcmx::detail {

class Pairs;

class Replays {
 public:
  struct Job {
    std::uint64_t publisher = 0;
    std::int64_t participant = 0, endpoint = 0;  // the subscriber
    bool vehicle = false;                        // vehicle group, else host-local (neighbour)
  };
  static constexpr std::size_t kMaxPerLease = 32;
  static constexpr std::size_t kMaxPending = 4096;

  explicit Replays(std::chrono::milliseconds lease) : lease_(lease) {}

  // Queues a replay: to send now, or pending while its publisher's budget is spent; false
  // (counted) for a subscriber endpoint that got one within the lease.
  bool queue(const Job& job);
  // Moves pending replays whose publisher has budget again to the send queue. Once a second.
  void tick();
  // Sends what is queued: the publisher's kept encodings (Pairs::kept_for_replay) on the
  // subscriber's group. Call with no lcmx lock held. Send failures are logged.
  void send(Pairs& pairs, std::uint64_t participant_id, udpm::Group& local, udpm::Group* vehicle);
  std::uint64_t refused() const;
  std::size_t ready() const;    // queued to send now
  std::size_t waiting() const;  // pending a publisher's budget

 private:
  using Clock = std::chrono::steady_clock;
  const std::chrono::milliseconds lease_;
  mutable std::mutex mu_;  // guards everything below
  std::vector<Job> jobs_;
  std::deque<Job> pending_;
  // (publisher, participant, endpoint) -> last replay queued; publisher -> recent replays.
  std::map<std::tuple<std::uint64_t, std::int64_t, std::int64_t>, Clock::time_point> last_;
  std::map<std::uint64_t, std::vector<Clock::time_point>> recent_;
  std::uint64_t refused_ = 0;
  Clock::time_point refused_logged_{};
};

}  // namespace lcmx::detail
