// One client's outgoing messages (docs/foxglove.md "Queue policy"): bounded in bytes and in
// messages. When a new message would exceed a bound, the oldest message of the subscription
// holding the most queued bytes is dropped first (so a client that does not keep up loses
// its large channels' messages, never its small ones' first), until the new one fits; a
// message larger than the byte bound alone is dropped itself. Messages are sent in arrival
// order. Control messages (JSON) are not in here: they are never dropped.
// Cost: push and pop scan the subscriptions that have queued messages (a compact array; tens to
// a few hundred), no allocation beyond the deques' blocks.
// Not thread-safe: the owner (the server's Client) locks it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <unordered_map>
#include <vector>

#include "payload.hpp"

namespace lcmx::foxglove::detail {

struct QueuedMessage {
  std::uint32_t subscription = 0;
  std::uint64_t timestamp_ns = 0;
  std::shared_ptr<const Payload> payload;  // shared by every client that gets it
  std::uint64_t order = 0;                 // set by push()
};

class ClientQueue {
 public:
  ClientQueue(std::size_t max_bytes, std::size_t max_messages)
      : max_bytes_(max_bytes), max_messages_(max_messages) {}

  // Queues `m`, dropping as the file comment says. Returns the number of messages dropped.
  std::size_t push(QueuedMessage m);
  // The oldest queued message, removed; nullopt when empty.
  std::optional<QueuedMessage> pop();
  // Forgets a subscription's queued messages (unsubscribed).
  void erase(std::uint32_t subscription);

  std::size_t bytes() const noexcept { return bytes_; }
  std::size_t size() const noexcept { return count_; }
  bool empty() const noexcept { return count_ == 0; }
  std::uint64_t dropped() const noexcept { return dropped_; }
  // Subscription whose message was dropped last (for the status message).
  std::uint32_t last_dropped_subscription() const noexcept { return last_dropped_sub_; }
  std::size_t max_bytes() const noexcept { return max_bytes_; }
  std::size_t max_messages() const noexcept { return max_messages_; }

 private:
  struct Sub {
    std::uint32_t id = 0;
    std::size_t bytes = 0;
    std::deque<QueuedMessage> q;  // oldest first, never empty while in subs_
  };
  static std::size_t size_of(const QueuedMessage& m) { return m.payload ? m.payload->size : 0; }
  void drop_oldest(std::size_t i);
  void remove_if_empty(std::size_t i);  // moves the last Sub into place i

  std::size_t max_bytes_, max_messages_;
  std::vector<Sub> subs_;                                // subscriptions with queued messages
  std::unordered_map<std::uint32_t, std::size_t> index_;  // id -> place in subs_
  std::size_t bytes_ = 0, count_ = 0;
  std::uint64_t next_order_ = 0, dropped_ = 0;
  std::uint32_t last_dropped_sub_ = 0;
};

}  // namespace lcmx::foxglove::detail
