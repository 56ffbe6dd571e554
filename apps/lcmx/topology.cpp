#include "topology.hpp"

#include <arpa/inet.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <thread>

#include "log_common.hpp"
#include "tools_common.hpp"
#include "lcmx/udpm/udpm.hpp"

namespace lcmx::cli {
namespace {

using Endpoint = lcmx_msgs::endpoint_t;
using Beacon = lcmx_msgs::beacon_t;

std::string who(const Beacon& b, const Endpoint& e) {
  return b.process_name + "[" + std::to_string(b.pid) + "]/" + e.node;
}

// Every name below comes from a beacon (whoever can send on the group chose it): escaped for
// the text output (safe_text.hpp); the JSON output escapes by JSON's rules (json_str).
std::string P(const std::string& s) { return printable(s); }

std::string host_hex(std::int64_t h) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(h));
  return buf;
}

std::string fp_hex(std::int64_t fp) {
  char buf[24];
  std::snprintf(buf, sizeof buf, "0x%016llx", static_cast<unsigned long long>(fp));
  return buf;
}

std::string num(double v) { return std::isfinite(v) ? fmt("%.3f", v) : "null"; }

// The endpoint's type as JSON members: "type" (as type_label, null for raw), "type_name" (the
// beacon's), "fingerprint" (hex string, null for raw).
std::string json_type(const Endpoint& e, const types::TypeRegistry* types) {
  if (e.fingerprint == 0) return "\"type\":null,\"type_name\":null,\"fingerprint\":null";
  return "\"type\":" + json_str(type_label(e, types)) + ",\"type_name\":" + json_str(e.type_name) +
         ",\"fingerprint\":" + json_str(fp_hex(e.fingerprint));
}

std::string json_strings(const std::vector<std::string>& v) {
  std::string o = "[";
  for (std::size_t i = 0; i < v.size(); ++i) o += (i ? "," : "") + json_str(v[i]);
  return o + "]";
}

// Every endpoint of the beacons, by topic, and the publishers by (participant, endpoint id):
// what `topics` (text and JSON) prints from. Points into `ps`, which must outlive it.
struct Ref {
  const Beacon* b;
  const Endpoint* e;
};
struct TopicIndex {
  std::map<std::string, std::vector<Ref>> by_topic;
  std::map<std::pair<std::int64_t, std::int64_t>, Ref> publishers;
  explicit TopicIndex(const std::vector<discovery::Participant>& ps) {
    for (const auto& p : ps)
      for (const auto& e : p.beacon.endpoints) {
        by_topic[e.topic].push_back({&p.beacon, &e});
        if (e.kind == Endpoint::KIND_PUBLISHER) publishers[{p.beacon.participant_id, e.id}] = {&p.beacon, &e};
      }
  }
};

}  // namespace

std::string type_label(const Endpoint& e, const types::TypeRegistry* types) {
  if (e.fingerprint == 0) return "raw";
  const std::string own = e.type_name.empty() ? fp_hex(e.fingerprint) : e.type_name;
  if (types == nullptr) return own;
  const auto fp = static_cast<std::uint64_t>(e.fingerprint);
  const types::StructType* first = nullptr;
  for (const auto& t : types->types()) {
    if (t->fingerprint != fp) continue;
    if (t->name == e.type_name) return t->full_name();
    if (first == nullptr) first = t.get();
  }
  return first ? first->full_name() : own;
}

void print_nodes(std::ostream& out, const std::vector<discovery::Participant>& ps, const types::TypeRegistry* types) {
  if (ps.empty()) {
    out << "no participants found\n";
    return;
  }
  for (const auto& p : ps) {
    const auto& b = p.beacon;
    out << "participant " << P(b.process_name) << " pid " << b.pid << "  host " << host_hex(b.host_id)
        << "  id " << b.participant_id << "  seen on "
        << (b.scope == Beacon::SCOPE_VEHICLE ? "vehicle group" : "host-local group");
    if (!b.vehicle_source.empty()) out << "  vehicle address " << P(b.vehicle_source);
    if (b.flags & Beacon::FLAG_BRIDGE) {
      out << "  MESSAGE BRIDGE";
      if (!b.carried.empty()) {
        out << " (carries";
        for (const auto& c : b.carried) out << " " << P(c);
        out << ")";
      }
    }
    out << "\n";
    for (const auto& n : b.nodes) {
      out << "  node " << P(n) << "\n";
      for (const auto& e : b.endpoints) {
        if (e.node != n) continue;
        const bool pub = e.kind == Endpoint::KIND_PUBLISHER;
        out << "    " << (pub ? "pub " : "sub ") << P(e.topic) << "  ["
            << P(type_label(e, types)) << "]  " << e.messages << " msgs  "
            << fmt("%.1f Hz", e.rate_hz);
        if (!pub) out << "  drops " << e.drops;
        out << "\n";
        for (const auto& err : e.errors) out << "      ERROR: " << P(err) << "\n";
      }
    }
  }
}

