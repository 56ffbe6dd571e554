// Data channels, the pure parts (channels.cpp uses them on the channel threads and in the shm
// callbacks; unit tests: test/bridge/pieces_test.cpp).
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <optional>
#include <utility>

#include "lcmx/bridge/config.hpp"
#include "lcmx/bridge/detail/wire.hpp"

namespace lcmx::bridge::datapath {

// A bounded per-(peer, channel) queue's push: when `q` holds `hwm` items, DropPolicy::oldest
// drops the front and queues `item`, DropPolicy::newest drops `item`. Returns whether something
// was dropped (the caller counts it).
template <class T>
bool push_bounded(std::deque<T>& q, T&& item, std::size_t hwm, DropPolicy policy) {
  bool dropped = false;
  if (q.size() >= hwm) {
    dropped = true;
    if (policy == DropPolicy::newest) return true;
    q.pop_front();
  }
  q.push_back(std::move(item));
  return dropped;
}

// The receiving side's sequence check per (peer, channel). A sender numbers its messages per
// channel from 1 within an instance (a restart is a new instance). accept() returns nullopt for
// a message that must not be delivered (same instance, sequence not above the last one: late
// data of an old link, a replay), otherwise the number of messages lost before it (a gap).
class RxSequence {
 public:
  std::optional<std::uint64_t> accept(const wire::DataHeader& h) {
    std::uint64_t lost = 0;
    if (!any_ || h.instance != instance_) {
      any_ = true;
      instance_ = h.instance;
    } else if (h.seq <= seq_) {
      return std::nullopt;
    } else {
      lost = h.seq - seq_ - 1;
    }
    seq_ = h.seq;
    return lost;
  }

 private:
  bool any_ = false;
  std::uint64_t instance_ = 0, seq_ = 0;
};

}  // namespace lcmx::bridge::datapath
