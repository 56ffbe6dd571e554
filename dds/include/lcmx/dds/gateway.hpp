// The DDS gateway (`lcmx dds-gateway`, docs/dds.md): an lcmx participant and a Cyclone DDS
// participant that exchange the configured channels/topics.
//
// Demand (docs/dds.md "Demand and loops"): a to_dds mapping subscribes to its lcmx channel only
// while DDS readers other than gateways' are matched with its writer; a from_dds mapping has a
// DDS reader only while lcmx subscribers are matched with its publisher. The control thread
// re-evaluates both every 20 ms.
// Loops: the gateway's lcmx publishers carry FLAG_DDS_GATEWAY and its export subscribers never
// match publishers of gateways (SubscriberOptions::from_dds_gateways); its DDS writers and
// readers carry the user data kGatewayUserData and it never imports samples of such writers.
// Threads: exports run on the gateway node's executor thread, imports on Cyclone's listener
// thread, demand/type checks/status on a control thread of its own.
#pragma once

#include <memory>

#include "lcmx/core/options.hpp"
#include "lcmx/dds/config.hpp"
#include "lcmx_msgs/dds_gateway_status_t.hpp"

namespace lcmx::dds {

// lcmx channel of the gateways' status (lcmx_msgs::dds_gateway_status_t).
inline constexpr const char* kStatusChannel = "LCMX_DDS_STATUS";
// USER_DATA of the gateways' DDS participants, writers and readers.
inline constexpr const char* kGatewayUserData = "lcmx-dds-gateway";

class Gateway {
 public:
  // Joins lcmx (options.dds_gateway is set here) and the DDS domain, creates every mapping's
  // topic, writer and publisher, and starts the control thread.
  // Throws: ConfigError (a mapping that cannot be set up), DdsError (Cyclone refused the
  // domain/config, e.g. an unknown interface), lcmx::Error (lcmx's transports).
  static Gateway start(Config cfg, RuntimeOptions options = RuntimeOptions::from_env());
  Gateway(Gateway&&) noexcept;
  Gateway& operator=(Gateway&&) noexcept;
  ~Gateway();  // stop()

  // A snapshot of every mapping's state and counters. Thread-safe.
  lcmx_msgs::dds_gateway_status_t status() const;
  // Stops the control thread, unsubscribes and deletes the DDS entities (waiting for running
  // callbacks), then leaves lcmx. Idempotent.
  void stop();

  struct Impl;

 private:
  explicit Gateway(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace lcmx::dds