void print_topics(std::ostream& out, const std::vector<discovery::Participant>& ps, const types::TypeRegistry* types) {
  const TopicIndex index(ps);
  const auto& by_topic = index.by_topic;
  const auto& pub_index = index.publishers;
  if (by_topic.empty()) {
    out << "no topics found (topics come from lcmx participants' beacons; channels of stock LCM programs "
           "show in `lcmx monitor` and `lcmx hz`)\n";
    return;
  }
  for (const auto& [topic, refs] : by_topic) {
    std::set<std::string> names;
    int npub = 0, nsub = 0;
    for (const auto& r : refs) {
      if (r.e->fingerprint != 0) names.insert(type_label(*r.e, types));
      (r.e->kind == Endpoint::KIND_PUBLISHER ? npub : nsub)++;
    }
    std::string type;
    for (const auto& t : names) type += (type.empty() ? "" : " | ") + t;
    if (type.empty()) type = "raw";
    // Endpoints of DDS gateways (FLAG_DDS_GATEWAY): the channel is mapped to a DDS topic.
    std::set<std::string> gateways;
    for (const auto& r : refs)
      if (r.b->flags & Beacon::FLAG_DDS_GATEWAY) gateways.insert(P(r.b->process_name) + " pid " + std::to_string(r.b->pid));
    std::string dds;
    for (const auto& g : gateways) dds += (dds.empty() ? "  DDS-mapped by " : ", ") + g;
    out << P(topic) << "  [" << P(type) << "]  " << npub << " publisher(s), " << nsub
        << " subscriber(s)" << (names.size() > 1 ? "  CONFLICT: different types" : "") << dds << "\n";
    for (const auto& r : refs) {
      if (r.e->kind != Endpoint::KIND_PUBLISHER) continue;
      out << "  pub " << P(who(*r.b, *r.e)) << "  host " << host_hex(r.b->host_id) << "  "
          << r.e->messages << " msgs  " << fmt("%.1f Hz", r.e->rate_hz)
          << (r.e->large ? "  class large" : "  class small") << "\n";
    }
    for (const auto& r : refs) {
      if (r.e->kind != Endpoint::KIND_SUBSCRIBER) continue;
      out << "  sub " << P(who(*r.b, *r.e)) << "  host " << host_hex(r.b->host_id) << "  "
          << r.e->messages << " msgs  " << fmt("%.1f Hz", r.e->rate_hz) << "  drops " << r.e->drops
          << "\n";
      for (const auto& m : r.e->matches) {
        auto it = pub_index.find({m.publisher_participant, m.publisher_endpoint});
        const std::string from = it == pub_index.end() ? "participant " + std::to_string(m.publisher_participant)
                                                       : who(*it->second.b, *it->second.e);
        out << "      <- " << P(from) << "  path " << P(m.path) << "  received " << m.received
            << "  drops " << m.drops << "\n";
      }
      for (const auto& err : r.e->errors) out << "      ERROR: " << P(err) << "\n";
    }
  }
}

