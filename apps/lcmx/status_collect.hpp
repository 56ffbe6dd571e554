// `lcmx bridge status` and `lcmx dds-gateway status`: collects the status messages that this
// host's daemons publish on a channel, one per process (keyed by pid, the latest kept).
// A daemon publishes at once when it sees a new status subscriber, so this waits for the first
// status (up to `wait_ms`), then 300 ms more (bounded by `wait_ms`) for other daemons of the
// host. Host-local group only (`url`; the vehicle group is never joined): this host's daemons.
// Errors: throws what Runtime::create / subscribe throw. Thread: the caller's, blocking.
#pragma once

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <map>
#include <mutex>
#include <string>

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

}  // namespace lcmx::cli
