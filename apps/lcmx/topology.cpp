#include "topology.hpp"

#include <algorithm>
#include <cstdio>
#include <map>
#include <set>
#include <string>

namespace lcmx::cli {
namespace {

using Endpoint = lcmx_msgs::endpoint_t;
using Beacon = lcmx_msgs::beacon_t;

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

std::string who(const Beacon& b, const Endpoint& e) {
  return b.process_name + "[" + std::to_string(b.pid) + "]/" + e.node;
}

std::string host_hex(std::int64_t h) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(h));
  return buf;
}

}  // namespace

void print_nodes(std::ostream& out, const std::vector<discovery::Participant>& ps) {
  if (ps.empty()) {
    out << "no participants found\n";
    return;
  }
  for (const auto& p : ps) {
    const auto& b = p.beacon;
    out << "participant " << b.process_name << " pid " << b.pid << "  host " << host_hex(b.host_id)
        << "  id " << b.participant_id << "  seen on "
        << (b.scope == Beacon::SCOPE_VEHICLE ? "vehicle group" : "host-local group");
    if (!b.vehicle_source.empty()) out << "  vehicle address " << b.vehicle_source;
    if (b.flags & Beacon::FLAG_BRIDGE) {
      out << "  MESSAGE BRIDGE";
      if (!b.carried.empty()) {
        out << " (carries";
        for (const auto& c : b.carried) out << " " << c;
        out << ")";
      }
    }
    out << "\n";
    for (const auto& n : b.nodes) {
      out << "  node " << n << "\n";
      for (const auto& e : b.endpoints) {
        if (e.node != n) continue;
        const bool pub = e.kind == Endpoint::KIND_PUBLISHER;
        out << "    " << (pub ? "pub " : "sub ") << e.topic << "  ["
            << (e.type_name.empty() ? "raw" : e.type_name) << "]  " << e.messages << " msgs  "
            << fmt("%.1f Hz", e.rate_hz);
        if (!pub) out << "  drops " << e.drops;
        out << "\n";
        for (const auto& err : e.errors) out << "      ERROR: " << err << "\n";
      }
    }
  }
}

void print_topics(std::ostream& out, const std::vector<discovery::Participant>& ps) {
  struct Ref {
    const Beacon* b;
    const Endpoint* e;
  };
  std::map<std::string, std::vector<Ref>> by_topic;
  std::map<std::pair<std::int64_t, std::int64_t>, Ref> pub_index;
  for (const auto& p : ps)
    for (const auto& e : p.beacon.endpoints) {
      by_topic[e.topic].push_back({&p.beacon, &e});
      if (e.kind == Endpoint::KIND_PUBLISHER) pub_index[{p.beacon.participant_id, e.id}] = {&p.beacon, &e};
    }
  if (by_topic.empty()) {
    out << "no topics found\n";
    return;
  }
  for (const auto& [topic, refs] : by_topic) {
    std::set<std::string> types;
    int npub = 0, nsub = 0;
    for (const auto& r : refs) {
      if (r.e->fingerprint != 0) types.insert(r.e->type_name);
      (r.e->kind == Endpoint::KIND_PUBLISHER ? npub : nsub)++;
    }
    std::string type;
    for (const auto& t : types) type += (type.empty() ? "" : " | ") + t;
    if (type.empty()) type = "raw";
    out << topic << "  [" << type << "]  " << npub << " publisher(s), " << nsub
        << " subscriber(s)" << (types.size() > 1 ? "  CONFLICT: different types" : "") << "\n";
    for (const auto& r : refs) {
      if (r.e->kind != Endpoint::KIND_PUBLISHER) continue;
      out << "  pub " << who(*r.b, *r.e) << "  host " << host_hex(r.b->host_id) << "  "
          << r.e->messages << " msgs  " << fmt("%.1f Hz", r.e->rate_hz)
          << (r.e->large ? "  class large" : "  class small") << "\n";
    }
    for (const auto& r : refs) {
      if (r.e->kind != Endpoint::KIND_SUBSCRIBER) continue;
      out << "  sub " << who(*r.b, *r.e) << "  host " << host_hex(r.b->host_id) << "  "
          << r.e->messages << " msgs  " << fmt("%.1f Hz", r.e->rate_hz) << "  drops " << r.e->drops
          << "\n";
      for (const auto& m : r.e->matches) {
        auto it = pub_index.find({m.publisher_participant, m.publisher_endpoint});
        const std::string from = it == pub_index.end() ? "participant " + std::to_string(m.publisher_participant)
                                                       : who(*it->second.b, *it->second.e);
        out << "      <- " << from << "  path " << m.path << "  received " << m.received
            << "  drops " << m.drops << "\n";
      }
      for (const auto& err : r.e->errors) out << "      ERROR: " << err << "\n";
    }
  }
}

}  // namespace lcmx::cli
