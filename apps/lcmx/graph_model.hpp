// `lcmx graph`'s model: the system as hosts -> processes -> nodes -> topics, with the path of
// every publisher/subscriber pair, built from discovery beacons; rendered as Graphviz DOT or
// JSON. Only the structure is rendered (no counters or rates), so the text changes exactly when
// the topology does (`--watch` compares it). Unit-tested in test/tools/.
// Threads: pure functions. Errors: none.
#pragma once

#include <string>
#include <vector>

#include "lcmx/discovery/discovery.hpp"
#include "lcmx/types/types.hpp"

namespace lcmx::cli::graph {

// Type names: package-qualified from `registry` (the type path) by the endpoint's fingerprint
// when it knows it, else the beacon's (lcm-gen's name, without package); "" for raw endpoints.

// Participants sorted (host, process name, pid, participant id) so that output is stable.
std::vector<discovery::Participant> sorted(std::vector<discovery::Participant> ps);

// digraph: a cluster per host, inside it a cluster per process, inside it a box per node;
// topics are ellipses outside; an edge node -> topic per publisher, an edge topic -> node per
// subscriber pair, labelled with its path ("shm", "udp", ...) and, when the topic has several
// publishers, which one. Stock LCM senders heard by a subscriber appear as "LCM sender".
std::string to_dot(const std::vector<discovery::Participant>& participants,
                   const types::TypeRegistry* registry = nullptr);

// {"hosts":[{"host":"<hex>","processes":[{"process":..,"pid":..,"participant":..,"bridge":..,
//   "nodes":[{"node":..,"publishes":[{"topic":..,"type":..}],
//             "subscribes":[{"topic":..,"type":..,"pairs":[{"publisher":..,"path":..}]}]}]}]}],
//  "topics":[{"topic":..,"types":[..],"publishers":N,"subscribers":N}]}
std::string to_json(const std::vector<discovery::Participant>& participants,
                    const types::TypeRegistry* registry = nullptr);

}  // namespace lcmx::cli::graph
