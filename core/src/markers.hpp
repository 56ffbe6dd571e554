// Markers: the data markers this participant sends (lcmx_msgs::marker_t on LCMX_BEACON,
// docs/ARCHITECTURE.md "UDP loss"). A marker names one channel a group's socket sends on that
// has readers there and says how many messages it sent on it so far (udpm::Group::
// publish_counted: counted under the send lock, so the count and the datagrams before it on the
// wire agree). A receiver counts what it got of the channel between two markers of one sender
// and knows exactly what it lost, per pair, whatever its socket's receive filter dropped of the
// sender's other channels; that filter takes the markers of the channels it reads by name
// (FrontDoor), so a new reader gets them before it even knows the sender.
//
// When, per channel: every kEvery while it moved since its last marker, kRepeats more a second
// apart after it stopped (a marker lost with the data before it is made good), and at once
// before the next message a newly matched reader gets (baseline(): the reader counts from that
// marker on). None while nobody on the group reads the channel (a publisher's blind start-up
// sends, which nobody may read, cost the LAN nothing).
//
// Threads: thread-safe. Its lock is taken before a group's send lock, never after it.
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <mutex>
#include <set>
#include <string>

#include "lcmx/udpm/udpm.hpp"

namespace lcmx::detail {

class Markers {
 public:
  Markers(std::uint64_t participant, std::uint64_t host) : participant_(participant), host_(host) {}

  // The markers due on `group` now (once a second, the receive thread). `read`: the channels
  // this participant sends there that someone of another process reads now. (Whether one is
  // due is judged on Group::channel_counts; the count a marker says is publish_counted's.)
  void tick(udpm::Group& group, bool vehicle, const std::set<std::string>& read);
  // A marker of `channel` on `group` now (its readers there grew: before its next message).
  // Any thread (a publisher's, publish_mu held).
  void baseline(udpm::Group& group, bool vehicle, const std::string& channel);

  struct Counters {
    std::uint64_t sent = 0;  // markers sent, both groups
  };
  Counters counters() const;

  static constexpr auto kEvery = std::chrono::seconds(2);
  static constexpr int kRepeats = 2;

 private:
  struct PerChannel {
    std::uint64_t count = 0;  // the count its last marker said
    std::chrono::steady_clock::time_point last{};
    int repeats = 0;          // markers still due after it stopped moving
    bool known = false;       // a marker of it went
  };
  // mu_ held. Sends the marker of `channel` with its exact count; returns that count.
  std::uint64_t send_locked(udpm::Group& group, const std::string& channel);

  const std::uint64_t participant_, host_;
  mutable std::mutex mu_;
  std::map<std::string, PerChannel> channels_[2];  // [0] host-local, [1] vehicle
  Counters counters_;
};

}  // namespace lcmx::detail
