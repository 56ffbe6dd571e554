// The topology as the lcmx tool shows it: built from discovery beacons.
#pragma once

#include <memory>
#include <ostream>
#include <string>
#include <vector>

#include "lcmx/discovery/discovery.hpp"
#include "lcmx/types/schema.hpp"
#include "lcmx/udpm/keys.hpp"
#include "verb.hpp"

namespace lcmx::cli {

// The type of an endpoint as the tool shows it: "raw" for a raw byte channel (fingerprint 0);
// the package-qualified name ("pkg.type") when `types` (the type path) holds a type with the
// endpoint's fingerprint — of those, the one whose short name is the beacon's type_name, as
// several types may share a layout; else the beacon's type_name (lcm-gen 1.3.1's
// getTypeName() has no package).
std::string type_label(const lcmx_msgs::endpoint_t& e, const types::TypeRegistry* types);

// Listens on the host-local group `url`, and on the vehicle group when given, for `wait_ms`
// (asking everyone to beacon at once midway), and returns the participants seen. A participant
// seen in both scopes is listed once, from its host-local beacon (complete).
// `groups`, when given, gets what the observer saw of each group: whether it is keyed, and what
// a keyed one refused (per source) while it listened.
// Throws lcmx::Error naming a bad URL or key file (observer_group).
struct GroupSeen {
  bool vehicle = false;
  std::string url;
  std::shared_ptr<const udpm::GroupKeys> keys;  // null: unkeyed
  std::vector<udpm::Refusals::Source> refused;
};
std::vector<discovery::Participant> observe(const Globals& g, std::vector<GroupSeen>* groups = nullptr);
// "group vehicle udpm://...: keyed (authenticated, key 1a2b3c4d)" lines, and a line per
// source a keyed group refused; JSON: an array of objects.
void print_groups(std::ostream& out, const std::vector<GroupSeen>& groups);
std::string groups_json(const std::vector<GroupSeen>& groups);

// Prints participants (host, pid, process) and their nodes with publishers/subscribers.
// `types`: the type path for package-qualified names (may be null).
void print_nodes(std::ostream& out, const std::vector<discovery::Participant>& ps,
                 const types::TypeRegistry* types = nullptr);
// Prints topics: type, publishers, subscribers, and per subscriber the path, rate, received
// and drops of each pair; type conflicts are flagged.
void print_topics(std::ostream& out, const std::vector<discovery::Participant>& ps,
                  const types::TypeRegistry* types = nullptr);
// The same as one line of JSON each (shapes in README "Scripting: --json").
void print_nodes_json(std::ostream& out, const std::vector<discovery::Participant>& ps,
                      const types::TypeRegistry* types = nullptr);
void print_topics_json(std::ostream& out, const std::vector<discovery::Participant>& ps,
                       const types::TypeRegistry* types = nullptr);

}  // namespace lcmx::cli
