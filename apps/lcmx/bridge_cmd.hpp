// `lcmx bridge ...`: the Message Bridge daemon and its tools (docs/bridge.md).
#pragma once

#include <ostream>
#include <string>

#include "lcmx_msgs/bridge_status_t.hpp"

namespace lcmx::cli {

// Runs the daemon until SIGINT/SIGTERM (exit 0, goodbye sent). With check_only, validates the
// config and returns. Exit codes: 0 ok, 1 runtime failure (e.g. cannot bind), 2 bad config.
// json: the --check verdict as JSON ({"config","ok","name","channels","peers","curve"} or
// {"config","ok":false,"error"}).
int bridge_run(const std::string& config_path, bool check_only, bool json = false);
// Prints the status of every bridge on this host (discovery group `url`), waiting up to wait_ms.
// 0 if some bridge answered, 1 otherwise.
// json: one line {"bridges":[...]} (bridge_status_t's fields, host as hex).
int bridge_status(const std::string& url, int wait_ms, bool json = false);
// Writes PREFIX.key / PREFIX.pub. 0 ok, 1 on failure.
int bridge_keygen(const std::string& prefix, bool force, bool json = false);

void print_bridge_status(std::ostream& out, const lcmx_msgs::bridge_status_t& s);
// One bridge's status as a JSON object (no newline).
std::string bridge_status_json(const lcmx_msgs::bridge_status_t& s);

}  // namespace lcmx::cli
