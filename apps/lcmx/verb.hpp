// How `lcmx <verb>` commands are registered (apps/lcmx/main.cpp): each verb file
// (bridge_cmd.cpp, ...) has an `add_<verb>(app, globals)` that adds its CLI11 subcommand, binds
// the subcommand's options to state its run function owns, and returns both. main() adds every
// verb, parses, and runs the one given. Adding a verb = one file + one line in main().
#pragma once

#include <CLI/CLI.hpp>

#include <functional>
#include <string>

namespace lcmx::cli {

// Options of `lcmx` itself, which may come before or after the verb. Filled in by the parse,
// so read them in run(), not in add_<verb>().
struct Globals {
  std::string url;          // --url: host-local discovery group
  std::string vehicle_url;  // --vehicle-url
  int wait_ms = 400;        // --wait: how long observers listen for beacons
};

struct Verb {
  CLI::App* command = nullptr;  // owned by the app
  std::function<int()> run;     // called when `command` was parsed; returns the exit code
};

// `lcmx bridge [--config FILE [--check] | status | keygen]` (bridge_cmd.cpp).
Verb add_bridge(CLI::App& app, const Globals& globals);

}  // namespace lcmx::cli
