// Options for the runtime, nodes, publishers and subscribers. Every field has a default
// that works with no configuration at all.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "lcmx/udpm/config.hpp"

namespace lcmx {

// How an executor thread waits for messages.
enum class WaitStrategy {
  block,            // default: sleep on a futex until woken (no CPU when idle)
  spin_then_block,  // poll for `spin` at the start of every wait, then sleep
  busy_poll,        // never sleep (lowest latency, one core per executor thread)
  // Poll, yielding the CPU between polls, only while the node's last message was handled
  // less than `spin` ago; then sleep. Stops polling as soon as a yield lets another thread
  // run (a contended CPU). Catches a request/response exchange without a wake-up (round trip
  // about halved on an idle machine) and costs nothing when idle, but up to `spin` per
  // message on a steady stream, and worse tails than block on a busy machine: not the
  // default (measured in bench/README.md "Wait strategies"). For request/response-heavy
  // nodes on machines with spare cores.
  adaptive,
};

enum class ExecutorKind {
  own_threads,  // the node starts `threads` threads that run its callbacks (default)
  manual,       // no thread: the user calls Node::spin_once() from their own loop
};

struct ExecutorOptions {
  ExecutorKind kind = ExecutorKind::own_threads;
  int threads = 1;  // own_threads: >1 runs different subscriptions' callbacks in parallel
  WaitStrategy wait = WaitStrategy::block;
  // spin_then_block: how long to poll first; adaptive: how long after the last message.
  std::chrono::microseconds spin{50};
  // The scheduler slice the executor's threads ask the kernel for (Linux's EEVDF, kernels
  // 6.12 and later: sched_setattr's sched_runtime for SCHED_OTHER threads). A short slice
  // lets a thread that wakes a reader and then has a little more to do (a relay: a message
  // in, several datagrams out) finish before the woken reader preempts it, so the reader then
  // runs on the same CPU instead of waking another (docs/dds.md "Benchmark"). 0 (default):
  // the kernel's default. Else 100 us .. 100 ms. A kernel without custom slices, or a thread
  // under another policy (SCHED_FIFO, ...), is left as it is (logged at debug level).
  std::chrono::microseconds slice{0};
};

struct NodeOptions {
  ExecutorOptions executor;
};

struct PublisherOptions {
  std::size_t max_message_size = 64u << 20;  // publish() of a larger message throws
  std::uint32_t shm_slots = 8;               // messages a shm subscriber may lag by
  std::size_t shm_initial_slot_size = 4096;  // grows by itself up to max_message_size
  // Keep last N ("transient-local" durability, like DDS/ROS 2 KEEP_LAST + TRANSIENT_LOCAL):
  // a subscriber that matches this publisher later receives its last `history` messages
  // first, once, then the live ones; on every path (intra, shm, UDP to other hosts, the
  // Message Bridge). 0 (default): volatile, a subscriber gets what is published after it
  // matched, as LCM does. At most kMaxHistory; shm_slots is raised to history + 1 if it is
  // smaller. Cost while > 0: every message is encoded into shared memory even with no
  // subscriber, and small ones are also kept as a private copy (N x message size) for
  // subscribers on other hosts. docs/ARCHITECTURE.md "Keep last N".
  std::uint32_t history = 0;
  static constexpr std::uint32_t kMaxHistory = 1000;
};

// What a full subscriber queue (in-process and UDP messages) does with a new message.
enum class QueuePolicy {
  drop_oldest,  // default: keep the newest messages
  drop_newest,  // keep what is queued, drop the new one
};

struct SubscriberOptions {
  std::size_t queue_depth = 16;  // in-process / UDP queue per subscriber (shm has its own ring)
  QueuePolicy policy = QueuePolicy::drop_oldest;
  // false: never matched with publishers of Message Bridge participants (RuntimeOptions::bridge),
  // including this process's own when it is one. The bridge's own subscribers use it, so a
  // bridge never forwards what a bridge republished (no loops).
  bool from_bridges = true;
  // false: never matched with publishers of DDS gateways (RuntimeOptions::dds_gateway),
  // including this process's own. A gateway's export subscribers use it, so no gateway sends
  // back to DDS what a gateway imported from DDS (docs/dds.md "Loops").
  bool from_dds_gateways = true;
  // Shared memory: a publisher matched later is read from the messages it committed at or
  // after this time, as far as its ring still holds them (the start-up race: a subscriber that
  // existed before it matched a publisher gets what was published meanwhile; what the ring
  // lost is counted in drops). Default (epoch): when the subscription is made. A relay that
  // subscribes on someone else's behalf (the Message Bridge, for a peer's demand) sets the
  // time that demand began. steady_clock is CLOCK_MONOTONIC: one clock for the whole host.
  std::chrono::steady_clock::time_point since{};
};

// A topic's class decides its path to other hosts (DESIGN.md "Delivery").
enum class TopicClass {
  automatic,  // small until a message exceeds RuntimeOptions::udp_limit, then large (sticky)
  small,      // always LCM UDP multicast to other hosts
  large,      // always the Message Bridge to other hosts (UDP fragments until it exists)
};

// When small topics are sent on the vehicle group.
enum class VehiclePublish {
  on_demand,  // only while a subscriber on another host wants the topic (default)
  always,     // every message, like stock LCM (for liblcm subscribers on other hosts)
};

struct RuntimeOptions {
  // Host-local group (LCM's default URL): discovery on this host, messages from stock LCM
  // programs, and the mirror. Tests use their own group/port. With no iface= it works like
  // liblcm's whatever the routing table says (joined on lo and where the kernel routes the group;
  // see lcmx/udpm/group.hpp); "&iface=lo" pins it to lo.
  std::string discovery_url = "udpm://239.255.76.67:7667?ttl=0";
  // Vehicle group across hosts, e.g. "udpm://239.255.76.68:7668?ttl=1&iface=eth0"; the
  // interface is required. Empty: this host only.
  std::string vehicle_url;
  VehiclePublish vehicle_publish = VehiclePublish::on_demand;
  // A message larger than this (encoded bytes) makes an automatic topic large: one LCM
  // datagram (LC02) carries up to 65499 bytes with the channel name.
  std::size_t udp_limit = 65000;
  // Also publish small messages on the host-local group, where the kernel routes it (as stock
  // LCM programs send), so stock programs on this host (lcm-logger, lcm-spy, drivers) hear them:
  // every channel with `mirror`, or the channels matching one of `mirror_channels` (fnmatch
  // globs, e.g. {"CAM_*", "POSE"}). Large topics are never mirrored.
  bool mirror = false;
  std::vector<std::string> mirror_channels;
  // Per-channel class overrides (channel name -> class).
  std::map<std::string, TopicClass> topic_class;
  // Liveness (DESIGN.md "Leases"): a participant of another host is gone after `lease`
  // without a beacon (3 beacons fit in it); one of this host (same pid namespace) is gone
  // as soon as its process exits (pidfd), its lease still covers a hung process.
  std::chrono::milliseconds beacon_period{400};
  std::chrono::milliseconds lease{1500};
  bool reclaim_orphans = true;  // remove shm segments of dead processes at start

