// Host-local discovery: participants beacon on an LCM udpm group (DESIGN.md "Discovery").
//
// A Discovery object runs one thread that
//  - sends this participant's beacon at once when announce_now() is called and every
//    `period` otherwise, and a goodbye when it stops;
//  - answers an observer's query (FLAG_QUERY) with a beacon at once;
//  - receives other participants' beacons, ignores its own, and declares a participant gone
//    after its lease (the lease it announced) or at once on its goodbye;
//  - in host scope, watches each peer's process (pidfd, same pid namespace) and declares it
//    gone as soon as the process exits.
// Observers (the lcmx tool) send only queries, never appear as participants.
//
// Threads: on_change is called on the discovery thread, never concurrently with itself; it
// must not call back into this Discovery's stop()/destructor. participants() is thread-safe.
// Errors: the constructor throws (udpm::Error or std::runtime_error) when the group cannot be
// opened; malformed beacons are counted and logged (rate-limited), never thrown.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "lcmx/udpm/udpm.hpp"
#include "lcmx_msgs/beacon_t.hpp"

namespace lcmx::discovery {

struct Options {
  udpm::GroupConfig group;                          // default: LCM's host-local group on lo
  // When set, beacons are sent on this group (owned with others) instead of one opened
  // from `group`, and nothing is received by the Discovery: the owner reads the group and
  // hands beacon-channel messages to deliver().
  std::shared_ptr<udpm::Group> shared_group;
  std::int8_t scope = lcmx_msgs::beacon_t::SCOPE_HOST;  // written into every beacon
  std::chrono::milliseconds period{400};            // periodic beacon
  std::chrono::milliseconds lease{1500};            // announced; others drop us after this
  bool observer = false;                            // query only, never announce
  // Bounds of the table of other participants (anyone on the group can send beacons). A new
  // participant, or a participant's new beacon, that would exceed them is refused and counted
  // (Counters::refused, a warning at most every 5 s); participants already in the table keep
  // their place until their goodbye or lease. The lease a beacon announces is cut to max_lease.
  std::size_t max_participants = 1024;
  std::size_t max_table_bytes = std::size_t{64} << 20;  // sum of their encoded beacons
  std::chrono::milliseconds max_lease{600000};  // the largest lease LCMX_LEASE_MS allows
  // Host scope: a peer in our pid namespace is watched with a pidfd (pid + start time from
  // its beacon, so a reused pid is never taken for it) and declared gone as soon as its
  // process exits, not only after its lease. Peers in other pid namespaces: lease only.
  bool watch_processes = true;
  // With `shared_group`: reads what the owner's sockets hold and hands its beacons to
  // deliver(), on the calling thread. The Discovery calls it on its own thread, holding none
  // of its locks, right before it would declare a lease expired: beacons that arrived in time
  // may still be queued (this process was stopped and resumed, a frozen container, a receive
  // thread that lags), and a lease expires only on beacons that did not come. Without it the
  // owner's receive thread alone decides how late a beacon is read. (A Discovery that reads
  // its own group drains it itself.)
  std::function<void()> drain_before_expiry;
};

// What is known about another participant: its latest beacon and when it arrived.
struct Participant {
  lcmx_msgs::beacon_t beacon;
  std::chrono::steady_clock::time_point last_seen;
};

enum class Change { joined, updated, left };

struct Counters {
  std::uint64_t beacons_sent = 0;
  std::uint64_t beacons_received = 0;
  std::uint64_t malformed = 0;
  std::uint64_t leases_expired = 0;
  std::uint64_t exits_seen = 0;  // peers declared gone because their process exited (pidfd)
  std::uint64_t goodbyes = 0;
  std::uint64_t refused = 0;  // beacons refused by max_participants / max_table_bytes
};

class Discovery {
 public:
  // `local` builds this participant's beacon (called on the discovery thread before each
  // send; the Discovery fills sequence, flags, lease and timestamp). Not used by observers.
  // `on_change` is told of every other participant that joins, changes (new revision or
  // new statistics) or leaves.
  using LocalFn = std::function<lcmx_msgs::beacon_t()>;
  using ChangeFn = std::function<void(Change, const Participant&)>;
  Discovery(Options options, LocalFn local, ChangeFn on_change);
  ~Discovery();  // stop()
  Discovery(const Discovery&) = delete;
  Discovery& operator=(const Discovery&) = delete;

  // Send our beacon as soon as possible (something changed). Thread-safe, never blocks.
  void announce_now();
  // Observers: ask every participant to beacon now.
  void query();
  // With Options::shared_group: a message received on the beacon channel. Any thread.
  void deliver(const udpm::Message& message);
  // Sends the goodbye and joins the thread. Idempotent.
  void stop();

  std::vector<Participant> participants() const;
  Counters counters() const;
  const Options& options() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace lcmx::discovery
