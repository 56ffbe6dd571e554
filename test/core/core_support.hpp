// Shared pieces of the core unit tests (lcmx_core_tests): a discovery group per call, a
// condition wait with a deadline, a gate for handlers.
#pragma once

#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <string>
#include <thread>

#include "lcmx/core.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace lcmx::core_test {

using namespace std::chrono_literals;

// Options with a discovery group of their own (derived from the pid and a counter, so tests
// run in parallel and two runtimes of one test can be kept apart), short beacons and lease.
inline lcmx::RuntimeOptions test_options() {
  static std::atomic<int> n{0};
  const int id = static_cast<int>(::getpid()) * 8 + n++;
  lcmx::RuntimeOptions o;
  o.discovery_url = "udpm://239.254." + std::to_string((id >> 8) & 0xff) + "." +
                    std::to_string(id & 0xff) + ":" + std::to_string(20000 + id % 40000) +
                    "?ttl=0&iface=lo";  // the root namespace: lo only, never the real interface
  o.beacon_period = 100ms;
  o.lease = 600ms;
  return o;
}

// Node options of a manual executor (the test calls spin_once()).
inline lcmx::NodeOptions manual() {
  lcmx::NodeOptions o;
  o.executor.kind = lcmx::ExecutorKind::manual;
  return o;
}

// A pose whose position[0] is `x` (a sequence number, a goal), the rest zero.
inline lcmx_examples::pose_t pose(double x) {
  lcmx_examples::pose_t p{};
  p.position[0] = x;
  return p;
}

// Waits for pred() with a deadline (condition polling, not a sleep to synchronise).
template <class Pred>
bool eventually(Pred pred, std::chrono::milliseconds deadline = 5000ms) {
  const auto end = std::chrono::steady_clock::now() + deadline;
  while (!pred()) {
    if (std::chrono::steady_clock::now() > end) return false;
    std::this_thread::yield();
  }
  return true;
}

// A gate a handler waits at until the test opens it (with a deadline, so nothing hangs).
struct Gate {
  std::mutex mu;
  std::condition_variable cv;
  bool open = false;
  int arrived = 0;
  void wait() {
    std::unique_lock lock(mu);
    ++arrived;
    cv.notify_all();
    cv.wait_for(lock, 10s, [&] { return open; });
  }
  void release() {
    std::lock_guard lock(mu);
    open = true;
    cv.notify_all();
  }
  bool wait_arrived(int n) {
    std::unique_lock lock(mu);
    return cv.wait_for(lock, 10s, [&] { return arrived >= n; });
  }
};

}  // namespace lcmx::core_test
