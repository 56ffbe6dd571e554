// What the lcmx roles of the benchmarks report about their subscribers (bench/harness): the
// path of each matched publisher, and the delivery counters, as "note" lines.
#pragma once

#include <string>

#include "lcmx/core.hpp"

namespace lcmxbench {

// The path of each publisher the subscriber is matched with, "shm,udp"; "" when none is listed.
std::string paths_of(const lcmx::SubscriberStats& stats);
// "note <who>: delivered=N drops=N decode_errors=N[ error='...']..." on the report fd.
void report_delivery(const std::string& who, const lcmx::SubscriberStats& stats);

}  // namespace lcmxbench
