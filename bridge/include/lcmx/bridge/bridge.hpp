// The Message Bridge (DESIGN.md "Message Bridge", docs/bridge.md): one per host. It is an
// ordinary lcmx participant (a Runtime with RuntimeOptions::bridge) that
//  - learns from host-local discovery which topics this host's participants subscribe to and
//    asks every peer bridge for them (demand, every heartbeat);
//  - subscribes to what its peers ask for when a non-bridge participant of this host publishes
//    it and the topic is large (or carried), and sends each message once per peer host over
//    ZeroMQ (one socket per channel, the peer's active link);
//  - republishes what its peers send into this host's shared memory, under the same channel;
//  - heartbeats every link of every peer, fails over and back, and publishes its status on
//    "LCMX_BRIDGE_STATUS" (lcmx_msgs::bridge_status_t).
//
// Threads: one control thread (heartbeats, demand, links, subscriptions, status), one
// forwarding thread per channel, one executor thread per channel for the shm subscriptions,
// one ZeroMQ I/O thread per channel plus one for control, a ZAP thread with CURVE.
// Errors: start() throws ConfigError (bad config), BridgeError (cannot bind a listen address,
// CURVE unavailable), lcmx::Error (runtime). Once started, nothing that peers do (absent,
// restarting, hostile frames) throws: it is logged and counted.
#pragma once

#include <memory>
#include <stdexcept>

#include "lcmx/bridge/config.hpp"
#include "lcmx/core/options.hpp"
#include "lcmx_msgs/bridge_status_t.hpp"

namespace lcmx::bridge {

class BridgeError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// The channel on which bridges publish their status (host-local).
inline constexpr const char* kStatusChannel = "LCMX_BRIDGE_STATUS";

class Bridge {
 public:
  // Starts the bridge. `runtime` supplies the discovery group, udp_limit, timing; the bridge
  // sets `bridge`, `bridge_carry` and clears `vehicle_url` itself (it talks to other hosts
  // only over its links, so what it republishes never goes out on UDP).
  static Bridge start(Config config, RuntimeOptions runtime = RuntimeOptions::from_env());

  Bridge(Bridge&&) noexcept;
  Bridge& operator=(Bridge&&) noexcept;
  ~Bridge();  // stop()

  // Stops every thread, closes the sockets and says goodbye. Idempotent.
  void stop();
  // A snapshot of the counters (what is published on kStatusChannel). Thread-safe.
  lcmx_msgs::bridge_status_t status() const;

  struct Impl;

 private:
  explicit Bridge(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace lcmx::bridge