  // This participant is a Message Bridge (`lcmx bridge`): its beacons carry FLAG_BRIDGE, its
  // endpoints are never announced to other hosts, and while it runs the other participants of
  // this host send large topics to other hosts only through it (not as UDP fragments).
  bool bridge = false;
  // This participant is a DDS gateway (`lcmx dds-gateway`): its beacons carry FLAG_DDS_GATEWAY
  // (`lcmx topics` marks its endpoints) and subscribers with from_dds_gateways = false never
  // match its publishers. Nothing else changes: its endpoints take every path.
  bool dds_gateway = false;
  // Bridge only: topic globs (fnmatch) it carries besides the large class. Announced on this
  // host; every participant here then treats matching topics as large.
  std::vector<std::string> bridge_carry;

  // Group keys (docs/keyed-groups.md): a key file (`lcmx keygen --group FILE`) makes the group
  // keyed: every lcmx datagram on it is authenticated (optionally encrypted), anything else
  // (stock LCM programs, hosts without the key, replays) refused and reported. Empty: unkeyed.
  // The file is re-read when it changes (rotation, no restart: docs/keyed-groups.md).
  std::string vehicle_key;  // the vehicle group's: against other machines on the LAN
  std::string host_key;     // the host-local group's: against other users of this host
  // Encrypt the payloads too (AEAD), not only authenticate. A key file line `encrypt` also
  // turns it on. Receivers take both forms.
  bool vehicle_crypt = false;
  bool host_crypt = false;
  // Keyed groups: a datagram of a sender not heard yet is taken only if the time stamped in it
  // is within this of this host's clock (udpm::GroupConfig::keyed_max_skew): the hosts' clocks
  // must agree within it. 0 turns the check off (no time sync; docs/keyed-groups.md "Replay").
  std::chrono::seconds keyed_max_skew{60};

  // Defaults overridden by the environment: LCMX_DISCOVERY_URL, LCMX_VEHICLE_URL,
  // LCMX_VEHICLE_PUBLISH (on_demand|always), LCMX_UDP_LIMIT, LCMX_MIRROR (0, 1 = every
  // channel, or comma-separated channel globs such as "CAM_*,POSE" = mirror_channels),
  // LCMX_LARGE_TOPICS / LCMX_SMALL_TOPICS (comma-separated channels), LCMX_BEACON_PERIOD_MS,
  // LCMX_LEASE_MS, LCMX_VEHICLE_KEY / LCMX_HOST_KEY (key files), LCMX_VEHICLE_CRYPT /
  // LCMX_HOST_CRYPT (0 or 1), LCMX_KEYED_MAX_SKEW_S. Throws lcmx::Error(invalid_argument) naming a bad variable.
  static RuntimeOptions from_env();
  // What Runtime::create refuses before it starts anything: a discovery_url or vehicle_url
  // that group_url_problem() finds wrong, lease not longer than beacon_period, a bad
  // LCMX_HOST_ID, a key file that cannot be read or is not private (group_config).
  // Throws lcmx::Error(invalid_argument) naming the values and their variables.
  // (The `lcmx` tools call it for every verb, the observers too.)
  void check() const;
  // Why `url` cannot be this group ("" when it can): not a udpm:// URL the runtime reads, or a
  // vehicle group (`vehicle`; "" there means none) that names no interface (iface=).
  static std::string group_url_problem(const std::string& url, bool vehicle);

  // The configuration the runtime opens the vehicle group (`vehicle`) or the host-local group
  // with: its URL parsed, and its key file read (vehicle_key / host_key, with *_crypt) when
  // one is named. The tools' observers open their groups with it too.
  // Throws lcmx::Error(invalid_argument) naming the option, its variable and the file.
  udpm::GroupConfig group_config(bool vehicle) const;
  // The key file of a group, read as group_config() does (null when none is named).
  // Throws as group_config().
  std::shared_ptr<const udpm::GroupKeys> group_keys(bool vehicle) const;
};

}  // namespace lcmx