void print_nodes_json(std::ostream& out, const std::vector<discovery::Participant>& ps,
                      const types::TypeRegistry* types) {
  std::ostringstream j;
  j << "{\"participants\":[";
  for (std::size_t i = 0; i < ps.size(); ++i) {
    const auto& b = ps[i].beacon;
    j << (i ? "," : "") << "{\"process\":" << json_str(b.process_name) << ",\"pid\":" << b.pid
      << ",\"host\":" << json_str(host_hex(b.host_id)) << ",\"id\":" << b.participant_id << ",\"scope\":"
      << (b.scope == Beacon::SCOPE_VEHICLE ? "\"vehicle\"" : "\"host\"")
      << ",\"vehicle_source\":" << json_str(b.vehicle_source)
      << ",\"bridge\":" << ((b.flags & Beacon::FLAG_BRIDGE) ? "true" : "false")
      << ",\"carries\":" << json_strings(b.carried) << ",\"nodes\":[";
    for (std::size_t n = 0; n < b.nodes.size(); ++n) {
      j << (n ? "," : "") << "{\"name\":" << json_str(b.nodes[n]) << ",\"endpoints\":[";
      bool first = true;
      for (const auto& e : b.endpoints) {
        if (e.node != b.nodes[n]) continue;
        const bool pub = e.kind == Endpoint::KIND_PUBLISHER;
        j << (first ? "" : ",") << "{\"kind\":" << (pub ? "\"pub\"" : "\"sub\"") << ",\"topic\":" << json_str(e.topic)
          << "," << json_type(e, types) << ",\"messages\":" << e.messages << ",\"rate_hz\":" << num(e.rate_hz);
        if (!pub) j << ",\"drops\":" << e.drops;
        j << ",\"errors\":" << json_strings(e.errors) << "}";
        first = false;
      }
      j << "]}";
    }
    j << "]}";
  }
  j << "]}";
  out << j.str() << "\n";
}

void print_topics_json(std::ostream& out, const std::vector<discovery::Participant>& ps,
                       const types::TypeRegistry* types) {
  const TopicIndex index(ps);
  const auto& by_topic = index.by_topic;
  const auto& pub_index = index.publishers;
  auto who_json = [](const Ref& r) {
    return "\"process\":" + json_str(r.b->process_name) + ",\"pid\":" + std::to_string(r.b->pid) +
           ",\"node\":" + json_str(r.e->node) + ",\"host\":" + json_str(host_hex(r.b->host_id)) +
           ",\"participant\":" + std::to_string(r.b->participant_id) + ",\"endpoint\":" + std::to_string(r.e->id);
  };
  std::ostringstream j;
  j << "{\"topics\":[";
  bool first_topic = true;
  for (const auto& [topic, refs] : by_topic) {
    std::set<std::string> names;
    for (const auto& r : refs)
      if (r.e->fingerprint != 0) names.insert(type_label(*r.e, types));
    j << (first_topic ? "" : ",") << "{\"topic\":" << json_str(topic) << ",\"types\":"
      << json_strings({names.begin(), names.end()}) << ",\"conflict\":" << (names.size() > 1 ? "true" : "false")
      << ",\"dds_mapped\":"
      << (std::any_of(refs.begin(), refs.end(), [](const Ref& r) { return (r.b->flags & Beacon::FLAG_DDS_GATEWAY) != 0; })
              ? "true" : "false")
      << ",\"publishers\":[";
    first_topic = false;
    bool first = true;
    for (const auto& r : refs) {
      if (r.e->kind != Endpoint::KIND_PUBLISHER) continue;
      j << (first ? "" : ",") << "{" << who_json(r) << "," << json_type(*r.e, types) << ",\"messages\":" << r.e->messages
        << ",\"rate_hz\":" << num(r.e->rate_hz) << ",\"class\":" << (r.e->large ? "\"large\"" : "\"small\"") << "}";
      first = false;
    }
    j << "],\"subscribers\":[";
    first = true;
    for (const auto& r : refs) {
      if (r.e->kind != Endpoint::KIND_SUBSCRIBER) continue;
      j << (first ? "" : ",") << "{" << who_json(r) << "," << json_type(*r.e, types) << ",\"messages\":" << r.e->messages
        << ",\"rate_hz\":" << num(r.e->rate_hz) << ",\"drops\":" << r.e->drops << ",\"matches\":[";
      first = false;
      for (std::size_t m = 0; m < r.e->matches.size(); ++m) {
        const auto& x = r.e->matches[m];
        auto it = pub_index.find({x.publisher_participant, x.publisher_endpoint});
        j << (m ? "," : "") << "{\"publisher\":"
          << (it == pub_index.end() ? std::string("null") : json_str(who(*it->second.b, *it->second.e)))
          << ",\"publisher_participant\":" << x.publisher_participant << ",\"publisher_endpoint\":"
          << x.publisher_endpoint << ",\"path\":" << json_str(x.path) << ",\"received\":" << x.received
          << ",\"drops\":" << x.drops << "}";
      }
      j << "],\"errors\":" << json_strings(r.e->errors) << "}";
    }
    j << "]}";
  }
  j << "]}";
  out << j.str() << "\n";
}

