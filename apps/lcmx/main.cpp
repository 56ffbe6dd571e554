// lcmx: the command-line tool. Verbs: nodes, topics, bridge (more verbs come with later issues).
// It listens to discovery as an observer: it asks every participant to beacon at once and
// never appears as a participant itself.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <cstdlib>
#include <iostream>
#include <memory>
#include <set>
#include <thread>

#include "lcmx/core/options.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "bridge_cmd.hpp"
#include "log_cmds.hpp"
#include "topology.hpp"

namespace {

// Listens on the host-local group, and on the vehicle group when given, for `wait_ms`.
// A participant seen in both scopes is listed once, from its host-local beacon (complete).
std::vector<lcmx::discovery::Participant> observe(const std::string& url, const std::string& vehicle_url,
                                                  int wait_ms) {
  std::vector<std::unique_ptr<lcmx::discovery::Discovery>> observers;
  for (const auto& u : {url, vehicle_url}) {
    if (u.empty()) continue;
    lcmx::discovery::Options o;
    o.group = lcmx::udpm::parse_url(u);
    o.observer = true;
    observers.push_back(std::make_unique<lcmx::discovery::Discovery>(o, nullptr, nullptr));
  }
  // Participants answer the query at once; a second query covers a lost datagram.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(wait_ms);
  std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms / 2));  // a listening window
  for (auto& d : observers) d->query();
  std::this_thread::sleep_until(deadline);
  std::vector<lcmx::discovery::Participant> all;
  std::set<std::int64_t> seen;
  for (auto& d : observers) {
    for (auto& p : d->participants())
      if (seen.insert(p.beacon.participant_id).second) all.push_back(std::move(p));
    d->stop();
  }
  return all;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lcmx: inspect and operate an lcmx system (https://... see README.md)"};
  app.require_subcommand(1);
  app.fallthrough();  // global options may also come after the verb
  std::string url = lcmx::RuntimeOptions::from_env().discovery_url;
  int wait_ms = 400;
  app.add_option("--url", url, "discovery group (default: LCMX_DISCOVERY_URL or LCM's default)")
      ->capture_default_str();
  std::string vehicle_url;
  if (const char* v = std::getenv("LCMX_VEHICLE_URL")) vehicle_url = v;
  app.add_option("--vehicle-url", vehicle_url,
                 "vehicle group, to see other hosts too (default: LCMX_VEHICLE_URL)")
      ->capture_default_str();
  app.add_option("--wait", wait_ms, "how long to listen for beacons, in milliseconds")
      ->check(CLI::Range(50, 60000))
      ->capture_default_str();

  auto* nodes = app.add_subcommand("nodes", "list participants (processes) and their nodes");
  auto* topics = app.add_subcommand(
      "topics", "list topics: type, publishers, subscribers, path per pair, rate, drops");

  auto* bridge = app.add_subcommand(
      "bridge", "run this host's Message Bridge (--config FILE), or inspect bridges (status, keygen)");
  bridge->fallthrough();
  std::string bridge_config;
  bool bridge_check = false;
  bridge->add_option("--config", bridge_config, "bridge config file (TOML, see docs/bridge.md)");
  bridge->add_flag("--check", bridge_check, "validate the config file and exit (0 ok, 2 bad)");
  auto* bstatus = bridge->add_subcommand(
      "status", "per bridge on this host: peers, active link, bytes per link, messages/bytes/drops per channel");
  std::string status_url = url;
  int status_wait = 3000;
  bstatus->add_option("--url", status_url, "host-local discovery group (default: LCMX_DISCOVERY_URL)")
      ->capture_default_str();
  bstatus->add_option("--wait", status_wait, "wait up to this long for bridges' status, in milliseconds")
      ->check(CLI::Range(50, 60000))
      ->capture_default_str();
  auto* keygen = bridge->add_subcommand("keygen", "write a CURVE key pair: PREFIX.key (secret, 0600), PREFIX.pub");
  std::string key_prefix;
  bool key_force = false;
  keygen->add_option("--out", key_prefix, "file name prefix")->required();
  keygen->add_flag("--force", key_force, "overwrite existing files");

  const auto log_verbs = lcmx::cli::add_log_verbs(app, url, vehicle_url);  // record, play, log

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  }
  if (auto rc = lcmx::cli::run_log_verbs(log_verbs)) return *rc;
  if (bridge->parsed()) {
    if (bstatus->parsed()) return lcmx::cli::bridge_status(status_url, status_wait);
    if (keygen->parsed()) return lcmx::cli::bridge_keygen(key_prefix, key_force);
    if (bridge_config.empty()) {
      std::cerr << "lcmx bridge: --config FILE is required (or: lcmx bridge status | keygen)\n";
      return 2;
    }
    return lcmx::cli::bridge_run(bridge_config, bridge_check);
  }
  spdlog::set_level(spdlog::level::warn);
  try {
    const auto ps = observe(url, vehicle_url, wait_ms);
    if (nodes->parsed()) lcmx::cli::print_nodes(std::cout, ps);
    if (topics->parsed()) lcmx::cli::print_topics(std::cout, ps);
  } catch (const std::exception& e) {
    std::cerr << "lcmx: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
