// Discovery glue (docs/ARCHITECTURE.md "Discovery"): other participants joining, changing and
// leaving (both scopes) go to the PeerTable and, as a delta, to Pairs; and this participant's
// beacon.
#include <spdlog/spdlog.h>
#include <unistd.h>

#include "internal.hpp"
#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/discovery/identity.hpp"

namespace lcmx::detail {

// Scopes (DESIGN.md "Discovery"): a host-scope beacon comes from a participant of this host
// (shm path); a vehicle-scope beacon from another host's participant (udp path). Vehicle
// beacons of this host's participants are ignored: they are known through the host scope.
// Discovery's delivery lock is held (changes arrive in the table's order).
void RuntimeImpl::on_participant(std::int8_t scope, discovery::Change change, const discovery::Participant& p) {
  const auto& b = p.beacon;
  const bool vehicle = scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE;
  const bool same_host = static_cast<std::uint64_t>(b.host_id) == host;
  // A neighbour: this network namespace (host scope), another host id. Without a vehicle
  // group it is matched here, over UDP on the host-local group.
  const bool neighbour = !vehicle && !same_host;
  if (neighbour && change == discovery::Change::joined) report_neighbour(b);
  if (vehicle == same_host && !(neighbour && !vehicle_group)) return;
  const Scope s = vehicle ? Scope::vehicle : neighbour ? Scope::neighbour : Scope::host;
  const auto delta = peers.apply(s, change, b);
  // (Whose data markers our receive filter takes: the publishers of what we subscribe to.)
  if (delta.structural && !delta.publisher_topics.empty() && front_door) front_door->filters_changed();
  settle(pairs.on_peer(delta, b, [this](std::uint32_t a) { return front_door && front_door->is_local_address(a); }));
  replays.send(pairs, participant_id, *local_group, vehicle_group.get());
  // A participant of this host that died left shared memory: its registry's speaker reclaims
  // it (its segments only, by name: discovery::Registry), not every process of the host.
}

// A host-scope beacon (this network namespace) from a participant with another host id: it
// sees another /dev/shm (another container) or has LCMX_HOST_ID set. No shared memory with
// it: it is reached over UDP, on the vehicle group if there is one (as another host), else
// on the host-local group (a neighbour). Logged once per participant.
void RuntimeImpl::report_neighbour(const lcmx_msgs::beacon_t& b) {
  {
    std::lock_guard lock(neighbours_mu_);
    if (neighbours_reported_.size() >= 1024) neighbours_reported_.clear();  // bounded
    if (!neighbours_reported_.insert(b.participant_id).second) return;
  }
  const std::string text = "participant " + b.process_name + " pid " + std::to_string(b.pid) +
                           " shares this network namespace but not this host's identity "
                           "(another /dev/shm, e.g. another container, or LCMX_HOST_ID): no "
                           "shared memory with it; it is reached over UDP on the " +
                           (vehicle_group ? std::string("vehicle group") : std::string("host-local group"));
  spdlog::info("lcmx: {}", text);
}

// Host scope: everything. Vehicle scope: without what only this host can use (Pairs::describe);
// addresses as "ip:port", never hostnames.
lcmx_msgs::beacon_t RuntimeImpl::build_beacon(std::int8_t scope) {
  const bool vehicle = scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE;
  lcmx_msgs::beacon_t b{};
  b.version = discovery::kBeaconVersion;
  b.scope = scope;
  b.local_source = udpm::to_string(local_group->local_source());
  if (vehicle_group) b.vehicle_source = udpm::to_string(vehicle_group->local_source());
  b.participant_id = static_cast<std::int64_t>(participant_id);
  b.host_id = static_cast<std::int64_t>(host);
  b.pid = static_cast<std::int32_t>(::getpid());
  b.process_name = discovery::process_name();
  b.flags = options.bridge ? lcmx_msgs::beacon_t::FLAG_BRIDGE : 0;
  if (options.dds_gateway) b.flags = static_cast<std::int8_t>(b.flags | lcmx_msgs::beacon_t::FLAG_DDS_GATEWAY);
  if (!vehicle) b.carried = options.bridge_carry;
  b.num_carried = static_cast<std::int32_t>(b.carried.size());
  b.revision = revision_.load();
  const auto now = std::chrono::steady_clock::now();
  std::lock_guard lock(rate_mu_);
  auto rate = [&](std::uint64_t id, std::uint64_t count) {
    auto& r = rates_[id * 2 + (vehicle ? 1 : 0)];
    r.used = true;
    if (r.when == std::chrono::steady_clock::time_point{}) {
      r.count = count;
      r.when = now;
      return 0.0;
    }
    if (now - r.when >= kRateWindow) {
      r.hz = static_cast<double>(count - r.count) / std::chrono::duration<double>(now - r.when).count();
      r.count = count;
      r.when = now;
    }
    return r.hz;
  };
  pairs.describe(vehicle, b, rate);
  // Endpoints gone since the last beacon of this scope: their rates go too.
  for (auto it = rates_.begin(); it != rates_.end();) {
    if ((it->first & 1) != (vehicle ? 1u : 0u)) {
      ++it;
    } else if (!it->second.used) {
      it = rates_.erase(it);
    } else {
      it->second.used = false;
      ++it;
    }
  }
  return b;
}

}  // namespace lcmx::detail
