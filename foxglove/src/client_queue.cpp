#include "client_queue.hpp"

namespace lcmx::foxglove::detail {

void ClientQueue::remove_if_empty(std::size_t i) {
  if (!subs_[i].q.empty()) return;
  index_.erase(subs_[i].id);
  if (i + 1 != subs_.size()) {
    subs_[i] = std::move(subs_.back());
    index_[subs_[i].id] = i;
  }
  subs_.pop_back();
}

void ClientQueue::drop_oldest(std::size_t i) {
  auto& s = subs_[i];
  const std::size_t size = size_of(s.q.front());
  bytes_ -= size;
  s.bytes -= size;
  s.q.pop_front();
  --count_;
  ++dropped_;
  last_dropped_sub_ = s.id;
  remove_if_empty(i);
}

std::size_t ClientQueue::push(QueuedMessage m) {
  const std::size_t size = size_of(m);
  if (size > max_bytes_ || max_messages_ == 0) {
    ++dropped_;
    last_dropped_sub_ = m.subscription;
    return 1;
  }
  std::size_t n = 0;
  while (count_ > 0 && (bytes_ + size > max_bytes_ || count_ + 1 > max_messages_)) {
    // The subscription holding the most bytes, the new message counted in its share: a
    // large channel's own messages make room for it before anyone else's.
    std::size_t victim = 0, most = 0;
    for (std::size_t i = 0; i < subs_.size(); ++i) {
      const std::size_t b = subs_[i].bytes + (subs_[i].id == m.subscription ? size : 0);
      if (i == 0 || b > most) {
        victim = i;
        most = b;
      }
    }
    drop_oldest(victim);
    ++n;
  }
  m.order = next_order_++;
  auto [it, fresh] = index_.emplace(m.subscription, subs_.size());
  if (fresh) subs_.push_back(Sub{m.subscription, 0, {}});
  auto& s = subs_[it->second];
  s.bytes += size;
  bytes_ += size;
  ++count_;
  s.q.push_back(std::move(m));
  return n;
}

std::optional<QueuedMessage> ClientQueue::pop() {
  if (count_ == 0) return std::nullopt;
  std::size_t best = 0;
  for (std::size_t i = 1; i < subs_.size(); ++i)
    if (subs_[i].q.front().order < subs_[best].q.front().order) best = i;
  auto& s = subs_[best];
  QueuedMessage m = std::move(s.q.front());
  s.q.pop_front();
  const std::size_t size = size_of(m);
  s.bytes -= size;
  bytes_ -= size;
  --count_;
  remove_if_empty(best);
  return m;
}

void ClientQueue::erase(std::uint32_t subscription) {
  auto it = index_.find(subscription);
  if (it == index_.end()) return;
  const std::size_t i = it->second;
  bytes_ -= subs_[i].bytes;
  count_ -= subs_[i].q.size();
  subs_[i].q.clear();
  remove_if_empty(i);
}

}  // namespace lcmx::foxglove::detail
