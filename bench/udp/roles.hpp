// Roles of lcmx_bench_udp's children (see roles.cpp); the harness's ping-pong protocol
// (bench/harness/pingpong.hpp) supplies the plan, the report/ack lines, Recorder and the driver,
// bench/latency the liblcm ping-pong pair.
#pragma once

#include <functional>
#include <string>

#include "latency/roles.hpp"

namespace lcmxbench::udp {

struct UdpConfig {
  RoleConfig base;          // base.url: liblcm URL (liblcm roles) or lcmx discovery URL
  std::string vehicle_url;  // lcmx roles: the vehicle group, with iface=
  double rate_hz = 30;      // stream roles: ticks per second
  int burst = 1;            // stream roles: messages sent back to back per tick
  std::string key_file;     // lcmx roles: the vehicle group's key file ("" = unkeyed)
  bool crypt = false;       // lcmx roles with a key file: encrypted, not only authenticated
};

// A CPU hog for the busy stream scenario: spins until killed (at most 10 minutes).
int run_hog();

int run_lcmx_udp_sub(const UdpConfig& u, bool stream);
int run_lcmx_udp_pub(const UdpConfig& u, bool stream);
int run_liblcm_stream_sub(const UdpConfig& u);
int run_liblcm_stream_pub(const UdpConfig& u);

// Publishes plan[0].messages messages of plan[0].size, `burst` back to back per tick at rate_hz
// ticks per second (no acks), then a "sent" line.
bool run_stream(const RoleConfig& cfg, double rate_hz, int burst, const std::function<void(std::size_t)>& prepare,
                const std::function<void(std::int64_t)>& send);

}  // namespace lcmxbench::udp
