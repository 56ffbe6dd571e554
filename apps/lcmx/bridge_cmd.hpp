// `lcmx bridge ...`: the Message Bridge daemon and its tools (docs/bridge.md).
#pragma once

#include <ostream>
#include <string>

#include "lcmx_msgs/bridge_status_t.hpp"

namespace lcmx::cli {

// Runs the daemon until SIGINT/SIGTERM (exit 0, goodbye sent). With check_only, validates the
// config and returns. Exit codes: 0 ok, 1 runtime failure (e.g. cannot bind), 2 bad config.
int bridge_run(const std::string& config_path, bool check_only);
// Prints the status of every bridge on this host (discovery group `url`), waiting up to wait_ms.
// 0 if some bridge answered, 1 otherwise.
int bridge_status(const std::string& url, int wait_ms);
// Writes PREFIX.key / PREFIX.pub. 0 ok, 1 on failure.
int bridge_keygen(const std::string& prefix, bool force);

void print_bridge_status(std::ostream& out, const lcmx_msgs::bridge_status_t& s);

}  // namespace lcmx::cli
