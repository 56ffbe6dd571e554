#include "replays.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>

#include "lcmx_msgs/history_t.hpp"
#include "pairs.hpp"
#include "publisher_impl.hpp"

namespace lcmx::detail {

namespace {
void log_refused(std::chrono::steady_clock::time_point& logged, std::uint64_t refused, const char* why) {
  const auto now = std::chrono::steady_clock::now();
  if (now - logged < std::chrono::seconds(5)) return;
  logged = now;
  spdlog::warn("lcmx: refused a keep-last-N replay ({} refused so far): {}", refused, why);
}
}  // namespace

bool Replays::queue(const Job& job) {
  std::lock_guard lock(mu_);
  const auto now = Clock::now();
  // Forget what is older than a lease (bounded by what a lease can hold).
  std::erase_if(last_, [&](const auto& kv) { return now - kv.second >= lease_; });
  const auto key = std::make_tuple(job.publisher, job.participant, job.endpoint);
  if (last_.count(key)) {
    ++refused_;
    log_refused(refused_logged_, refused_, "a subscriber endpoint gets one replay of a publisher per lease");
    return false;
  }
  last_[key] = now;
  auto& recent = recent_[job.publisher];
  std::erase_if(recent, [&](const auto& t) { return now - t >= lease_; });
  if (recent.size() < kMaxPerLease && pending_.empty()) {
    recent.push_back(now);
    jobs_.push_back(job);
    return true;
  }
  if (pending_.size() >= kMaxPending) {
    pending_.pop_front();
    ++refused_;
    log_refused(refused_logged_, refused_, "more replays waiting than kMaxPending (forged subscribers?)");
  }
  pending_.push_back(job);
  return true;
}

void Replays::tick() {
  std::lock_guard lock(mu_);
  const auto now = Clock::now();
  for (auto& [publisher, recent] : recent_) std::erase_if(recent, [&](const auto& t) { return now - t >= lease_; });
  std::deque<Job> wait;
  for (auto& job : pending_) {
    auto& recent = recent_[job.publisher];
    if (recent.size() < kMaxPerLease) {
      recent.push_back(now);
      jobs_.push_back(job);
    } else {
      wait.push_back(job);
    }
  }
  pending_.swap(wait);
  std::erase_if(recent_, [](const auto& kv) { return kv.second.empty(); });
}

std::uint64_t Replays::refused() const {
  std::lock_guard lock(mu_);
  return refused_;
}

std::size_t Replays::ready() const {
  std::lock_guard lock(mu_);
  return jobs_.size();
}

std::size_t Replays::waiting() const {
  std::lock_guard lock(mu_);
  return pending_.size();
}

void Replays::send(Pairs& pairs, std::uint64_t participant_id, udpm::Group& local, udpm::Group* vehicle) {
  std::vector<Job> jobs;
  {
    std::lock_guard lock(mu_);
    jobs.swap(jobs_);
  }
  for (const auto& j : jobs) {
    auto kept = pairs.kept_for_replay(j.publisher, j.vehicle);
    if (!kept || kept->messages.empty()) continue;
    lcmx_msgs::history_t h{};
    h.channel = kept->channel;
    for (auto& k : kept->messages) {
      lcmx_msgs::history_message_t x{};
      x.sent = k.sequence ? 1 : 0;
      x.sequence = static_cast<std::int32_t>(k.sequence.value_or(0));
      x.data.assign(reinterpret_cast<const std::uint8_t*>(k.encoded->data()),
                    reinterpret_cast<const std::uint8_t*>(k.encoded->data()) + k.encoded->size());
      x.size = static_cast<std::int32_t>(x.data.size());
      h.messages.push_back(std::move(x));
    }
    h.publisher_participant = static_cast<std::int64_t>(participant_id);
    h.publisher_endpoint = static_cast<std::int64_t>(j.publisher);
    h.subscriber_participant = j.participant;
    h.subscriber_endpoint = j.endpoint;
    h.num_messages = static_cast<std::int32_t>(h.messages.size());
    std::vector<std::byte> buf(static_cast<std::size_t>(h.getEncodedSize()));
    h.encode(buf.data(), 0, static_cast<int>(buf.size()));
    try {
      if (j.vehicle && vehicle)
        vehicle->publish(kHistoryChannel, buf);
      else if (!j.vehicle)
        local.publish_routed(kHistoryChannel, buf);
      spdlog::debug("lcmx: channel '{}': sent the last {} messages to a subscriber that matched late ({} group)",
                    h.channel, h.num_messages, j.vehicle ? "vehicle" : "host-local");
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: channel '{}': cannot send the last {} messages to a subscriber that matched late: {}",
                   h.channel, h.num_messages, e.what());
    }
  }
}

}  // namespace lcmx::detail
