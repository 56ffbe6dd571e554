// reclaim_orphans: removes segments whose creating process is dead.
#include <spdlog/spdlog.h>

#include "impl.hpp"

namespace lcmx::shm {

ReclaimReport reclaim_orphans(const std::string& prefix) {
  ReclaimReport report;
  if (prefix.empty() || prefix.find('/') != std::string::npos) return report;
  for (const auto& name : detail::list_shm(prefix)) {
    std::string why;
    // peek_segment checks the file size before touching any field, then magic, version and
    // layout; it never throws.
    auto info = detail::peek_segment(name, &why);
    if (!info) {
      ++report.skipped;
      spdlog::warn("lcmx shm reclaim: leaving /dev/shm/{} alone: {}", name, why);
      continue;
    }
    if (detail::process_alive(info->owner_pid, info->owner_start_time)) continue;
    if (detail::unlink_segment(name)) ++report.removed;
  }
  return report;
}

}  // namespace lcmx::shm
