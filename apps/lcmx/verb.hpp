// How `lcmx <verb>` commands are registered (apps/lcmx/main.cpp): each verb file
// (bridge_cmd.cpp, ...) has an `add_<verb>(app, globals)` that adds its CLI11 subcommand, binds
// the subcommand's options to state its run function owns, and returns both. main() adds every
// verb, parses, and runs the one given. Adding a verb = one file + one line in main().
#pragma once

#include <CLI/CLI.hpp>

#include <functional>
#include <string>

#include "lcmx/core/options.hpp"

namespace lcmx::cli {

// Options of `lcmx` itself, which may come before or after the verb. Filled in by the parse,
// so read them in run(), not in add_<verb>().
struct Globals {
  std::string url;          // --url: host-local discovery group
  std::string vehicle_url;  // --vehicle-url
  int wait_ms = 400;        // --wait: how long observers listen for beacons
  std::string vehicle_key;  // --vehicle-key: the vehicle group's key file (LCMX_VEHICLE_KEY)
  std::string host_key;     // --host-key: the host-local group's key file (LCMX_HOST_KEY)
};

// The runtime options of a verb that joins lcmx as a participant: the environment's (LCMX_*,
// RuntimeOptions::from_env, which throws on bad values) with `lcmx --url / --vehicle-url`.
// `reach_stock`: also publish on LCM's UDP groups for stock programs (the host-local mirror;
// the vehicle group always), as `pub --udp` and `play --udp` do.
inline RuntimeOptions runtime_options(const Globals& g, bool reach_stock = false) {
  auto ro = RuntimeOptions::from_env();
  ro.discovery_url = g.url;
  if (!g.vehicle_url.empty()) ro.vehicle_url = g.vehicle_url;
  ro.vehicle_key = g.vehicle_key;
  ro.host_key = g.host_key;
  if (reach_stock) {
    ro.mirror = true;
    ro.vehicle_publish = VehiclePublish::always;
  }
  return ro;
}

// The configuration an observer (lcmx nodes, topics, monitor, graph, ...) opens a group with:
// its URL (`lcmx --url` / `--vehicle-url`) and key file (`--host-key` / `--vehicle-key`, or
// LCMX_HOST_KEY / LCMX_VEHICLE_KEY), as a participant's runtime opens it.
// Throws lcmx::Error(invalid_argument) naming a bad URL or key file and its variable.
inline udpm::GroupConfig observer_group(const Globals& g, bool vehicle) {
  auto ro = runtime_options(g);
  return ro.group_config(vehicle);
}

// CLI11's PositiveNumber / NonNegativeNumber are ranges up to DBL_MAX, whose error spells
// out a 309-digit number: these say "must be greater than 0 (got X)".
inline CLI::Validator number_check(bool zero_ok) {
  return CLI::Validator(
      [zero_ok](std::string& s) -> std::string {
        double v = 0;
        if (!CLI::detail::lexical_cast(s, v)) return "not a number: " + s;
        if (v > 0 || (zero_ok && v == 0)) return {};
        return (zero_ok ? "must be 0 or more (got " : "must be greater than 0 (got ") + s + ")";
      },
      zero_ok ? "NONNEGATIVE" : "POSITIVE");
}
inline CLI::Validator positive_number() { return number_check(false); }
inline CLI::Validator non_negative_number() { return number_check(true); }

struct Verb {
  CLI::App* command = nullptr;  // owned by the app
  std::function<int()> run;     // called when `command` was parsed; returns the exit code
};

// `lcmx bridge [--config FILE [--check] | status | keygen]` (bridge_cmd.cpp).
Verb add_bridge(CLI::App& app, const Globals& globals);
// `lcmx keygen --group FILE [--next | --promote | --retire]` (keygen_cmd.cpp).
Verb add_keygen(CLI::App& app, const Globals& globals);

}  // namespace lcmx::cli
