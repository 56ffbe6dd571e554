// `lcmx dds-gateway` (run, --check, status) and `lcmx idl` (docs/dds.md).
#include <signal.h>
#include <spdlog/cfg/env.h>
#include <spdlog/spdlog.h>

#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <mutex>
#include <sstream>
#include <utility>

#include "dds_cmds.hpp"
#include "lcmx/core.hpp"
#include "lcmx/dds/gateway.hpp"
#include "lcmx/dds/idl.hpp"
#include "log_common.hpp"
#include "status_collect.hpp"

namespace lcmx::cli {
namespace {

std::string pad(std::string s, std::size_t w) {
  if (s.size() < w) s.append(w - s.size(), ' ');
  return s;
}

// Names in a status message (the host-local group: any process can send one) are escaped.
void print_status(std::ostream& out, const lcmx_msgs::dds_gateway_status_t& s) {
  char host[32];
  std::snprintf(host, sizeof host, "%016llx", static_cast<unsigned long long>(s.host_id));
  out << "dds-gateway " << printable(s.name) << "  pid " << s.pid << "  host " << host << "  domain " << s.domain
      << "  partition " << (s.partition.empty() ? "-" : printable(s.partition)) << "\n";
  out << "  " << pad("channel", 18) << pad("topic", 20) << pad("mode", 7) << pad("dir", 9) << pad("state", 18)
      << pad("out msgs", 10) << pad("out bytes", 12) << pad("out drop", 9) << pad("in msgs", 9) << pad("in bytes", 12)
      << pad("in drop", 8) << "loops\n";
  for (const auto& m : s.mappings) {
    std::string state;
    if (m.direction != "from_dds") state += m.exporting ? "out:" + std::to_string(m.dds_readers) + "rd " : "out:idle ";
    if (m.direction != "to_dds")
      state += m.importing ? "in:" + std::to_string(m.lcmx_subscribers) + "sub/" + std::to_string(m.dds_writers) + "wr"
                           : "in:idle";
    out << "  " << pad(printable(m.channel), 18) << pad(printable(m.topic), 20) << pad(printable(m.mode), 7)
        << pad(printable(m.direction), 9) << pad(state, 18)
        << pad(std::to_string(m.exported), 10) << pad(std::to_string(m.exported_bytes), 12)
        << pad(std::to_string(m.export_drops), 9) << pad(std::to_string(m.imported), 9)
        << pad(std::to_string(m.imported_bytes), 12) << pad(std::to_string(m.import_drops), 8) << m.suppressed << "\n";
    out << "      DDS type " << printable(m.dds_type) << "\n";
    for (const auto& e : m.errors) out << "      ERROR: " << printable(e) << "\n";
  }
}

std::string status_json(const lcmx_msgs::dds_gateway_status_t& s) {
  char host[32];
  std::snprintf(host, sizeof host, "%016llx", static_cast<unsigned long long>(s.host_id));
  std::ostringstream j;
  j << "{\"name\":" << json_str(s.name) << ",\"pid\":" << s.pid << ",\"host\":\"" << host << "\",\"domain\":" << s.domain
    << ",\"partition\":" << json_str(s.partition) << ",\"mappings\":[";
  for (std::size_t i = 0; i < s.mappings.size(); ++i) {
    const auto& m = s.mappings[i];
    j << (i ? "," : "") << "{\"channel\":" << json_str(m.channel) << ",\"topic\":" << json_str(m.topic)
      << ",\"dds_type\":" << json_str(m.dds_type) << ",\"mode\":" << json_str(m.mode)
      << ",\"direction\":" << json_str(m.direction) << ",\"exporting\":" << (m.exporting ? "true" : "false")
      << ",\"importing\":" << (m.importing ? "true" : "false") << ",\"dds_readers\":" << m.dds_readers
      << ",\"lcmx_subscribers\":" << m.lcmx_subscribers << ",\"dds_writers\":" << m.dds_writers
      << ",\"exported\":" << m.exported
      << ",\"exported_bytes\":" << m.exported_bytes << ",\"export_drops\":" << m.export_drops
      << ",\"imported\":" << m.imported << ",\"imported_bytes\":" << m.imported_bytes
      << ",\"import_drops\":" << m.import_drops << ",\"suppressed\":" << m.suppressed << ",\"errors\":[";
    for (std::size_t k = 0; k < m.errors.size(); ++k) j << (k ? "," : "") << json_str(m.errors[k]);
    j << "]}";
  }
  j << "]}";
  return j.str();
}

int gateway_run(const std::string& path, bool check_only, bool json) {
  dds::Config cfg;
  try {
    cfg = dds::load_config(path);
  } catch (const dds::ConfigError& e) {
    if (check_only && json)
      std::cout << "{\"config\":" << json_str(path) << ",\"ok\":false,\"error\":" << json_str(e.what()) << "}"
                << std::endl;
    std::cerr << "lcmx dds-gateway: bad config: " << e.what() << "\n";
    return 2;
  }
  if (check_only) {
    if (json)
      std::cout << "{\"config\":" << json_str(path) << ",\"ok\":true,\"name\":" << json_str(cfg.name)
                << ",\"domain\":" << cfg.domain << ",\"mappings\":" << cfg.mappings.size() << "}" << std::endl;
    else
      std::cout << path << ": ok: dds-gateway " << cfg.name << ", domain " << cfg.domain << ", "
                << cfg.mappings.size() << " mapping(s)\n";
    return 0;
  }
  spdlog::set_level(spdlog::level::info);
  spdlog::cfg::load_env_levels();
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGINT);
  sigaddset(&set, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &set, nullptr);
  try {
    const std::string name = cfg.name;
    auto gw = dds::Gateway::start(std::move(cfg), RuntimeOptions::from_env());
    std::cout << "dds-gateway " << name << ": ready" << std::endl;
    int sig = 0;
    sigwait(&set, &sig);
    spdlog::info("dds-gateway: signal {}: stopping", sig);
    gw.stop();
  } catch (const dds::ConfigError& e) {
    std::cerr << "lcmx dds-gateway: bad config: " << e.what() << "\n";
    return 2;
  } catch (const std::exception& e) {
    std::cerr << "lcmx dds-gateway: " << e.what() << "\n";
    return 1;
  }
  return 0;
}

int gateway_status(const std::string& url, int wait_ms, bool json) {
  return show_statuses<lcmx_msgs::dds_gateway_status_t>("dds-gateway", "gateways", url, dds::kStatusChannel, wait_ms,
                                                        json, print_status, status_json);
}

}  // namespace

