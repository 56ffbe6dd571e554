// Channel subscriptions (Node::subscribe_channels, for `lcmx record`): a filter over channel
// names that becomes one ordinary raw subscriber per accepted channel, created the first time
// the channel shows up — a publisher here (add_publisher), a publisher endpoint in a beacon of
// either scope (on_participant), or a stock LCM sender's datagram (on_udp expands before it
// dispatches, so that first datagram is delivered too). RuntimeImpl::mu guards everything here.
// While any exists, the host-scope beacon carries FLAG_CHANNELS (build_beacon): a Message Bridge
// of this host then announces its peers' large topics as its republishers, so they show up here
// too (docs/bridge.md "Pattern subscribers").
#include <spdlog/spdlog.h>

#include <set>

#include "internal.hpp"
#include "lcmx/discovery/beacon_codec.hpp"

namespace lcmx::detail {

void RuntimeImpl::expand_locked(const std::string& channel, std::vector<Event>& events) {
  if (channel.empty() || channel.size() > kMaxChannelLength ||
      channel.find('\0') != std::string::npos || channel == discovery::kBeaconChannel || channel == kHistoryChannel)
    return;
  for (const auto& p : channel_subs) {
    if (p->removed || p->children.count(channel) || p->declined.count(channel)) continue;
    bool accept = false;
    try {
      accept = p->filter(channel);
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: channel filter threw on '{}': {}", channel, e.what());
    }
    if (!accept) {
      if (p->declined.size() >= 4096) p->declined.clear();  // bounded (hostile senders)
      p->declined.insert(channel);
      continue;
    }
    if (p->children.size() >= p->max_channels) {
      if (p->refused++ == 0)
        spdlog::warn("lcmx: channel subscription of node '{}' is at its limit of {} channels: "
                     "'{}' and later new channels are not subscribed",
                     p->node->name, p->max_channels, channel);
      if (p->declined.size() >= 4096) p->declined.clear();
      p->declined.insert(channel);
      continue;
    }
    auto cb = p->callback;
    auto sub = std::make_shared<RawSubscriberCore>(
        channel, p->options, [cb](const RawMessage& m) { (*cb)(m); });
    sub->state = std::make_shared<SubscriberState>();
    sub->state->node = p->node;
    sub->state->node_name = p->node->name;
    sub->id = new_endpoint_id();
    p->node->add(sub);  // NodeImpl::mu after RuntimeImpl::mu: the lock order
    subs[sub->id] = sub;
    p->children[channel] = sub;
    for (auto& [id, pub] : pubs) match_local_locked(*pub, *sub, events);
    sync_remote_locked(*sub, events);
    ++revision;
    announce_pending = true;
  }
}

void RuntimeImpl::add_channel_subscription(const std::shared_ptr<ChannelSubscriptionCore>& p) {
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    channel_subs.push_back(p);
    std::set<std::string> known;
    for (auto& [id, pub] : pubs) known.insert(pub->channel());
    for (const auto* scope_map : {&remotes, &vehicle_remotes})
      for (const auto& [pid, b] : *scope_map)
        for (const auto& e : b.endpoints)
          if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER) known.insert(e.topic);
    for (const auto& c : known) expand_locked(c, events);
    announce_pending = false;
  }
  changed();
  emit(std::move(events));
}

std::vector<std::shared_ptr<SubscriberCore>> RuntimeImpl::remove_channel_subscription(
    ChannelSubscriptionCore* p) {
  std::vector<std::shared_ptr<SubscriberCore>> out;
  std::lock_guard lock(mu);
  p->removed = true;
  std::erase_if(channel_subs, [&](const auto& x) { return x.get() == p; });
  for (auto& [c, sub] : p->children) out.push_back(std::move(sub));
  p->children.clear();
  return out;
}

std::vector<std::pair<std::string, std::shared_ptr<SubscriberCore>>> RuntimeImpl::channel_children(
    const ChannelSubscriptionCore& p) {
  std::lock_guard lock(mu);
  return {p.children.begin(), p.children.end()};
}

std::uint64_t RuntimeImpl::channel_refused(const ChannelSubscriptionCore& p) {
  std::lock_guard lock(mu);
  return p.refused;
}

}  // namespace lcmx::detail
