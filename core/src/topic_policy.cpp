#include "topic_policy.hpp"

#include <fnmatch.h>

#include "lcmx/core/error.hpp"

namespace lcmx::detail {

TopicPolicy::TopicPolicy(const RuntimeOptions& options) : options_(options) {
  for (const auto& glob : options.bridge_carry)
    if (glob.empty() || glob.size() > 255)
      throw Error(Errc::invalid_argument, "bridge_carry: a topic pattern must have 1..255 characters");
  carried_ = options.bridge_carry;
  for (const auto& glob : options.mirror_channels)
    if (glob.empty() || glob.size() > 255)
      throw Error(Errc::invalid_argument, "mirror_channels: a channel pattern must have 1..255 characters");
}

TopicClass TopicPolicy::class_of(const std::string& channel) const {
  if (auto it = options_.topic_class.find(channel); it != options_.topic_class.end()) return it->second;
  std::lock_guard lock(mu_);
  for (const auto& glob : carried_)
    if (::fnmatch(glob.c_str(), channel.c_str(), 0) == 0) return TopicClass::large;
  return TopicClass::automatic;
}

bool TopicPolicy::mirrored(const std::string& channel) const {
  if (options_.mirror) return true;
  for (const auto& glob : options_.mirror_channels)
    if (::fnmatch(glob.c_str(), channel.c_str(), 0) == 0) return true;
  return false;
}

bool TopicPolicy::set_bridges(bool seen, std::vector<std::string> globs) {
  {
    std::lock_guard lock(mu_);
    carried_ = std::move(globs);
  }
  return bridge_seen_.exchange(seen) != seen;
}

}  // namespace lcmx::detail
