#include "death_watch.hpp"

#include <spdlog/spdlog.h>

#include <cstdlib>

namespace lcmx::detail {

DeathWatch::DeathWatch(std::uint64_t own_pid_namespace) : own_pid_namespace_(own_pid_namespace) {
  try {
    watch_ = std::make_unique<shm::OwnerWatch>();
  } catch (const shm::Error& e) {
    spdlog::warn("lcmx: no fast death notice for publishers in other pid namespaces (their "
                 "lease applies): {}", e.what());
  }
}

int DeathWatch::fd() const {
  std::lock_guard lock(mu_);
  return watch_ ? watch_->fd() : -1;
}

void DeathWatch::watch(std::uint64_t participant, std::uint64_t endpoint, std::int64_t pid_namespace,
                       const std::string& segment) {
  if (pid_namespace == 0 || static_cast<std::uint64_t>(pid_namespace) == own_pid_namespace_) return;
  std::lock_guard lock(mu_);
  if (!watch_) return;
  const std::pair<std::uint64_t, std::uint64_t> pub{participant, endpoint};
  if (watched_.count(pub) || watched_.size() >= 4096) return;  // bounded
  try {
    const auto key = watch_->watch(segment);
    keys_[key] = {participant, endpoint, segment, false};
    watched_.insert(pub);
  } catch (const shm::Error& err) {
    spdlog::debug("lcmx: cannot watch the writer of {}: {} (its lease applies)", segment, err.what());
  }
}

void DeathWatch::forget(std::uint64_t participant) {
  std::lock_guard lock(mu_);
  for (auto it = keys_.begin(); it != keys_.end();) {
    if (it->second.participant != participant) {
      ++it;
      continue;
    }
    if (watch_) watch_->unwatch(it->first);
    watched_.erase({it->second.participant, it->second.endpoint});
    it = keys_.erase(it);
  }
}

namespace {
// Whether the writer of `segment` ("<base>_g<N>") or of one of its next generations runs: a
// writer that grew closes older generations without dying.
bool writer_runs(const std::string& segment) {
  const auto g = segment.rfind("_g");
  if (g == std::string::npos) return shm::owner_alive(segment);
  const std::string base = segment.substr(0, g + 2);
  const long n = std::strtol(segment.c_str() + g + 2, nullptr, 10);
  for (long k = n; k < n + 8; ++k)
    if (shm::owner_alive(base + std::to_string(k))) return true;
  return false;
}
}  // namespace

std::vector<DeathWatch::Dead> DeathWatch::take_dead() {
  std::vector<Dead> out;
  std::lock_guard lock(mu_);
  if (!watch_) return out;
  std::vector<std::uint64_t> keys;
  try {
    keys = watch_->take_dead();
  } catch (const std::exception& e) {
    spdlog::warn("lcmx: OwnerWatch: {}", e.what());
    return out;
  }
  for (const auto key : keys) {
    auto it = keys_.find(key);
    if (it == keys_.end()) continue;
    auto d = it->second;
    keys_.erase(it);
    watched_.erase({d.participant, d.endpoint});
    d.grew = writer_runs(d.segment);
    if (!d.grew) spdlog::info("lcmx: the writer of {} died: its publisher is gone", d.segment);
    out.push_back(std::move(d));
  }
  return out;
}

}  // namespace lcmx::detail
