// `lcmx record`, `lcmx play FILE`, `lcmx log info FILE`: LCM event logs (lcmx::eventlog).
// main.cpp registers them with add_log_verbs() and runs the parsed one with run_log_verbs().
#pragma once

#include <CLI/CLI.hpp>

#include <optional>
#include <string>

namespace lcmx::cli {

// The tool's global options, read when the verb runs (they may follow the verb).
struct Globals {
  const std::string* url = nullptr;          // host-local group
  const std::string* vehicle_url = nullptr;  // vehicle group, may be empty
};

CLI::App* add_record(CLI::App& app, Globals g);
int run_record();
CLI::App* add_play(CLI::App& app, Globals g);
int run_play();
CLI::App* add_log(CLI::App& app);
int run_log();

struct LogVerbs {
  CLI::App* record = nullptr;
  CLI::App* play = nullptr;
  CLI::App* log = nullptr;
};

inline LogVerbs add_log_verbs(CLI::App& app, const std::string& url, const std::string& vehicle_url) {
  const Globals g{&url, &vehicle_url};
  return {add_record(app, g), add_play(app, g), add_log(app)};
}

// The exit code of the verb that was parsed, or nullopt if none of these was.
inline std::optional<int> run_log_verbs(const LogVerbs& v) {
  if (v.record->parsed()) return run_record();
  if (v.play->parsed()) return run_play();
  if (v.log->parsed()) return run_log();
  return std::nullopt;
}

}  // namespace lcmx::cli
