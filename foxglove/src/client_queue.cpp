#include "client_queue.hpp"

namespace lcmx::foxglove::detail {

void ClientQueue::drop_from(std::map<std::uint32_t, PerSub>::iterator it) {
  auto& ps = it->second;
  bytes_ -= ps.q.front().payload->size();
  ps.bytes -= ps.q.front().payload->size();
  ps.q.pop_front();
  --count_;
  ++dropped_;
  last_dropped_sub_ = it->first;
  if (ps.q.empty()) subs_.erase(it);
}

std::size_t ClientQueue::push(QueuedMessage m) {
  const std::size_t size = m.payload ? m.payload->size() : 0;
  if (size > max_bytes_ || max_messages_ == 0) {
    ++dropped_;
    last_dropped_sub_ = m.subscription;
    return 1;
  }
  std::size_t n = 0;
  while (count_ > 0 && (bytes_ + size > max_bytes_ || count_ + 1 > max_messages_)) {
    // The subscription holding the most bytes, the new message counted in its share: a
    // large channel's own messages make room for it before anyone else's.
    auto victim = subs_.end();
    std::size_t most = 0;
    for (auto it = subs_.begin(); it != subs_.end(); ++it) {
      const std::size_t b = it->second.bytes + (it->first == m.subscription ? size : 0);
      if (victim == subs_.end() || b > most) {
        victim = it;
        most = b;
      }
    }
    drop_from(victim);
    ++n;
  }
  m.order = next_order_++;
  auto& ps = subs_[m.subscription];
  ps.bytes += size;
  bytes_ += size;
  ++count_;
  ps.q.push_back(std::move(m));
  return n;
}

std::optional<QueuedMessage> ClientQueue::pop() {
  if (count_ == 0) return std::nullopt;
  auto best = subs_.end();
  for (auto it = subs_.begin(); it != subs_.end(); ++it)
    if (best == subs_.end() || it->second.q.front().order < best->second.q.front().order) best = it;
  QueuedMessage m = std::move(best->second.q.front());
  best->second.q.pop_front();
  const std::size_t size = m.payload ? m.payload->size() : 0;
  best->second.bytes -= size;
  bytes_ -= size;
  --count_;
  if (best->second.q.empty()) subs_.erase(best);
  return m;
}

void ClientQueue::erase(std::uint32_t subscription) {
  auto it = subs_.find(subscription);
  if (it == subs_.end()) return;
  bytes_ -= it->second.bytes;
  count_ -= it->second.q.size();
  subs_.erase(it);
}

}  // namespace lcmx::foxglove::detail
