#include "peers.hpp"

#include <arpa/inet.h>

#include <algorithm>
#include <cstdlib>

namespace lcmx::detail {

std::optional<udpm::Source> parse_source(const std::string& text) {
  const auto colon = text.rfind(':');
  if (colon == std::string::npos || colon == 0) return std::nullopt;
  in_addr a{};
  if (::inet_pton(AF_INET, text.substr(0, colon).c_str(), &a) != 1) return std::nullopt;
  char* end = nullptr;
  const long port = std::strtol(text.c_str() + colon + 1, &end, 10);
  if (end == text.c_str() + colon + 1 || *end != '\0' || port <= 0 || port > 65535) return std::nullopt;
  return udpm::Source{a.s_addr, htons(static_cast<std::uint16_t>(port))};
}

namespace {
// FNV-1a over what matching reads.
struct Hash {
  std::uint64_t h = 1469598103934665603ull;
  void bytes(const void* p, std::size_t n) {
    const auto* b = static_cast<const unsigned char*>(p);
    for (std::size_t i = 0; i < n; ++i) h = (h ^ b[i]) * 1099511628211ull;
  }
  template <class T>
  void value(const T& v) { bytes(&v, sizeof v); }
  void text(const std::string& s) {
    value(s.size());
    bytes(s.data(), s.size());
  }
};
}  // namespace

// Everything of a beacon that decides pairs, and nothing that changes with traffic (messages,
// rates, received, drops): a peer whose shape is unchanged needs no matching, whatever its
// `revision` says (a forged or stale revision cannot hide a change either).
std::uint64_t PeerTable::shape_of(const lcmx_msgs::beacon_t& b) {
  Hash h;
  h.value(b.flags);
  h.text(b.local_source);
  h.text(b.vehicle_source);
  for (const auto& g : b.carried) h.text(g);
  for (const auto& e : b.endpoints) {
    h.value(e.id);
    h.value(e.kind);
    h.text(e.node);
    h.text(e.topic);
    h.text(e.type_name);
    h.value(e.fingerprint);
    h.text(e.shm_segment);
    h.value(e.large);
    h.value(e.history);
    for (const auto& m : e.matches) {
      h.value(m.publisher_participant);
      h.value(m.publisher_endpoint);
      h.text(m.path);
    }
    for (const auto& x : e.errors) h.text(x);
  }
  return h.h;
}

void PeerTable::index(const Peer& p, bool add) {
  const auto id = p.beacon.participant_id;
  for (const auto& e : p.beacon.endpoints) {
    auto& by_topic = e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER ? publishers_ : subscribers_;
    if (add) {
      ++by_topic[e.topic][id];
      continue;
    }
    auto t = by_topic.find(e.topic);
    if (t == by_topic.end()) continue;
    auto c = t->second.find(id);
    if (c != t->second.end() && --c->second <= 0) t->second.erase(c);
    if (t->second.empty()) by_topic.erase(t);
  }
  auto key = [](const udpm::Source& s) { return std::make_pair(s.address_be, s.port_be); };
  auto set = [&](auto& map, const std::optional<udpm::Source>& s) {
    if (!s) return;
    if (add) map[key(*s)] = id;
    else if (auto it = map.find(key(*s)); it != map.end() && it->second == id) map.erase(it);
  };
  set(local_sources_, p.local_source);
  set(vehicle_sources_, p.vehicle_source);
  if (p.scope != Scope::vehicle && p.local_source) {
    if (add) local_ports_[p.local_source->port_be] = id;
    else if (auto it = local_ports_.find(p.local_source->port_be); it != local_ports_.end() && it->second == id)
      local_ports_.erase(it);
  }
}

PeerTable::Delta PeerTable::apply(Scope scope, discovery::Change change, const lcmx_msgs::beacon_t& b) {
  Delta d;
  d.scope = scope;
  d.change = change;
  auto topics = [&](const lcmx_msgs::beacon_t& x) {
    for (const auto& e : x.endpoints)
      (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER ? d.publisher_topics : d.subscriber_topics).insert(e.topic);
    if (scope == Scope::host && (x.flags & lcmx_msgs::beacon_t::FLAG_BRIDGE)) d.bridge = true;
  };
  std::lock_guard lock(mu_);
  auto it = peers_.find(b.participant_id);
  if (it != peers_.end()) {
    d.before = it->second.beacon;
    topics(d.before);
  }
  if (change == discovery::Change::left) {
    if (it == peers_.end()) return d;
    index(it->second, false);
    peers_.erase(it);
    d.structural = true;
    return d;
  }
  Peer p;
  p.scope = scope;
  p.beacon = b;
  p.shape = shape_of(b);
  p.local_source = parse_source(b.local_source);
  p.vehicle_source = parse_source(b.vehicle_source);
  if (it != peers_.end() && it->second.scope == scope && it->second.shape == p.shape) {
    it->second.beacon = std::move(p.beacon);  // statistics only
    return d;
  }
  d.structural = true;
  topics(b);
  if (it != peers_.end()) {
    index(it->second, false);
    it->second = std::move(p);
  } else {
    it = peers_.emplace(b.participant_id, std::move(p)).first;
  }
  index(it->second, true);
  return d;
}

std::vector<PeerTable::Endpoint> PeerTable::endpoints_on(const std::string& topic, std::int8_t kind) const {
  std::vector<Endpoint> out;
  std::lock_guard lock(mu_);
  const auto& by_topic = kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER ? publishers_ : subscribers_;
  auto t = by_topic.find(topic);
  if (t == by_topic.end()) return out;
  for (const auto& [id, count] : t->second) {
    auto p = peers_.find(id);
    if (p == peers_.end()) continue;
    const auto& b = p->second.beacon;
    for (const auto& e : b.endpoints) {
      if (e.kind != kind || e.topic != topic) continue;
      out.push_back({p->second.scope, id, b.flags, b.process_name, b.pid, b.pid_namespace, e});
    }
  }
  return out;
}

std::set<std::string> PeerTable::published_topics() const {
  std::set<std::string> out;
  std::lock_guard lock(mu_);
  for (const auto& [topic, ids] : publishers_)
    for (const auto& [id, n] : ids)
      if (auto p = peers_.find(id); p != peers_.end() && p->second.scope != Scope::neighbour) {
        out.insert(topic);
        break;
      }
  return out;
}

std::set<std::string> PeerTable::published_by(std::int64_t id) const {
  std::set<std::string> out;
  std::lock_guard lock(mu_);
  auto p = peers_.find(id);
  if (p == peers_.end()) return out;
  for (const auto& e : p->second.beacon.endpoints)
    if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER) out.insert(e.topic);
  return out;
}

