#include "markers.hpp"

#include <spdlog/spdlog.h>

#include <map>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/lcmtypes/envelope.hpp"
#include "lcmx_msgs/marker_t.hpp"

namespace lcmx::detail {

void Markers::tick(udpm::Group& group, bool vehicle, const std::set<std::string>& read) {
  std::lock_guard lock(mu_);
  auto& mine = channels_[vehicle ? 1 : 0];
  std::erase_if(mine, [&](const auto& kv) { return !read.count(kv.first); });  // nobody reads it now
  if (read.empty()) return;
  std::map<std::string, std::uint64_t, std::less<>> counts;
  for (auto& [name, n] : group.channel_counts()) counts.emplace(std::move(name), n);
  const auto now = std::chrono::steady_clock::now();
  for (const auto& channel : read) {
    const auto c = counts.find(channel);
    if (c == counts.end()) continue;  // nothing sent on it yet
    auto& p = mine[channel];
    if (p.known && c->second != p.count) {  // moved: every kEvery, then kRepeats more after
      p.repeats = kRepeats;
      if (now - p.last < kEvery) continue;
    } else if (p.known) {
      if (p.repeats == 0 || now - p.last < std::chrono::seconds(1)) continue;
      --p.repeats;
    }
    p.count = send_locked(group, channel);
    p.last = now;
    p.known = true;
  }
}

void Markers::baseline(udpm::Group& group, bool vehicle, const std::string& channel) {
  std::lock_guard lock(mu_);
  auto& p = channels_[vehicle ? 1 : 0][channel];
  p.count = send_locked(group, channel);
  p.last = std::chrono::steady_clock::now();
  p.known = true;
  p.repeats = 1;  // once more at a tick (this one may be lost)
}

std::uint64_t Markers::send_locked(udpm::Group& group, const std::string& channel) {
  std::uint64_t count = 0;
  try {
    group.publish_counted(discovery::kBeaconChannel, [&](std::span<const udpm::ChannelCount> counts) {
      for (const auto& c : counts)
        if (c.channel == channel) count = c.messages;
      lcmx_msgs::marker_t m{};
      m.version = 1;
      m.participant_id = static_cast<std::int64_t>(participant_);
      m.host_id = static_cast<std::int64_t>(host_);
      m.channel = channel;
      m.count = static_cast<std::int64_t>(count);
      return lcmtypes::encode(m);
    });
    ++counters_.sent;
  } catch (const udpm::Error& e) {
    spdlog::debug("lcmx: the data marker of '{}' could not be sent: {}", channel, e.what());
  }
  return count;
}

Markers::Counters Markers::counters() const {
  std::lock_guard lock(mu_);
  return counters_;
}

}  // namespace lcmx::detail
