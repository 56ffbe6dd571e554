// `lcmx services`: the services discovery sees (servers announce "<name>/rq" subscribers of
// lcmx_msgs.service_request_t in their beacons), each with its servers and clients; the
// request/response types come from probing every service once (a raw client; --no-probe skips).
// `lcmx call NAME [JSON]`: one call, the request written as JSON and encoded with the `.lcm`
// files of the type path (the server's probe answer names its types by fingerprint); the
// response printed decoded (or --json). Raw services take --hex and answer in hex.
// Threads: the main thread does everything; replies arrive on the client's own thread.
#include <spdlog/spdlog.h>

#include <cstdio>
#include <iostream>
#include <map>
#include <set>

#include "lcmx/core.hpp"
#include "lcmx/types/value.hpp"
#include "lcmx_msgs/service_request_t.hpp"
#include "log_common.hpp"
#include "service_cmds.hpp"
#include "tap.hpp"
#include "topology.hpp"

namespace lcmx::cli {
namespace {

using Clock = std::chrono::steady_clock;

// ---- lcmx services ----

struct ServicesOptions {
  std::vector<std::string> types;
  bool json = false;
  bool no_probe = false;
  const Globals* g = nullptr;
};
ServicesOptions g_services;

struct SeenService : SeenServersClients {
  std::optional<ServerInfo> probed;  // the best server's answer
};

int run_services() {
  const auto& o = g_services;
  spdlog::set_level(spdlog::level::warn);
  types::TypeRegistry reg;
  try {
    reg = load_types(o.types);
  } catch (const std::exception& e) {
    std::cerr << "lcmx services: " << e.what() << "\n";
    return 1;
  }
  std::map<std::string, SeenService> services;
  try {
    const std::string suffix = "/rq";
    for (const auto& p : observe(*o.g)) {
      for (const auto& e : p.beacon.endpoints) {
        if (e.fingerprint != lcmx_msgs::service_request_t::getHash() || e.topic.size() <= suffix.size() ||
            e.topic.compare(e.topic.size() - suffix.size(), suffix.size(), suffix) != 0)
          continue;
        auto& s = services[e.topic.substr(0, e.topic.size() - suffix.size())];
        const SeenEndpoint se = seen_endpoint(p, e);
        (e.kind == lcmx_msgs::endpoint_t::KIND_SUBSCRIBER ? s.servers : s.clients).push_back(se);
      }
    }
    if (!o.no_probe && !services.empty()) {
      auto rt = Runtime::create(runtime_options(*o.g));
      auto node = rt.create_node("lcmx_services");
      std::map<std::string, RawClient> clients;
      for (const auto& [name, s] : services)
        if (!s.servers.empty()) clients.emplace(name, node.create_client_raw(name));
      const auto deadline = Clock::now() + std::chrono::milliseconds(std::max(o.g->wait_ms, 1000));
      for (auto& [name, c] : clients) {
        const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
        if (c.wait_for_service(std::max(left, std::chrono::milliseconds(0))) && !c.servers().empty())
          services[name].probed = c.servers().front();
      }
    }
  } catch (const std::exception& e) {
    std::cerr << "lcmx services: " << e.what() << "\n";
    return 1;
  }

  if (o.json) {
    std::cout << "{\"services\":[";
    bool first = true;
    for (const auto& [name, s] : services) {
      std::cout << (first ? "" : ",") << "{\"name\":" << json_str(name);
      first = false;
      if (s.probed) {
        const auto& i = *s.probed;
        std::cout << ",\"request_type\":" << json_str(type_name(reg, i.request_type, i.request_fingerprint))
                  << ",\"response_type\":" << json_str(type_name(reg, i.response_type, i.response_fingerprint))
                  << ",\"request_fingerprint\":\""
                  << hex_fingerprint(static_cast<std::uint64_t>(i.request_fingerprint)) << "\""
                  << ",\"response_fingerprint\":\""
                  << hex_fingerprint(static_cast<std::uint64_t>(i.response_fingerprint)) << "\"";
      }
      print_endpoints_json(std::cout, s);
      std::cout << "}";
    }
    std::cout << "]}" << std::endl;
    return 0;
  }
  if (services.empty()) {
    std::cout << "no services seen (listened " << o.g->wait_ms << " ms on " << o.g->url << ")\n";
    return 0;
  }
  for (const auto& [name, s] : services) {
    std::cout << printable(name);  // names and types from the network: escaped (safe_text.hpp)
    if (s.probed)
      std::cout << "  " << printable(type_name(reg, s.probed->request_type, s.probed->request_fingerprint)) << " -> "
                << printable(type_name(reg, s.probed->response_type, s.probed->response_fingerprint));
    else if (!o.no_probe)
      std::cout << "  (types unknown: no server answered a probe)";
    std::cout << "\n";
    print_endpoints_text(std::cout, s);
  }
  return 0;
}

// ---- lcmx call ----

struct CallOptions {
  std::string name;
  std::optional<std::string> json;
  std::optional<std::string> hex;
  std::vector<std::string> types;
  double timeout_s = 5;
  bool json_out = false;
  const Globals* g = nullptr;
};
CallOptions g_call;

int run_call() {
  const auto& o = g_call;
  spdlog::set_level(spdlog::level::warn);
  types::TypeRegistry reg;
  try {
    reg = load_types(o.types);
  } catch (const std::exception& e) {
    std::cerr << "lcmx call: " << e.what() << "\n";
    return 1;
  }
  const auto timeout = std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::duration<double>(o.timeout_s));
  const auto deadline = Clock::now() + timeout;
  try {
    auto rt = Runtime::create(runtime_options(*o.g));
    auto node = rt.create_node("lcmx_call");
    auto client = node.create_client_raw(o.name);
    if (!client.wait_for_service(timeout) || client.servers().empty()) {
      std::cerr << "lcmx call: no server of '" << o.name << "' answered within " << o.timeout_s
                << " s ('lcmx services' lists the services seen)\n";
      return 1;
    }
    const ServerInfo server = client.servers().front();
    Bytes request;
    if (server.request_fingerprint == 0 || o.hex) {
      if (!o.hex) {
        std::cerr << "lcmx call: service '" << o.name << "' takes raw bytes: give them with --hex\n";
        return 2;
      }
      auto b = from_hex(*o.hex);
      if (!b) {
        std::cerr << "lcmx call: --hex: not an even number of hex digits\n";
        return 2;
      }
      request = std::move(*b);
    } else {
      const auto* type = reg.find(static_cast<std::uint64_t>(server.request_fingerprint));
      if (type == nullptr) {
        std::cerr << "lcmx call: the server takes " << printable(server.request_type) << " ("
                  << hex_fingerprint(static_cast<std::uint64_t>(server.request_fingerprint))
                  << "), which is not in the type path"
                  << (reg.size() == 0 ? " (give --types DIR|FILE or set LCMX_TYPES_PATH)" : "") << "\n";
        return 1;
      }
      const auto bytes = types::encode(*type, types::from_json(*type, o.json.value_or("{}")));
      request.resize(bytes.size());
      std::memcpy(request.data(), bytes.data(), bytes.size());
    }
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    auto r = client.call(request, std::max(left, std::chrono::milliseconds(1)));
    if (!r.ok()) {
      std::cerr << "lcmx call: " << to_string(r.error()) << ": " << printable(r.message()) << "\n";
      return 1;
    }
    const auto& resp = r.value();
    if (server.response_fingerprint == 0) {
      std::cout << (o.json_out ? "{\"hex\":\"" + to_hex(resp) + "\"}" : to_hex(resp)) << std::endl;
      return 0;
    }
    const auto* rtype = reg.find(static_cast<std::uint64_t>(server.response_fingerprint));
    if (rtype == nullptr) {
      std::cerr << "lcmx call: the response (" << resp.size() << " bytes) is a " << printable(server.response_type)
                << " (" << hex_fingerprint(static_cast<std::uint64_t>(server.response_fingerprint))
                << "), not in the type path; printed in hex\n";
      std::cout << to_hex(resp) << std::endl;
      return 0;
    }
    const auto value = types::decode(*rtype, resp.data(), resp.size());
    if (o.json_out) std::cout << types::to_json(value) << std::endl;
    else std::cout << types::to_text(value) << std::flush;
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "lcmx call: " << e.what() << "\n";
    return 1;
  }
}

}  // namespace