PeerTable::Publishing PeerTable::publishing(std::int64_t id, const std::string& topic) const {
  Publishing out;
  std::lock_guard lock(mu_);
  auto p = peers_.find(id);
  if (p == peers_.end()) return out;
  out.flags = p->second.beacon.flags;
  for (const auto& e : p->second.beacon.endpoints)
    if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER && e.topic == topic) out.publishes = true;
  return out;
}

PeerTable::Sender PeerTable::sender(bool vehicle, const udpm::Source& source, bool local_address) const {
  std::lock_guard lock(mu_);
  auto found = [&](std::int64_t id) {
    auto p = peers_.find(id);
    return Sender{id, p != peers_.end() && p->second.scope == Scope::host};
  };
  const auto key = std::make_pair(source.address_be, source.port_be);
  if (vehicle) {
    if (auto it = vehicle_sources_.find(key); it != vehicle_sources_.end()) return found(it->second);
    return {};
  }
  if (auto it = local_sources_.find(key); it != local_sources_.end()) return found(it->second);
  // A participant of this network namespace sends its mirror (and a neighbour its messages)
  // from the same port and another address of this host: where the group routes.
  if (local_address)
    if (auto it = local_ports_.find(source.port_be); it != local_ports_.end()) return found(it->second);
  // A same-host participant's vehicle socket (its vehicle-group messages heard here).
  if (auto it = vehicle_sources_.find(key); it != vehicle_sources_.end()) {
    const auto s = found(it->second);
    if (s.same_host) return s;
  }
  return {};
}

std::optional<udpm::Source> PeerTable::source_of(std::int64_t id, bool vehicle) const {
  std::lock_guard lock(mu_);
  auto p = peers_.find(id);
  if (p == peers_.end()) return std::nullopt;
  return vehicle ? p->second.vehicle_source : p->second.local_source;
}

bool PeerTable::announced(std::uint64_t participant, std::uint64_t endpoint) const {
  std::lock_guard lock(mu_);
  auto p = peers_.find(static_cast<std::int64_t>(participant));
  if (p == peers_.end()) return false;
  for (const auto& e : p->second.beacon.endpoints)
    if (static_cast<std::uint64_t>(e.id) == endpoint) return true;
  return false;
}

std::optional<PeerTable::Endpoint> PeerTable::host_endpoint(std::uint64_t participant, std::uint64_t endpoint) const {
  std::lock_guard lock(mu_);
  auto p = peers_.find(static_cast<std::int64_t>(participant));
  if (p == peers_.end() || p->second.scope != Scope::host) return std::nullopt;
  const auto& b = p->second.beacon;
  for (const auto& e : b.endpoints)
    if (static_cast<std::uint64_t>(e.id) == endpoint)
      return Endpoint{Scope::host, b.participant_id, b.flags, b.process_name, b.pid, b.pid_namespace, e};
  return std::nullopt;
}

PeerTable::Bridges PeerTable::host_bridges() const {
  Bridges out;
  std::lock_guard lock(mu_);
  for (const auto& [id, p] : peers_) {
    if (p.scope != Scope::host || !(p.beacon.flags & lcmx_msgs::beacon_t::FLAG_BRIDGE)) continue;
    out.seen = true;
    for (const auto& g : p.beacon.carried)
      if (!g.empty() && std::find(out.carried.begin(), out.carried.end(), g) == out.carried.end())
        out.carried.push_back(g);
  }
  return out;
}

}  // namespace lcmx::detail
