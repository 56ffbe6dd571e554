// lcmx: the command-line tool. Verbs: nodes, topics, bridge; each registered in main() with one
// line (verb.hpp).
// It listens to discovery as an observer: it asks every participant to beacon at once and
// never appears as a participant itself.
#include <CLI/CLI.hpp>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <cstdlib>
#include <iostream>
#include <memory>
#include <optional>
#include <set>
#include <sstream>
#include <thread>
#include <tuple>

#include "lcmx/core/options.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "lcmx/types/schema.hpp"
#include "bridge_cmd.hpp"
#ifdef LCMX_WITH_DDS
#include "dds_cmds.hpp"
#endif
#include "echo_cmds.hpp"
#include "foxglove_cmd.hpp"
#include "log_cmds.hpp"
#include "monitor_cmds.hpp"
#include "service_cmds.hpp"
#include "topology.hpp"
#include "verb.hpp"

namespace {


// The verb of the command line: the first argument that is neither an option of `lcmx` nor
// such an option's value; nullopt if there is none.
std::optional<std::string> verb_of(CLI::App& app, int argc, char** argv) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--") return i + 1 < argc ? std::optional<std::string>(argv[i + 1]) : std::nullopt;
    if (a.size() > 1 && a[0] == '-') {
      const CLI::Option* o = a.find('=') == std::string::npos ? app.get_option_no_throw(a) : nullptr;
      if (o != nullptr && o->get_type_size() > 0) ++i;  // skip its value
      continue;
    }
    return a;
  }
  return std::nullopt;
}

// `lcmx nodes` / `lcmx topics`: observe, print (as text or JSON), with package-qualified type
// names from the type path (--types / LCMX_TYPES_PATH) when there is one.
using Printer = void (*)(std::ostream&, const std::vector<lcmx::discovery::Participant>&,
                         const lcmx::types::TypeRegistry*);
// `with_groups` (nodes): also which groups are keyed, and what a keyed group refused while the
// observer listened.
lcmx::cli::Verb add_observer_verb(CLI::App& app, const lcmx::cli::Globals& g, const std::string& name,
                                  const std::string& description, Printer print, Printer print_json,
                                  bool with_groups = false) {
  struct State {
    std::vector<std::string> types;
    bool json = false;
  };
  auto st = std::make_shared<State>();
  auto* cmd = app.add_subcommand(name, description);
  cmd->add_option("--types", st->types,
                  "`.lcm` file or directory for package-qualified type names, found by fingerprint "
                  "(repeatable; default: LCMX_TYPES_PATH)")
      ->allow_extra_args(false);
  cmd->add_flag("--json", st->json, "print as one line of JSON");
  return {cmd, [&g, print, print_json, st, name, with_groups] {
            spdlog::set_level(spdlog::level::warn);
            // The type path is optional here: without it, names are lcm-gen's (no package). An
            // explicit --types that does not load is an error; a bad LCMX_TYPES_PATH a warning.
            std::optional<lcmx::types::TypeRegistry> reg;
            try {
              const auto paths = lcmx::types::TypeRegistry::paths_or_env(st->types);
              if (!paths.empty()) reg = lcmx::types::TypeRegistry::load(paths);
            } catch (const std::exception& e) {
              if (!st->types.empty()) {
                std::cerr << "lcmx " << name << ": --types: " << e.what() << "\n";
                return 2;
              }
              std::cerr << "lcmx " << name << ": warning: LCMX_TYPES_PATH: " << e.what()
                        << " (type names without package)\n";
            }
            try {
              std::vector<lcmx::cli::GroupSeen> groups;
              const auto ps = lcmx::cli::observe(g, &groups);
              if (!with_groups) {
                (st->json ? print_json : print)(std::cout, ps, reg ? &*reg : nullptr);
              } else if (st->json) {
                std::ostringstream j;  // {"participants":[...]} + "groups"
                print_json(j, ps, reg ? &*reg : nullptr);
                std::string s = j.str();
                while (!s.empty() && s.back() == '\n') s.pop_back();
                if (!s.empty()) s.pop_back();  // the closing brace
                std::cout << s << ",\"groups\":" << lcmx::cli::groups_json(groups) << "}" << std::endl;
              } else {
                print(std::cout, ps, reg ? &*reg : nullptr);
                lcmx::cli::print_groups(std::cout, groups);
              }
            } catch (const std::exception& e) {
              std::cerr << "lcmx: " << e.what() << "\n";
              return 1;
            }
            return 0;
          }};
}

// A group URL checked as the runtime will (RuntimeOptions::group_url_problem), so that a bad --url
// or --vehicle-url is a bad argument (exit 2) and not a failure after the verb has started.
CLI::Validator group_url(bool vehicle) {
  return CLI::Validator(
      [vehicle](std::string& s) { return lcmx::RuntimeOptions::group_url_problem(s, vehicle); }, "URL");
}

}  // namespace

