#include "graph_model.hpp"

#include <algorithm>
#include <cstdio>
#include <map>
#include <set>
#include <sstream>
#include <tuple>

#include "log_common.hpp"

namespace lcmx::cli::graph {
namespace {

using Endpoint = lcmx_msgs::endpoint_t;
using Beacon = lcmx_msgs::beacon_t;

std::string host_hex(std::int64_t h) {
  char b[24];
  std::snprintf(b, sizeof b, "%016llx", static_cast<unsigned long long>(h));
  return b;
}

// A DOT string. Each line of `s` is escaped as for a terminal first (safe_text.hpp printable:
// control characters, which DOT would pass on to a terminal or into labels, as \xNN; a backslash
// as \\, which DOT reads as one), then its quotes; the lines are joined with DOT's \n (labels of
// several lines: a topic and its types).
std::string q(const std::string& s) {
  std::string o = "\"";
  std::size_t start = 0;
  for (;;) {
    const auto nl = s.find('\n', start);
    for (char c : printable(std::string_view(s).substr(start, nl == std::string::npos ? nl : nl - start))) {
      if (c == '"') o += '\\';
      o += c;
    }
    if (nl == std::string::npos) break;
    o += "\\n";
    start = nl + 1;
  }
  return o + "\"";
}

std::string proc_label(const Beacon& b) { return b.process_name + "[" + std::to_string(b.pid) + "]"; }

struct Pub {
  const Beacon* b;
  const Endpoint* e;
};

using PubIndex = std::map<std::pair<std::int64_t, std::int64_t>, Pub>;

PubIndex index_publishers(const std::vector<discovery::Participant>& ps) {
  PubIndex idx;
  for (const auto& p : ps)
    for (const auto& e : p.beacon.endpoints)
      if (e.kind == Endpoint::KIND_PUBLISHER) idx[{p.beacon.participant_id, e.id}] = {&p.beacon, &e};
  return idx;
}

std::string publisher_name(const PubIndex& idx, const lcmx_msgs::match_t& m) {
  if (m.publisher_participant == 0) return "LCM sender";
  auto it = idx.find({m.publisher_participant, m.publisher_endpoint});
  if (it == idx.end()) return "participant " + std::to_string(m.publisher_participant);
  return proc_label(*it->second.b) + "/" + it->second.e->node;
}

std::string type_of(const Endpoint& e, const types::TypeRegistry* reg) {
  if (e.fingerprint == 0) return "";
  if (reg != nullptr)
    if (const auto* t = reg->find(static_cast<std::uint64_t>(e.fingerprint))) return t->full_name();
  return e.type_name;
}

std::string node_id(const Beacon& b, const std::string& node) {
  return "n_" + std::to_string(b.participant_id) + "_" + node;
}

}  // namespace

std::vector<discovery::Participant> sorted(std::vector<discovery::Participant> ps) {
  std::sort(ps.begin(), ps.end(), [](const auto& a, const auto& b) {
    return std::tie(a.beacon.host_id, a.beacon.process_name, a.beacon.pid, a.beacon.participant_id) <
           std::tie(b.beacon.host_id, b.beacon.process_name, b.beacon.pid, b.beacon.participant_id);
  });
  for (auto& p : ps) {
    auto& eps = p.beacon.endpoints;
    std::sort(eps.begin(), eps.end(), [](const Endpoint& a, const Endpoint& b) {
      return std::tie(a.node, a.kind, a.topic, a.id) < std::tie(b.node, b.kind, b.topic, b.id);
    });
    for (auto& e : eps)
      std::sort(e.matches.begin(), e.matches.end(), [](const auto& x, const auto& y) {
        return std::tie(x.publisher_participant, x.publisher_endpoint, x.path) <
               std::tie(y.publisher_participant, y.publisher_endpoint, y.path);
      });
  }
  return ps;
}

std::string to_dot(const std::vector<discovery::Participant>& in, const types::TypeRegistry* reg) {
  const auto ps = sorted(in);
  const auto idx = index_publishers(ps);
  std::ostringstream o;
  o << "digraph lcmx {\n  rankdir=LR;\n  graph [fontname=\"Helvetica\", fontsize=11];\n  node [fontname=\"Helvetica\", fontsize=10];\n"
       "  edge [fontname=\"Helvetica\", fontsize=9];\n";
  // Hosts and processes.
  std::map<std::int64_t, std::vector<const Beacon*>> hosts;
  for (const auto& p : ps) hosts[p.beacon.host_id].push_back(&p.beacon);
  std::set<std::string> topics;
  bool stock = false;
  for (const auto& [host, beacons] : hosts) {
    o << "  subgraph " << q("cluster_host_" + host_hex(host)) << " {\n    label=" << q("host " + host_hex(host))
      << ";\n    style=rounded;\n";
    for (const auto* b : beacons) {
      o << "    subgraph " << q("cluster_p_" + std::to_string(b->participant_id)) << " {\n      label="
        << q(proc_label(*b) + ((b->flags & Beacon::FLAG_BRIDGE) ? " (bridge)" : "")) << ";\n      style=filled;\n"
        << "      fillcolor=\"#eeeeee\";\n";
      for (const auto& n : b->nodes) o << "      " << q(node_id(*b, n)) << " [shape=box, label=" << q(n) << "];\n";
      o << "    }\n";
      for (const auto& e : b->endpoints) {
        topics.insert(e.topic);
        for (const auto& m : e.matches) stock |= m.publisher_participant == 0;
      }
    }
    o << "  }\n";
  }
  // Topics.
  for (const auto& t : topics) {
    std::set<std::string> types;
    for (const auto& p : ps)
      for (const auto& e : p.beacon.endpoints)
        if (e.topic == t && e.fingerprint != 0) types.insert(type_of(e, reg));
    std::string label = t;
    for (const auto& ty : types) label += "\n" + ty;
    const bool conflict = types.size() > 1;
    if (conflict) label += "\nCONFLICT: different types";
    o << "  " << q("t_" + t) << " [shape=ellipse, style=filled, fillcolor="
      << (conflict ? "\"#ffd0d0\"" : "\"#dde8ff\"") << ", label=" << q(label) << "];\n";
  }
  if (stock) o << "  \"stock_lcm\" [shape=box, style=dashed, label=\"LCM sender(s)\"];\n";
  // Edges: publisher node -> topic, topic -> subscriber node (one per pair, labelled by path).
  for (const auto& p : ps) {
    const auto& b = p.beacon;
    std::set<std::pair<std::string, std::string>> pub_edges;
    for (const auto& e : b.endpoints) {
      if (e.kind == Endpoint::KIND_PUBLISHER) {
        if (pub_edges.insert({e.node, e.topic}).second)
          o << "  " << q(node_id(b, e.node)) << " -> " << q("t_" + e.topic) << ";\n";
        continue;
      }
      if (e.matches.empty()) {
        std::string why = "no publisher";
        if (!e.errors.empty()) why = "not matched: " + e.errors.front().substr(0, 60);
        o << "  " << q("t_" + e.topic) << " -> " << q(node_id(b, e.node)) << " [style=dotted, label=" << q(why) << "];\n";
        continue;
      }
      std::set<std::string> stock_paths;
      for (const auto& m : e.matches) {
        if (m.publisher_participant == 0) {
          stock_paths.insert(m.path);
          continue;
        }
        o << "  " << q("t_" + e.topic) << " -> " << q(node_id(b, e.node)) << " [label="
          << q(m.path + " from " + publisher_name(idx, m)) << "];\n";
      }
      for (const auto& path : stock_paths) {
        o << "  \"stock_lcm\" -> " << q("t_" + e.topic) << " [style=dashed];\n";
        o << "  " << q("t_" + e.topic) << " -> " << q(node_id(b, e.node)) << " [label="
          << q(path + " from LCM sender") << "];\n";
      }
    }
  }
  o << "}\n";
  return o.str();
}

std::string to_json(const std::vector<discovery::Participant>& in, const types::TypeRegistry* reg) {
  const auto ps = sorted(in);
  const auto idx = index_publishers(ps);
  std::ostringstream o;
  o << "{\"hosts\":[";
  std::map<std::int64_t, std::vector<const Beacon*>> hosts;
  for (const auto& p : ps) hosts[p.beacon.host_id].push_back(&p.beacon);
  bool first_host = true;
  for (const auto& [host, beacons] : hosts) {
    o << (first_host ? "" : ",") << "{\"host\":" << json_str(host_hex(host)) << ",\"processes\":[";
    first_host = false;
    for (std::size_t i = 0; i < beacons.size(); ++i) {
      const auto& b = *beacons[i];
      o << (i ? "," : "") << "{\"process\":" << json_str(b.process_name) << ",\"pid\":" << b.pid
        << ",\"participant\":" << b.participant_id
        << ",\"bridge\":" << ((b.flags & Beacon::FLAG_BRIDGE) ? "true" : "false") << ",\"nodes\":[";
      for (std::size_t k = 0; k < b.nodes.size(); ++k) {
        const auto& n = b.nodes[k];
        o << (k ? "," : "") << "{\"node\":" << json_str(n) << ",\"publishes\":[";
        bool f = true;
        for (const auto& e : b.endpoints) {
          if (e.node != n || e.kind != Endpoint::KIND_PUBLISHER) continue;
          o << (f ? "" : ",") << "{\"topic\":" << json_str(e.topic) << ",\"type\":" << json_str(type_of(e, reg)) << "}";
          f = false;
        }
        o << "],\"subscribes\":[";
        f = true;
        for (const auto& e : b.endpoints) {
          if (e.node != n || e.kind != Endpoint::KIND_SUBSCRIBER) continue;
          o << (f ? "" : ",") << "{\"topic\":" << json_str(e.topic) << ",\"type\":" << json_str(type_of(e, reg))
            << ",\"pairs\":[";
          f = false;
          for (std::size_t m = 0; m < e.matches.size(); ++m)
            o << (m ? "," : "") << "{\"publisher\":" << json_str(publisher_name(idx, e.matches[m]))
              << ",\"path\":" << json_str(e.matches[m].path) << "}";
          o << "]}";
        }
        o << "]}";
      }
      o << "]}";
    }
    o << "]}";
  }
  o << "],\"topics\":[";
  std::map<std::string, std::tuple<std::set<std::string>, int, int>> topics;
  for (const auto& p : ps)
    for (const auto& e : p.beacon.endpoints) {
      auto& [types, pubs, subs] = topics[e.topic];
      if (e.fingerprint != 0) types.insert(type_of(e, reg));
      (e.kind == Endpoint::KIND_PUBLISHER ? pubs : subs)++;
    }
  bool f = true;
  for (const auto& [t, v] : topics) {
    const auto& [types, pubs, subs] = v;
    o << (f ? "" : ",") << "{\"topic\":" << json_str(t) << ",\"types\":[";
    f = false;
    bool ft = true;
    for (const auto& ty : types) {
      o << (ft ? "" : ",") << json_str(ty);
      ft = false;
    }
    o << "],\"publishers\":" << pubs << ",\"subscribers\":" << subs << "}";
  }
  o << "]}";
  return o.str();
}

}  // namespace lcmx::cli::graph
