// `lcmx services` and `lcmx call` (service_cmd.cpp), `lcmx actions` and `lcmx action send`
// (action_cmd.cpp): services and actions seen by discovery, and calls and goals with JSON typed
// by the `.lcm` files of the type path. Registered in main.cpp like every verb.
#pragma once

#include <cctype>
#include <cstdio>
#include <optional>
#include <span>
#include <string>

#include <ostream>
#include <vector>

#include "lcmx/discovery/discovery.hpp"
#include "log_common.hpp"
#include "tap.hpp"
#include "verb.hpp"

namespace lcmx::cli {

Verb add_services(CLI::App& app, const Globals& globals);
Verb add_call(CLI::App& app, const Globals& globals);
Verb add_actions(CLI::App& app, const Globals& globals);
Verb add_action(CLI::App& app, const Globals& globals);

// The name a tool shows for a service's or action's type: package-qualified from the type path
// when it has the fingerprint, else lcm-gen's name; "raw" for bytes.
inline std::string type_name(const types::TypeRegistry& reg, const std::string& name, std::int64_t fp) {
  if (fp == 0) return "raw";
  if (const auto* t = reg.find(static_cast<std::uint64_t>(fp))) return t->full_name();
  return name.empty() ? hex_fingerprint(static_cast<std::uint64_t>(fp)) : name;
}

inline std::string to_hex(std::span<const std::byte> b) {
  std::string s;
  char two[3];
  for (auto x : b) {
    std::snprintf(two, sizeof two, "%02x", std::to_integer<unsigned>(x));
    s += two;
  }
  return s;
}

// Hex digits to bytes; nullopt for an odd count or a non-hex character.
inline std::optional<Bytes> from_hex(const std::string& h) {
  if (h.size() % 2 != 0) return std::nullopt;
  Bytes out;
  for (std::size_t i = 0; i < h.size(); i += 2) {
    unsigned v = 0;
    if (!std::isxdigit(static_cast<unsigned char>(h[i])) || !std::isxdigit(static_cast<unsigned char>(h[i + 1])) ||
        std::sscanf(h.substr(i, 2).c_str(), "%2x", &v) != 1)
      return std::nullopt;
    out.push_back(static_cast<std::byte>(v));
  }
  return out;
}

// A server or client of a service or action, from its participant's beacon.
struct SeenEndpoint {
  std::int64_t participant = 0, host = 0;
  std::int32_t pid = 0;
  std::string process, node;
};
inline SeenEndpoint seen_endpoint(const discovery::Participant& p, const lcmx_msgs::endpoint_t& e) {
  return {p.beacon.participant_id, p.beacon.host_id, p.beacon.pid, p.beacon.process_name, e.node};
}
struct SeenServersClients {
  std::vector<SeenEndpoint> servers, clients;
};

// `,"servers":[{participant, host, pid, process, node}],"clients":[...]` (--json output).
inline void print_endpoints_json(std::ostream& out, const SeenServersClients& s) {
  for (const auto* list : {&s.servers, &s.clients}) {
    out << (list == &s.servers ? ",\"servers\":[" : ",\"clients\":[");
    bool first = true;
    for (const auto& e : *list) {
      out << (first ? "" : ",") << "{\"participant\":\"" << hex_fingerprint(static_cast<std::uint64_t>(e.participant))
          << "\",\"host\":\"" << hex_fingerprint(static_cast<std::uint64_t>(e.host)) << "\",\"pid\":" << e.pid
          << ",\"process\":" << json_str(e.process) << ",\"node\":" << json_str(e.node) << "}";
      first = false;
    }
    out << "]";
  }
}

// One line per server, then the number of clients (text output).
inline void print_endpoints_text(std::ostream& out, const SeenServersClients& s) {
  for (const auto& e : s.servers)
    out << "  server  pid " << e.pid << " " << printable(e.process) << ", node " << printable(e.node) << " (host "
        << hex_fingerprint(static_cast<std::uint64_t>(e.host)) << ")\n";
  out << "  clients " << s.clients.size() << "\n";
}

}  // namespace lcmx::cli