int main(int argc, char** argv) {
  // stdout is each verb's output (tables, JSON lines, `ready`); the log (the library's and the
  // verbs') goes to stderr. spdlog's own default logger writes to stdout.
  spdlog::set_default_logger(
      std::make_shared<spdlog::logger>("", std::make_shared<spdlog::sinks::stderr_color_sink_mt>()));
  CLI::App app{"lcmx: inspect and operate an lcmx system (see README.md)"};
  app.require_subcommand(1);
  app.fallthrough();  // global options may also come after the verb
  lcmx::cli::Globals g;
  lcmx::RuntimeOptions env;
  try {
    env = lcmx::RuntimeOptions::from_env();
    g.url = env.discovery_url;
  } catch (const std::exception& e) {
    std::cerr << "lcmx: " << e.what() << "\n";
    return 2;
  }
  g.vehicle_url = env.vehicle_url;
  g.vehicle_key = env.vehicle_key;
  g.host_key = env.host_key;
  for (const auto& [var, value, vehicle] : {std::tuple{"LCMX_DISCOVERY_URL", g.url, false},
                                            std::tuple{"LCMX_VEHICLE_URL", g.vehicle_url, true}})
    if (const auto why = lcmx::RuntimeOptions::group_url_problem(value, vehicle); !why.empty()) {
      std::cerr << "lcmx: " << var << " " << why << "\n";
      return 2;
    }
  // `lcmx keygen` writes key files: a key variable naming one not written yet is no error there.
  bool keygen = false;
  for (int i = 1; i < argc; ++i) keygen = keygen || std::string(argv[i]) == "keygen";
  try {
    // The rest of what every runtime refuses, also for verbs that make none (topics, nodes).
    if (!keygen) env.check();
  } catch (const std::exception& e) {
    std::cerr << "lcmx: " << e.what() << "\n";
    return 2;
  }
  app.add_option("--url", g.url, "discovery group (default: LCMX_DISCOVERY_URL or LCM's default)")
      ->check(group_url(false))
      ->capture_default_str();
  app.add_option("--vehicle-url", g.vehicle_url,
                 "vehicle group, to see other hosts too, with its interface: "
                 "udpm://GROUP:PORT?ttl=1&iface=NAME (default: LCMX_VEHICLE_URL)")
      ->check(group_url(true))
      ->capture_default_str();
  app.add_option("--vehicle-key", g.vehicle_key,
                 "the vehicle group's key file (lcmx keygen --group; default: LCMX_VEHICLE_KEY): keyed groups, "
                 "docs/keyed-groups.md");
  app.add_option("--host-key", g.host_key, "the host-local group's key file (default: LCMX_HOST_KEY)");
  app.add_option("--wait", g.wait_ms, "how long to listen for beacons, in milliseconds")
      ->check(CLI::Range(50, 60000))
      ->capture_default_str();

  // The verbs, one line each (see verb.hpp).
  std::vector<lcmx::cli::Verb> verbs;
  verbs.push_back(add_observer_verb(app, g, "nodes", "list participants (processes) and their nodes",
                                    lcmx::cli::print_nodes, lcmx::cli::print_nodes_json, true));
  verbs.push_back(add_observer_verb(app, g, "topics",
                                    "list topics: type, publishers, subscribers, path per pair, rate, drops",
                                    lcmx::cli::print_topics, lcmx::cli::print_topics_json));
  verbs.push_back(lcmx::cli::add_bridge(app, g));
  verbs.push_back(lcmx::cli::add_keygen(app, g));
  verbs.push_back(lcmx::cli::add_record(app, g));
  verbs.push_back(lcmx::cli::add_play(app, g));
  verbs.push_back(lcmx::cli::add_log(app, g));
  verbs.push_back(lcmx::cli::add_monitor(app, g));
  verbs.push_back(lcmx::cli::add_graph(app, g));
  verbs.push_back(lcmx::cli::add_echo(app, g));
  verbs.push_back(lcmx::cli::add_hz(app, g));
  verbs.push_back(lcmx::cli::add_bw(app, g));
  verbs.push_back(lcmx::cli::add_pub(app, g));
  verbs.push_back(lcmx::cli::add_services(app, g));
  verbs.push_back(lcmx::cli::add_call(app, g));
  verbs.push_back(lcmx::cli::add_actions(app, g));
  verbs.push_back(lcmx::cli::add_action(app, g));
  verbs.push_back(lcmx::cli::add_foxglove(app, g));
#ifdef LCMX_WITH_DDS
  verbs.push_back(lcmx::cli::add_dds_gateway(app, g));
  verbs.push_back(lcmx::cli::add_idl(app, g));
#endif

  // An unknown verb is named (also before --help, which would otherwise print the top-level help).
  if (const auto verb = verb_of(app, argc, argv)) {
    try {
      (void)app.get_subcommand(*verb);
    } catch (const CLI::OptionNotFound&) {
      std::cerr << "lcmx: unknown command '" << *verb << "'\nRun 'lcmx --help' for the list of commands.\n";
      return 2;
    }
  }
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and friends exit 0; every bad argument exits 2, as each verb's --help says
    // (CLI11's own codes, 105-109, mean nothing to a script).
    const int rc = app.exit(e);
    return rc == 0 ? 0 : 2;
  }
  for (auto& v : verbs)
    if (v.command->parsed()) return v.run();
  return 2;  // not reached: require_subcommand(1)
}
