// Discovery glue (docs/ARCHITECTURE.md "Discovery"): other participants joining, changing and
// leaving (both scopes), and this participant's beacon.
#include <arpa/inet.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>

#include "internal.hpp"
#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/discovery/identity.hpp"

namespace lcmx::detail {
namespace {
// The port of "a.b.c.d:port", network order; 0 if there is none.
std::uint16_t port_of(const std::string& source) {
  const auto colon = source.rfind(':');
  if (colon == std::string::npos) return 0;
  const long port = std::strtol(source.c_str() + colon + 1, nullptr, 10);
  return port > 0 && port < 65536 ? htons(static_cast<std::uint16_t>(port)) : 0;
}
}  // namespace

// Scopes (DESIGN.md "Discovery"): a host-scope beacon comes from a participant of this host
// (shm path); a vehicle-scope beacon from another host's participant (udp path). Vehicle
// beacons of this host's participants are ignored: they are known through the host scope.
void RuntimeImpl::on_participant(std::int8_t scope, discovery::Change change,
                                 const discovery::Participant& p) {
  const auto& b = p.beacon;
  const bool vehicle = scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE;
  const bool same_host = static_cast<std::uint64_t>(b.host_id) == host;
  // A neighbour: this network namespace (host scope), another host id. Without a vehicle
  // group it is matched here, over UDP on the host-local group.
  const bool neighbour = !vehicle && !same_host;
  if (neighbour && change == discovery::Change::joined) report_neighbour(b);
  if (vehicle == same_host && !(neighbour && !vehicle_group)) return;
  auto& scope_map = vehicle ? vehicle_remotes : neighbour ? neighbour_remotes : remotes;
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    // Sources: which UDP sender is which participant.
    auto forget_sources = [&](std::map<std::string, std::int64_t>& m) {
      std::erase_if(m, [&](const auto& kv) { return kv.second == b.participant_id; });
    };
    forget_sources(vehicle ? vehicle_sources : neighbour ? neighbour_sources : host_sources);
    std::erase_if(neighbour ? neighbour_ports : host_ports,
                  [&](const auto& kv) { return !vehicle && kv.second == b.participant_id; });
    const std::string where = vehicle ? " on host " + std::to_string(b.host_id) : "";
    if (change == discovery::Change::left) {
      scope_map.erase(b.participant_id);
      if (!vehicle) forget_owner_locked(static_cast<std::uint64_t>(b.participant_id));
      events.push_back({Event::Kind::participant_left, "",
                        "participant " + b.process_name + " pid " + std::to_string(b.pid) + where + " left"});
    } else {
      if (change == discovery::Change::joined)
        events.push_back({Event::Kind::participant_joined, "",
                          "participant " + b.process_name + " pid " + std::to_string(b.pid) + where +
                              " joined"});
      scope_map[b.participant_id] = b;
      if (vehicle) {
        if (!b.vehicle_source.empty()) vehicle_sources[b.vehicle_source] = b.participant_id;
      } else if (neighbour) {
        if (!b.local_source.empty()) neighbour_sources[b.local_source] = b.participant_id;
        if (const auto port = port_of(b.local_source); port != 0) neighbour_ports[port] = b.participant_id;
      } else {
        if (!b.local_source.empty()) host_sources[b.local_source] = b.participant_id;
        if (const auto port = port_of(b.local_source); port != 0) host_ports[port] = b.participant_id;
        if (!b.vehicle_source.empty()) host_sources[b.vehicle_source] = b.participant_id;
      }
      // Its messages may have arrived before its beacon and been taken for a stock LCM
      // sender's: now that we know who it is, that foreign match goes (its real one, if its
      // type matches, comes from the beacon).
      std::vector<std::string> sources = {b.local_source, b.vehicle_source};
      if (!vehicle)  // its mirror: the local_source port from any address of this host
        if (const auto port = port_of(b.local_source); port != 0)
          for (const auto a : host_addresses)
            sources.push_back(udpm::to_string(udpm::Source{a, port}));
      for (const auto& src : sources) {
        if (src.empty()) continue;
        const auto key = std::hash<std::string>{}(src);
        for (auto& [id, sub] : subs) {
          auto& st = *sub->state;
          std::lock_guard l2(st.mu);
          if (std::erase_if(st.matches, [&](const auto& m) {
                return m->foreign && m->publisher_endpoint == key;
              })) {
            ++st.version;
            st.matched_cv.notify_all();
            announce_pending = true;
          }
        }
      }
    }
    // Any change of our matches is announced at once: publishers count subscribers by the
    // matches subscribers announce (versions only grow, so their sum tells).
    const auto match_versions = [&] {
      std::uint64_t v = 0;
      for (auto& [id, sub] : subs) {
        std::lock_guard l2(sub->state->mu);
        v += sub->state->version;
      }
      return v;
    };
    const auto v0 = match_versions();
    if (change != discovery::Change::left && !channel_subs.empty())
      for (const auto& e : b.endpoints)
        if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER) expand_locked(e.topic, events);
    if (!vehicle) update_bridges_locked();
    for (auto& [id, sub] : subs) sync_remote_locked(*sub, events);
    for (auto& [id, pub] : pubs) count_remote_locked(*pub, events);
    if (match_versions() != v0) ++revision, announce_pending = true;
  }
  if (announce_pending.exchange(false)) {
    if (disco) disco->announce_now();
    if (disco_vehicle) disco_vehicle->announce_now();
  }
  send_replays();
  // A participant of this host that died left shared memory: its registry's speaker reclaims
  // it (its segments only, by name: discovery::Registry), not every process of the host.
  emit(std::move(events));
}

