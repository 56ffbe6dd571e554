#include "events.hpp"

#include <spdlog/spdlog.h>

namespace lcmx::detail {

void EventHub::set_callback(std::function<void(const Event&)> callback) {
  std::lock_guard lock(mu_);
  callback_ = std::move(callback);
}

std::uint64_t EventHub::add_tap(std::function<void(const Event&)> tap) {
  std::lock_guard lock(mu_);
  const auto id = ++last_id_;
  taps_[id] = std::make_shared<const std::function<void(const Event&)>>(std::move(tap));
  return id;
}

void EventHub::remove_tap(std::uint64_t id) {
  std::lock_guard lock(mu_);
  taps_.erase(id);
}

std::uint64_t EventHub::add_housekeeping(std::function<void()> job) {
  std::lock_guard lock(mu_);
  const auto id = ++last_id_;
  jobs_[id] = std::make_shared<const std::function<void()>>(std::move(job));
  return id;
}

void EventHub::remove_housekeeping(std::uint64_t id) {
  std::lock_guard lock(mu_);
  jobs_.erase(id);
}

void EventHub::emit(std::vector<Event> events) {
  if (events.empty()) return;
  std::function<void(const Event&)> cb;
  std::vector<Tap> taps;
  {
    std::lock_guard lock(mu_);
    cb = callback_;
    for (const auto& [id, t] : taps_) taps.push_back(t);
  }
  for (const auto& e : events) {
    for (const auto& t : taps) (*t)(e);
    if (e.kind == Event::Kind::type_mismatch || e.kind == Event::Kind::error)
      spdlog::error("lcmx: {}", e.message);
    else
      spdlog::debug("lcmx: {}", e.message);
    // The user's callback runs on lcmx's threads: what it throws must not end them.
    try {
      if (cb) cb(e);
    } catch (const std::exception& x) {
      spdlog::error("lcmx: the on_event callback threw: {}", x.what());
    } catch (...) {
      spdlog::error("lcmx: the on_event callback threw");
    }
  }
}

void EventHub::run_housekeeping() {
  std::vector<Job> jobs;
  {
    std::lock_guard lock(mu_);
    for (const auto& [id, j] : jobs_) jobs.push_back(j);
  }
  for (const auto& j : jobs) {
    try {
      (*j)();
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: housekeeping failed: {}", e.what());
    }
  }
}

}  // namespace lcmx::detail
