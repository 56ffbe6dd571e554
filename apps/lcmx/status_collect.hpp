// `lcmx bridge status` and `lcmx dds-gateway status`: collects the status messages that this
// host's daemons publish on a channel, one per process (keyed by pid, the latest kept).
// A daemon publishes at once when it sees a new status subscriber, so this waits for the first
// status (up to `wait_ms`), then 300 ms more (bounded by `wait_ms`) for other daemons of the
// host. Host-local group only (`url`; the vehicle group is never joined): this host's daemons.
// Errors: throws what Runtime::create / subscribe throw. Thread: the caller's, blocking.
#pragma once

#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <exception>
#include <iostream>
#include <map>
#include <mutex>
#include <string>
#include <utility>

#include "lcmx/core.hpp"

namespace lcmx::cli {

template <class Status>
std::map<std::int32_t, Status> collect_statuses(const std::string& url, const std::string& channel,
                                                const std::string& node_name, int wait_ms) {
  std::mutex mu;
  std::condition_variable cv;
  std::map<std::int32_t, Status> seen;  // by pid
  auto options = RuntimeOptions::from_env();
  options.discovery_url = url;
  options.vehicle_url.clear();
  auto rt = Runtime::create(options);
  auto node = rt.create_node(node_name);
  auto sub = node.subscribe<Status>(channel, [&](const Status& s) {
    std::lock_guard lock(mu);
    seen[s.pid] = s;
    cv.notify_all();
  });
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(wait_ms);
  std::unique_lock lock(mu);
  if (cv.wait_until(lock, deadline, [&] { return !seen.empty(); })) {
    const auto more = std::min(deadline, std::chrono::steady_clock::now() + std::chrono::milliseconds(300));
    cv.wait_until(lock, more, [] { return false; });
  }
  return seen;  // copied under the lock; the subscription ends after
}

// The `status` subcommand of `parent` with its options (--url, --wait); `what`: the help line,
// `daemons`: "bridges", "gateways". `url` and `wait_ms` must outlive the parse.
inline CLI::App* add_status_subcommand(CLI::App& parent, const std::string& what, const std::string& daemons,
                                       std::string& url, int& wait_ms) {
  auto* status = parent.add_subcommand("status", what);
  status->add_option("--url", url, "host-local discovery group (default: lcmx --url, LCMX_DISCOVERY_URL)");
  status->add_option("--wait", wait_ms, "wait up to this long for " + daemons + "' status, in milliseconds")
      ->check(CLI::Range(50, 60000))
      ->capture_default_str();
  return status;
}

// The whole `lcmx <daemon> status` verb: collects the statuses (above), then prints each with
// `print(out, status)`, or with --json one object {"<json_key>":[to_json(status), ...]}.
// None within `wait_ms`: "no <daemon> found on this host within N ms" on stderr, exit status
// 1; an error (bad URL, ...): "lcmx <daemon> status: <what>" on stderr, 1.
template <class Status, class Print, class ToJson>
int show_statuses(const std::string& daemon, const std::string& json_key, const std::string& url,
                  const std::string& channel, int wait_ms, bool json, Print print, ToJson to_json) {
  spdlog::set_level(spdlog::level::warn);
  try {
    std::string node = daemon + "_status";  // "bridge_status", "dds_gateway_status"
    std::replace(node.begin(), node.end(), '-', '_');
    const auto seen = collect_statuses<Status>(url, channel, node, wait_ms);
    if (json) {
      std::cout << "{\"" << json_key << "\":[";
      bool first = true;
      for (const auto& [pid, s] : seen) std::cout << (std::exchange(first, false) ? "" : ",") << to_json(s);
      std::cout << "]}" << std::endl;
    } else {
      for (const auto& [pid, s] : seen) print(std::cout, s);
    }
    if (seen.empty()) {
      std::cerr << "no " << daemon << " found on this host within " << wait_ms << " ms\n";
      return 1;
    }
  } catch (const std::exception& e) {
    std::cerr << "lcmx " << daemon << " status: " << e.what() << "\n";
    return 1;
  }
  return 0;
}

}  // namespace lcmx::cli
