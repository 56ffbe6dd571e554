// Options for the runtime, nodes, publishers and subscribers. Every field has a default
// that works with no configuration at all.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <string>

namespace lcmx {

// How an executor thread waits for messages.
enum class WaitStrategy {
  block,            // sleep on a futex until woken (default: no CPU when idle)
  spin_then_block,  // poll for `spin` first, then sleep (lower latency across vCPUs)
  busy_poll,        // never sleep (lowest latency, one core per executor thread)
};

enum class ExecutorKind {
  own_threads,  // the node starts `threads` threads that run its callbacks (default)
  manual,       // no thread: the user calls Node::spin_once() from their own loop
};

struct ExecutorOptions {
  ExecutorKind kind = ExecutorKind::own_threads;
  int threads = 1;  // own_threads: >1 runs different subscriptions' callbacks in parallel
  WaitStrategy wait = WaitStrategy::block;
  std::chrono::microseconds spin{50};  // spin_then_block: how long to poll first
};

struct NodeOptions {
  ExecutorOptions executor;
};

struct PublisherOptions {
  std::size_t max_message_size = 64u << 20;  // publish() of a larger message throws
  std::uint32_t shm_slots = 8;               // messages a shm subscriber may lag by
  std::size_t shm_initial_slot_size = 4096;  // grows by itself up to max_message_size
};

struct SubscriberOptions {
  std::size_t queue_depth = 16;  // intra-process queue per subscriber; full -> drop oldest
};

struct RuntimeOptions {
  // Host-local discovery group (LCM's default URL). Tests use their own group/port.
  std::string discovery_url = "udpm://239.255.76.67:7667?ttl=0";
  std::chrono::milliseconds beacon_period{1000};
  std::chrono::milliseconds lease{3500};
  bool reclaim_orphans = true;  // remove shm segments of dead processes at start

  // Defaults overridden by the environment: LCMX_DISCOVERY_URL, LCMX_BEACON_PERIOD_MS,
  // LCMX_LEASE_MS. Throws lcmx::Error(invalid_argument) naming a bad variable.
  static RuntimeOptions from_env();
};

}  // namespace lcmx
