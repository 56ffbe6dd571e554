// EventHub: where the runtime's Events go (the user's Runtime::on_event callback, lcmx's own
// taps), and the housekeeping jobs run about once a second on the receive thread.
//
// Threads: every member is thread-safe. emit() and run_housekeeping() call out with no lock of
// the hub held; call them with no lcmx lock held (discovery's delivery lock excepted, see
// add_tap). The hub's lock is a leaf: nothing is taken while it is held.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <vector>

#include "lcmx/core/stats.hpp"

namespace lcmx::detail {

class EventHub {
 public:
  // Replaces the user's callback (Runtime::on_event). What it throws is logged, never
  // propagated: it runs on lcmx's threads.
  void set_callback(std::function<void(const Event&)> callback);

  // lcmx's own listeners (service clients, action servers): called for every event before the
  // user's callback, on the thread that emits it, with no lcmx lock held except possibly
  // discovery's delivery lock. A tap must be quick and must not call into the runtime (set a
  // flag, interrupt a node). It may still run once after remove_tap() returns: capture weak
  // pointers.
  std::uint64_t add_tap(std::function<void(const Event&)> tap);
  void remove_tap(std::uint64_t id);

  // Housekeeping (service servers forget gone clients): called about once a second on the
  // receive thread with no lcmx lock held, so a job may call into the runtime (destroy a
  // publisher). Must be quick. May still run once after remove_housekeeping() returns: capture
  // weak pointers. What a job throws is logged.
  std::uint64_t add_housekeeping(std::function<void()> job);
  void remove_housekeeping(std::uint64_t id);

  // Taps first, then the log (errors and type mismatches at error level, the rest at debug),
  // then the user's callback; in order.
  void emit(std::vector<Event> events);
  void run_housekeeping();

 private:
  using Tap = std::shared_ptr<const std::function<void(const Event&)>>;
  using Job = std::shared_ptr<const std::function<void()>>;
  std::mutex mu_;  // guards everything below
  std::function<void(const Event&)> callback_;
  std::map<std::uint64_t, Tap> taps_;
  std::map<std::uint64_t, Job> jobs_;
  std::uint64_t last_id_ = 0;
};

}  // namespace lcmx::detail
