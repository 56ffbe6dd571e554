// What the runtime answers for services and actions beyond publish/subscribe (see
// internal.hpp).
#include "internal.hpp"

namespace lcmx::detail {

bool RuntimeImpl::subscriber_announced(std::uint64_t participant, const std::string& channel) {
  std::lock_guard lock(mu);
  if (participant == participant_id) {
    for (const auto& [id, sub] : subs)
      if (sub->channel() == channel) return true;
    return false;
  }
  const auto id = static_cast<std::int64_t>(participant);
  for (const auto* table : {&remotes, &vehicle_remotes, &neighbour_remotes}) {
    auto it = table->find(id);
    if (it == table->end()) continue;
    for (const auto& e : it->second.endpoints)
      if (e.kind == lcmx_msgs::endpoint_t::KIND_SUBSCRIBER && e.topic == channel) return true;
  }
  return false;
}

}  // namespace lcmx::detail
