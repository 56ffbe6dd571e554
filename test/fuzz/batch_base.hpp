// The base record of the fuzz inputs compressed against a base (records_z_t with
// base_participant set, docs/discovery.md "Compressed against a base"): make_seeds deflates a
// seed against it, fuzz_beacon inflates with it whatever names a base.
#pragma once

#include <cstdint>

#include "lcmx/discovery/beacon_codec.hpp"

namespace lcmx::fuzz {

inline lcmx_msgs::beacon_t batch_base_record() {
  lcmx_msgs::beacon_t b{};
  b.version = lcmx::discovery::kBeaconVersion;
  b.participant_id = 0x5eed;
  b.revision = 3;
  b.process_name = "fuzz_base";
  b.scope = lcmx_msgs::beacon_t::SCOPE_VEHICLE;
  b.nodes = {"node"};
  b.num_nodes = 1;
  lcmx_msgs::endpoint_t e{};
  e.id = 1;
  e.kind = lcmx_msgs::endpoint_t::KIND_PUBLISHER;
  e.node = "node";
  e.topic = "POSE";
  e.type_name = "pose_t";
  b.endpoints = {e};
  b.num_endpoints = 1;
  return b;
}

}  // namespace lcmx::fuzz