// A host-scope beacon (this network namespace) from a participant with another host id: it
// sees another /dev/shm (another container) or has LCMX_HOST_ID set. No shared memory with
// it: it is reached over UDP, on the vehicle group if there is one (as another host), else
// on the host-local group (a neighbour, on_participant). Logged once per participant.
void RuntimeImpl::report_neighbour(const lcmx_msgs::beacon_t& b) {
  {
    std::lock_guard lock(mu);
    if (neighbours_reported.size() >= 1024) neighbours_reported.clear();  // bounded
    if (!neighbours_reported.insert(b.participant_id).second) return;
  }
  const std::string text = "participant " + b.process_name + " pid " + std::to_string(b.pid) +
                           " shares this network namespace but not this host's identity "
                           "(another /dev/shm, e.g. another container, or LCMX_HOST_ID): no "
                           "shared memory with it; it is reached over UDP on the " +
                           (vehicle_group ? std::string("vehicle group") : std::string("host-local group"));
  spdlog::info("lcmx: {}", text);
}

// Host scope: everything. Vehicle scope: the same endpoints without what only this host can
// use (shm segment names); addresses as "ip:port", never hostnames.
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
  const auto now = std::chrono::steady_clock::now();
  auto rate = [&](std::uint64_t id, std::uint64_t count) {
    auto& r = rates[id * 2 + (vehicle ? 1 : 0)];
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
  std::lock_guard lock(mu);
  b.revision = revision.load();
  // A bridge of this host announces its peers' large topics while someone here takes channels
  // by pattern (docs/bridge.md "Pattern subscribers").
  if (!vehicle && !channel_subs.empty())
    b.flags = static_cast<std::int8_t>(b.flags | lcmx_msgs::beacon_t::FLAG_CHANNELS);
  for (auto& w : nodes)
    if (auto n = w.lock()) b.nodes.push_back(n->name);
  b.num_nodes = static_cast<std::int32_t>(b.nodes.size());
  // Other hosts see neither a bridge's endpoints nor, while a bridge runs here, large
  // publishers: those reach them through the bridges (DESIGN.md "Discovery", scopes).
  if (vehicle && options.bridge) {
    b.num_endpoints = 0;
    return b;
  }
  for (auto& [id, pub] : pubs) {
    if (vehicle && pub->bridged_only()) continue;
    lcmx_msgs::endpoint_t e{};
    e.id = static_cast<std::int64_t>(id);
    e.kind = lcmx_msgs::endpoint_t::KIND_PUBLISHER;
    e.node = pub->node->name;
    e.topic = pub->channel();
    e.type_name = pub->type.name;
    e.fingerprint = pub->type.fingerprint;
    if (!vehicle) e.shm_segment = pub->segment_name();
    e.large = pub->large() ? 1 : 0;
    e.max_message_size = static_cast<std::int64_t>(pub->options.max_message_size);
    e.history = static_cast<std::int32_t>(pub->options.history);
    e.messages = static_cast<std::int64_t>(pub->published());
    e.rate_hz = rate(id, pub->published());
    e.errors = pub->errors;
    e.num_errors = static_cast<std::int32_t>(e.errors.size());
    b.endpoints.push_back(std::move(e));
  }
  for (auto& [id, sub] : subs) {
    lcmx_msgs::endpoint_t e{};
    e.id = static_cast<std::int64_t>(id);
    e.kind = lcmx_msgs::endpoint_t::KIND_SUBSCRIBER;
    e.node = sub->state->node_name;
    e.topic = sub->channel();
    e.type_name = sub->type().name;
    e.fingerprint = sub->type().fingerprint;
    e.messages = static_cast<std::int64_t>(sub->delivered.load());
    e.rate_hz = rate(id, sub->delivered.load());
    std::lock_guard l2(sub->state->mu);
    for (const auto& m : sub->state->matches) {
      lcmx_msgs::match_t mt;
      mt.publisher_participant = static_cast<std::int64_t>(m->publisher_participant);
      mt.publisher_endpoint = static_cast<std::int64_t>(m->publisher_endpoint);
      mt.path = to_string(m->path);
      mt.received = static_cast<std::int64_t>(m->stats->received.load());
      mt.drops = static_cast<std::int64_t>(m->stats->drops.load());
      e.drops += mt.drops;
      e.matches.push_back(std::move(mt));
    }
    e.num_matches = static_cast<std::int32_t>(e.matches.size());
    e.errors = sub->state->errors;
    e.num_errors = static_cast<std::int32_t>(e.errors.size());
    b.endpoints.push_back(std::move(e));
  }
  b.num_endpoints = static_cast<std::int32_t>(b.endpoints.size());
  return b;
}

}  // namespace lcmx::detail
