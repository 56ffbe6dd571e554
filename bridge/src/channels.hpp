// Data channels, the pure parts (channels.cpp uses them on the channel threads and in the shm
// callbacks; unit tests: test/bridge/pieces_test.cpp).
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

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

// The receiving side's order per (peer, channel). A sender numbers its messages per channel
// from 1 within an instance (a restart is a new instance) and hands each to the socket of the
// link it uses then: one DEALER per link, each with a routing id of its own (`socket` here).
// Each socket delivers in order; after the sender switched links, the new socket's first
// messages may overtake what the old one still carries (a fail-back: the old link still works
// and is slower, or busier). So a message that leaves a gap is held while the gap may still
// fill from another socket:
//  - a message that closes the gap is delivered, then the held ones that follow it in order;
//  - a message beyond the gap from the socket that delivered the last one gives up on the gap
//    at once: that socket delivers in order, so what it carried of the gap is gone;
//  - the caller gives up when the hold is due (`hold` after it began) or when it knows the old
//    socket's link is down (expire with `force`), and push() does when more than `cap` are held.
// Giving up counts the missing numbers as lost and delivers what is held, in order. A message
// whose number is not above the last delivered one is not delivered (`stale`: late data of a
// link given up on, or a replay). Each number is thus delivered at most once, in order, and
// every number below the last delivered one was either delivered or counted lost, once.
// Not thread-safe: one per (peer, channel), used by the channel's thread only.
template <class T>
class RxOrder {
 public:
  using Clock = std::chrono::steady_clock;
  struct Out {
    std::vector<T> deliver;  // in order
    std::uint64_t lost = 0;  // numbers given up on
    std::uint64_t stale = 0;  // messages not delivered: not above the last delivered number
  };

  RxOrder(std::size_t cap, Clock::duration hold) : cap_(cap < 1 ? 1 : cap), hold_(hold) {}

  // One message from `socket` (its routing id) on `link` (the receiver's index of the link it
  // came over; -1: unknown).
  void push(const wire::DataHeader& h, std::string_view socket, int link, T item, Clock::time_point now, Out& out) {
    if (!any_ || h.instance != instance_) {
      give_up(out);  // the old instance is gone: its gap never fills
      any_ = true;
      instance_ = h.instance;
      deliver(h.seq, socket, link, std::move(item), out);  // joining mid-stream is not a loss
      return;
    }
    if (h.seq <= seq_ || held_.count(h.seq)) {
      ++out.stale;
      return;
    }
    if (h.seq == seq_ + 1) {
      deliver(h.seq, socket, link, std::move(item), out);
      release(out);
      return;
    }
    if (socket == socket_) {  // beyond the gap, from the socket that delivered the last one
      held_.emplace(h.seq, Held{std::string(socket), link, std::move(item)});
      give_up_below(h.seq, out);
      release(out);
      return;
    }
    if (held_.empty()) since_ = now;
    held_.emplace(h.seq, Held{std::string(socket), link, std::move(item)});
    if (held_.size() > cap_) give_up(out);
  }

  // Gives up on the gap when the hold is due, or at once with `force` (the caller knows the
  // old socket's link is down). Nothing to do when nothing is held.
  void expire(Clock::time_point now, bool force, Out& out) {
    if (!held_.empty() && (force || now - since_ >= hold_)) give_up(out);
  }

  bool holding() const { return !held_.empty(); }
  // When the hold is due (meaningful only while holding()).
  Clock::time_point due() const { return since_ + hold_; }
  // The link of the last delivered message (-1: none or unknown): the one the gap may still
  // come over.
  int last_link() const { return link_; }
  std::size_t held() const { return held_.size(); }

 private:
  struct Held {
    std::string socket;
    int link;
    T item;
  };
  void deliver(std::uint64_t seq, std::string_view socket, int link, T&& item, Out& out) {
    seq_ = seq;
    if (socket_ != socket) socket_.assign(socket);
    link_ = link;
    out.deliver.push_back(std::move(item));
  }
  // Delivers the held messages that follow the last delivered one in order.
  void release(Out& out) {
    while (!held_.empty() && held_.begin()->first == seq_ + 1) {
      auto node = held_.extract(held_.begin());
      deliver(node.key(), node.mapped().socket, node.mapped().link, std::move(node.mapped().item), out);
    }
  }
  // Counts the numbers missing below `below` lost and delivers the held ones below it.
  void give_up_below(std::uint64_t below, Out& out) {
    while (!held_.empty() && held_.begin()->first < below) {
      auto node = held_.extract(held_.begin());
      out.lost += node.key() - seq_ - 1;
      deliver(node.key(), node.mapped().socket, node.mapped().link, std::move(node.mapped().item), out);
    }
    if (below > seq_ + 1) {
      out.lost += below - seq_ - 1;
      seq_ = below - 1;
    }
  }
  // Gives up on every gap: delivers all that is held, in order.
  void give_up(Out& out) {
    while (!held_.empty()) {
      give_up_below(held_.begin()->first, out);
      release(out);
    }
  }

  std::size_t cap_;
  Clock::duration hold_;
  bool any_ = false;
  std::uint64_t instance_ = 0, seq_ = 0;
  std::string socket_;
  int link_ = -1;
  std::map<std::uint64_t, Held> held_;
  Clock::time_point since_{};
};

}  // namespace lcmx::bridge::datapath