Verb add_services(CLI::App& app, const Globals& g) {
  g_services.g = &g;
  auto* c = app.add_subcommand("services", "list the services discovery sees: servers, clients, types");
  c->add_option("-t,--types", g_services.types,
                ".lcm file or directory for package-qualified type names (repeatable); default LCMX_TYPES_PATH")
      ->allow_extra_args(false);
  c->add_flag("--json", g_services.json,
              "one line of JSON: {services: [{name, request_type, response_type, request_fingerprint, "
              "response_fingerprint, servers: [{participant, host, pid, process, node}], clients: [...]}]}");
  c->add_flag("--no-probe", g_services.no_probe,
              "do not probe the services for their types (only listen to discovery)");
  return {c, [] { return run_services(); }};
}

Verb add_call(CLI::App& app, const Globals& g) {
  g_call.g = &g;
  auto* c = app.add_subcommand("call", "call a service once: the request as JSON, the response printed decoded");
  c->add_option("name", g_call.name, "service name")->required();
  auto* json = c->add_option("json", g_call.json,
                "the request as JSON, e.g. '{\"position\": [1, 2, 3]}'; fields not given are zero (default {})");
  c->add_option("-t,--types", g_call.types,
                ".lcm file or directory (searched recursively; repeatable, or a ':' list); default LCMX_TYPES_PATH")
      ->allow_extra_args(false);
  c->add_option("--hex", g_call.hex, "the request as hex bytes (raw services, or to send exact bytes); not with JSON")
      ->excludes(json);
  c->add_option("--timeout", g_call.timeout_s, "seconds to find a server and get the answer")
      ->check(positive_number())
      ->capture_default_str();
  c->add_flag("--json", g_call.json_out, "print the response as one line of JSON");
  c->footer(
      "The server's probe answer names its request and response types by fingerprint; the type path must hold "
      "them. Exit: 0 answered, 1 no server / call error (timeout, server gone, handler failed, type mismatch) / "
      "bad type path or JSON, 2 bad arguments.");
  return {c, [] { return run_call(); }};
}

}  // namespace lcmx::cli
