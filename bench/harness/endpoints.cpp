#include "endpoints.hpp"

#include "process.hpp"

namespace lcmxbench {

std::string paths_of(const lcmx::SubscriberStats& stats) {
  std::string paths;
  for (const auto& p : stats.publishers) paths += std::string(paths.empty() ? "" : ",") + lcmx::to_string(p.path);
  return paths;
}

void report_delivery(const std::string& who, const lcmx::SubscriberStats& s) {
  std::string line = "note " + who + ": delivered=" + std::to_string(s.delivered) + " drops=" + std::to_string(s.drops) +
                     " decode_errors=" + std::to_string(s.decode_errors);
  for (const auto& e : s.errors) line += " error='" + e + "'";
  report_line(line);
}

}  // namespace lcmxbench
