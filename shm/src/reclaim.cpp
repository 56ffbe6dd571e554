// reclaim_orphans: removes segments whose Writer is gone (no Writer lock), except
// generations a live Reader still needs to follow a cleanly exited Writer.
#include <sys/stat.h>
#include <unistd.h>

#include <spdlog/spdlog.h>

#include <cerrno>
#include <set>

#include "impl.hpp"

namespace lcmx::shm {

ReclaimReport reclaim_orphans(const std::string& prefix) {
  ReclaimReport report;
  if (prefix.empty() || prefix.find('/') != std::string::npos) return report;
  std::set<std::string> bases;
  const uid_t me = ::geteuid();
  for (const auto& name : detail::list_shm(prefix)) {
    // Another user's files are not ours to judge (nor, in sticky /dev/shm, to unlink).
    struct stat st {};
    if (::stat(("/dev/shm/" + name).c_str(), &st) != 0) continue;
    if (me != 0 && st.st_uid != me) continue;
    // Alive (in any pid namespace sharing /dev/shm): the Writer holds its lock. Checked
    // first, so a file being created (lock taken before the magic) is never warned about.
    if (detail::writer_lock_held(name)) continue;
    std::string why;
    // peek_segment checks ownership and the file size before touching any field, then magic,
    // version and layout; it never throws.
    auto info = detail::peek_segment(name, &why);
    auto sg = detail::split_generation(name);
    if (!info || !sg) {
      // Removed meanwhile by its owner or another reclaimer (several processes starting at
      // once): nothing to leave alone, nothing to warn about.
      if (::stat(("/dev/shm/" + name).c_str(), &st) != 0 && errno == ENOENT) continue;
      ++report.skipped;
      spdlog::warn("lcmx shm reclaim: leaving /dev/shm/{} alone: {}", name,
                   info ? "no generation suffix" : why);
      continue;
    }
    bases.insert(sg->first);
  }
  for (const auto& base : bases) report.removed += detail::release_unneeded_generations(base);
  return report;
}

}  // namespace lcmx::shm