Verb add_dds_gateway(CLI::App& app, const Globals& g) {
  struct State {
    std::string config, status_url;
    bool check = false, json = false;
    int status_wait = 3000;
  };
  auto st = std::make_shared<State>();
  auto* cmd = app.add_subcommand(
      "dds-gateway", "run a Cyclone DDS gateway (--config FILE), or show the gateways' counters (status)");
  cmd->fallthrough();
  cmd->add_option("--config", st->config, "gateway config file (TOML, see docs/dds.md)");
  cmd->add_flag("--check", st->check, "validate the config file and exit (0 ok, 2 bad)");
  cmd->add_flag("--json", st->json, "--check, status: print the result as JSON");
  auto* status = add_status_subcommand(
      *cmd, "per gateway on this host and per mapping: state, messages/bytes/drops each way, loops refused, errors",
      "gateways", st->status_url, st->status_wait);
  return {cmd, [st, status, &g] {
            if (status->parsed())
              return gateway_status(st->status_url.empty() ? g.url : st->status_url, st->status_wait, st->json);
            if (st->config.empty()) {
              std::cerr << "lcmx dds-gateway: --config FILE is required (or: lcmx dds-gateway status)\n";
              return 2;
            }
            return gateway_run(st->config, st->check, st->json);
          }};
}

Verb add_idl(CLI::App& app, const Globals&) {
  struct State {
    std::vector<std::string> paths, type_names;
    std::string out;
    bool ros2 = false;
  };
  auto st = std::make_shared<State>();
  auto* cmd = app.add_subcommand("idl", "write OMG IDL for .lcm types (for idlc and DDS programs; docs/dds.md)");
  cmd->add_option("paths", st->paths, ".lcm files or directories (searched recursively)")->required();
  cmd->add_option("--type", st->type_names, "only this type, package-qualified (repeatable; default: every type)")
      ->allow_extra_args(false);
  cmd->add_flag("--ros2", st->ros2, "ROS 2 naming: modules pkg::msg::dds_, types T_ (as rmw_cyclonedds)");
  cmd->add_option("-o,--output", st->out, "write to this file (default: standard output)");
  return {cmd, [st] {
            try {
              std::vector<std::filesystem::path> paths(st->paths.begin(), st->paths.end());
              const auto reg = types::TypeRegistry::load(paths);
              std::vector<const types::StructType*> roots;
              if (st->type_names.empty())
                for (const auto& t : reg.types()) roots.push_back(t.get());
              for (const auto& n : st->type_names) roots.push_back(&reg.at(n));
              if (roots.empty()) {
                std::cerr << "lcmx idl: no types in the given paths\n";
                return 2;
              }
              const std::string idl = dds::to_idl(roots, st->ros2);
              if (st->out.empty()) {
                std::cout << idl;
              } else {
                std::ofstream f(st->out, std::ios::binary | std::ios::trunc);
                f << idl;
                if (!f.flush()) {
                  std::cerr << "lcmx idl: cannot write " << st->out << "\n";
                  return 1;
                }
              }
            } catch (const std::exception& e) {
              std::cerr << "lcmx idl: " << e.what() << "\n";
              return 2;
            }
            return 0;
          }};
}

}  // namespace lcmx::cli
