// The topology as the lcmx tool shows it: built from discovery beacons.
#pragma once

#include <ostream>
#include <vector>

#include "lcmx/discovery/discovery.hpp"

namespace lcmx::cli {

// Prints participants (host, pid, process) and their nodes with publishers/subscribers.
void print_nodes(std::ostream& out, const std::vector<discovery::Participant>& ps);
// Prints topics: type, publishers, subscribers, and per subscriber the path, rate, received
// and drops of each pair; type conflicts are flagged.
void print_topics(std::ostream& out, const std::vector<discovery::Participant>& ps);

}  // namespace lcmx::cli