// Listens on the host-local group, and on the vehicle group when given, for `wait_ms`.
// A participant seen in both scopes is listed once, from its host-local beacon (complete).
std::vector<discovery::Participant> observe(const Globals& g, std::vector<GroupSeen>* groups) {
  const int wait_ms = g.wait_ms;
  std::vector<std::unique_ptr<discovery::Discovery>> observers;
  std::vector<std::shared_ptr<udpm::Refusals>> refusals;
  for (const bool vehicle : {false, true}) {
    if (vehicle && g.vehicle_url.empty()) continue;
    auto o = observer_options(g, vehicle);
    o.group.refusals = std::make_shared<udpm::Refusals>();
    refusals.push_back(o.group.refusals);
    if (groups) groups->push_back(GroupSeen{vehicle, vehicle ? g.vehicle_url : g.url, o.group.keys, {}});
    observers.push_back(std::make_unique<discovery::Discovery>(o, nullptr, nullptr));
  }
  // Participants answer the query at once; a second query covers a lost datagram.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(wait_ms);
  std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms / 2));  // a listening window
  for (auto& d : observers) d->query();
  std::this_thread::sleep_until(deadline);
  std::vector<discovery::Participant> all;
  std::set<std::int64_t> seen;
  for (auto& d : observers) {
    for (auto& p : d->participants())
      if (seen.insert(p.beacon.participant_id).second) all.push_back(std::move(p));
    d->stop();
  }
  if (groups)
    for (std::size_t i = 0; i < groups->size(); ++i) (*groups)[i].refused = refusals[i]->sources();
  return all;
}

namespace {
std::string keyed_text(const GroupSeen& s) {
  if (!s.keys) return "unkeyed (open to anyone on it; stock LCM programs can use it)";
  char id[16];
  std::snprintf(id, sizeof id, "%08x", s.keys->keys[0].id);
  std::string t = std::string("keyed (") + (s.keys->encrypt ? "encrypted" : "authenticated") + ", key " + id;
  if (s.keys->keys.size() > 1) {
    std::snprintf(id, sizeof id, "%08x", s.keys->keys[1].id);
    t += ", also accepting " + std::string(id);
  }
  return t + ")";
}
}  // namespace

void print_groups(std::ostream& out, const std::vector<GroupSeen>& groups) {
  for (const auto& s : groups) {
    out << "group " << (s.vehicle ? "vehicle" : "host-local") << " " << P(s.url) << ": " << keyed_text(s) << "\n";
    for (const auto& r : s.refused) out << "  " << udpm::describe(r) << " (" << r.count << " datagram(s))\n";
  }
}

std::string groups_json(const std::vector<GroupSeen>& groups) {
  std::ostringstream j;
  j << "[";
  for (std::size_t i = 0; i < groups.size(); ++i) {
    const auto& s = groups[i];
    j << (i ? "," : "") << "{\"scope\":" << (s.vehicle ? "\"vehicle\"" : "\"host\"") << ",\"url\":" << json_str(s.url)
      << ",\"keyed\":" << (s.keys ? "true" : "false") << ",\"encrypted\":" << (s.keys && s.keys->encrypt ? "true" : "false")
      << ",\"refused\":[";
    for (std::size_t k = 0; k < s.refused.size(); ++k) {
      const auto& r = s.refused[k];
      char a[INET_ADDRSTRLEN] = {};
      in_addr addr{};
      addr.s_addr = r.address_be;
      ::inet_ntop(AF_INET, &addr, a, sizeof a);
      j << (k ? "," : "") << "{\"source\":" << json_str(a) << ",\"reason\":" << json_str(udpm::to_string(r.first))
        << ",\"datagrams\":" << r.count << ",\"text\":" << json_str(udpm::describe(r)) << "}";
    }
    j << "]}";
  }
  j << "]";
  return j.str();
}

}  // namespace lcmx::cli
