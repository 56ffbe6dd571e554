// Discovery in two scopes (DESIGN.md "Discovery", docs/discovery.md).
//
// On one host, participants meet in a shared-memory registry (registry.hpp): each writes its
// beacon (both scopes) into a state file of its own when it changes, and a heartbeat into its
// slot every `period`; each reads only the state files whose revision changed and whose
// topics concern it. One participant per registry and group, the *speaker* (elected by an OFD
// lock, no daemon), watches every participant's process (pidfd: its death is in the registry
// within milliseconds), reclaims the shared memory of the dead, and alone sends on the group:
// a small heartbeat every period (digest of the set it speaks for), the records (beacon_t) of
// participants that changed, goodbyes, and answers to requests (rate-limited).
// A Discovery object runs one thread that
//  - publishes this participant's beacon into the registry at once when announce_now() is
//    called and every `period` otherwise (statistics only while an observer watches), and
//    leaves the registry when it stops;
//  - reads the registry when it changes (one futex word) and at least every period: a
//    participant is gone when its slot is freed (goodbye), marked dead (its process exited,
//    seen by the speaker) or its heartbeat is older than its lease;
//  - in host scope, hears neighbours (other registries on the host-local group: another
//    /dev/shm); in vehicle scope, other hosts. Only the host's vehicle speaker hears the
//    vehicle group's discovery: per host a table kept in step with its speaker's heartbeat
//    digest (a mismatch asks for the index, then the missing records; a host whose heartbeat
//    stops for its lease takes all its participants with it), which it writes into the host's
//    vehicle table (shared memory). Every other participant of the host *follows* that table:
//    it is woken when it changes and reads only the records of other hosts whose topics concern
//    it (docs/discovery.md "Vehicle table"), and ignores the group's discovery datagrams.
// Observers (the lcmx tools) read the registry and ask other hosts' speakers for everything,
// never appear as participants.
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

#include "lcmx/discovery/registry.hpp"
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
  // The host registry this participant joins (shared by the host and vehicle Discovery of one
  // process: one slot). Null: the Discovery opens the registry of (this host, its group).
  std::shared_ptr<Registry> registry;
  std::uint32_t registry_slots = 1024;  // of a registry it creates (registry.hpp)
  std::string registry_directory = "/dev/shm";
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
  // Vehicle scope: called on the discovery thread, with no lock held, whenever listening()
  // changes (the Discovery starts or stops speaking for its host, or finds no vehicle table to
  // follow): an owner that filters the group's datagrams before they reach deliver() (a
  // udpm::ReceiveFilter) lets the discovery datagrams through exactly while it is true.
  std::function<void(bool listening)> on_listening;
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
  std::uint64_t forged = 0;   // goodbyes, records or source claims from the wrong address;
                              // records naming another host's (or this host's) participant
  std::uint64_t requests_answered = 0;  // speaker: index / record requests answered
  std::uint64_t requests_limited = 0;   // speaker: requests folded into a later answer
  std::uint64_t requests_folded = 0;    // receiver: own requests dropped or shortened (what they
                                        // asked came, or someone asked it, meanwhile)
  std::uint64_t registry_reads = 0;     // state files read
  std::uint64_t registry_skipped = 0;   // changed participants none of whose topics concern us
  std::uint64_t speaker_terms = 0;      // times this Discovery became its group's speaker
  std::uint64_t acting_terms = 0;       // vehicle scope: times it spoke for a silent speaker (docs/discovery.md)
  std::uint64_t missed_batches = 0;     // receiver: compressed batches against a base record not
                                        // held (the index asked instead)
  std::uint64_t table_records = 0;      // vehicle scope: other hosts' records taken from this
                                        // host's vehicle table (a follower, or a new speaker)
  std::uint64_t table_reads = 0;        // vehicle scope: vehicle tables read (a new one each)
  std::uint64_t table_skipped = 0;      // vehicle scope: records of a table not read (their topics
                                        // do not concern this participant)
  std::uint64_t tables_refused = 0;     // vehicle scope: tables not followed: not of this host, or
                                        // not written by a live participant of its registry under
                                        // that participant's uid
  std::uint64_t requests_sent = 0;      // receiver: requests (index or records) sent on the group
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
  // True while this Discovery is its registry's speaker on its group.
  bool speaking() const;
  // Whether it takes the group's discovery datagrams (deliver()): always in host scope and for
  // observers; in vehicle scope while it speaks (or acts) for its host, or while it has no
  // current vehicle table to follow (docs/discovery.md "Vehicle table"). Any thread.
  bool listening() const;
  // Vehicle scope: whether it has heard the whole vehicle once (docs/discovery.md "Complete"):
  // it listened for kCompleteAfter periods (every live host's heartbeat came) and holds, for
  // every host heard, the records that host's digest names. Then a subscriber of another host
  // that existed is known here (a publisher's start-up window ends its blind sends). Once true
  // it stays true. Host scope: always true. Any thread; never blocks (an atomic).
  bool complete() const;
  // The registry it uses (null for a vehicle-scope observer).
  std::shared_ptr<Registry> registry() const;
  const Options& options() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace lcmx::discovery
