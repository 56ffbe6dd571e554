// Pairs, this participant's endpoints: nodes, publishers, subscribers, channel subscriptions
// (Node::subscribe_channels, `lcmx record`), and what the beacon says of them.
#include <spdlog/spdlog.h>

#include "lcmx/discovery/beacon_codec.hpp"
#include "pairs.hpp"

namespace lcmx::detail {

Pairs::Outcome Pairs::add_node(const std::shared_ptr<NodeImpl>& node) {
  std::lock_guard lock(mu_);
  std::erase_if(nodes_, [](const auto& w) { return w.expired(); });
  nodes_.push_back(node);
  return {{}, true};
}

std::vector<std::shared_ptr<NodeImpl>> Pairs::live_nodes() {
  std::vector<std::shared_ptr<NodeImpl>> out;
  std::lock_guard lock(mu_);
  for (auto& w : nodes_)
    if (auto n = w.lock()) out.push_back(std::move(n));
  return out;
}

Pairs::Outcome Pairs::add_publisher(PublisherImpl* pub) {
  Outcome out{{}, true};
  std::lock_guard lock(mu_);
  expand_locked(pub->channel(), out);  // before: the loop below matches the new subscribers
  pubs_[pub->id] = pub;
  pubs_by_channel_.emplace(pub->channel(), pub->id);
  for (auto& sub : subscribers_of_locked(pub->channel())) match_local_locked(*pub, *sub, out);
  count_remote_locked(*pub, out);
  return out;
}

Pairs::Outcome Pairs::remove_publisher(PublisherImpl* pub) {
  Outcome out{{}, true};
  std::lock_guard lock(mu_);
  pubs_.erase(pub->id);
  std::erase_if(pubs_by_channel_, [&](const auto& kv) { return kv.second == pub->id; });
  for (auto& sub : subscribers_of_locked(pub->channel())) {
    auto& st = *sub->state;
    std::lock_guard l2(st.mu);
    const auto n = std::erase_if(st.matches, [&](const auto& m) {
      return m->path == Path::intra && m->publisher_endpoint == pub->id;
    });
    if (n) {
      ++st.version;
      st.matched_cv.notify_all();
      out.events.push_back({Event::Kind::publisher_unmatched, sub->channel(),
                            fmt::format("'{}': in-process publisher {} is gone", sub->channel(), pub->id)});
    }
  }
  return out;
}

Pairs::Outcome Pairs::add_subscriber(const std::shared_ptr<SubscriberCore>& sub) {
  Outcome out{{}, true};
  std::lock_guard lock(mu_);
  subs_[sub->id] = sub;
  subs_by_channel_.emplace(sub->channel(), sub->id);
  for (auto* pub : publishers_of_locked(sub->channel())) match_local_locked(*pub, *sub, out);
  sync_remote_locked(*sub, out);
  return out;
}

Pairs::Outcome Pairs::remove_subscriber(const SubscriberCore* sub) {
  std::lock_guard lock(mu_);
  for (auto* pub : publishers_of_locked(sub->channel())) pub->remove_intra(sub);
  subs_.erase(sub->id);
  std::erase_if(subs_by_channel_, [&](const auto& kv) { return kv.second == sub->id; });
  return {{}, true};
}

// Channel subscriptions: subscribes `channel` for every one whose filter accepts it and that
// has no subscriber of it yet.
void Pairs::expand_locked(const std::string& channel, Outcome& out) {
  if (channel.empty() || channel.size() > kMaxChannelLength || channel.find('\0') != std::string::npos ||
      channel == discovery::kBeaconChannel || channel == kHistoryChannel)
    return;
  for (const auto& p : channel_subs_) {
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
    auto sub = std::make_shared<RawSubscriberCore>(channel, p->options, [cb](const RawMessage& m) { (*cb)(m); });
    sub->state = std::make_shared<SubscriberState>();
    sub->state->node = p->node;
    sub->state->node_name = p->node->name;
    sub->state->since_ns = p->since_ns;
    sub->id = new_endpoint_id();
    p->node->add(sub);  // NodeImpl::mu after Pairs::mu_: the lock order
    subs_[sub->id] = sub;
    subs_by_channel_.emplace(channel, sub->id);
    p->children[channel] = sub;
    for (auto* pub : publishers_of_locked(channel)) match_local_locked(*pub, *sub, out);
    sync_remote_locked(*sub, out);
    out.announce = true;
  }
}

Pairs::Outcome Pairs::add_channel_subscription(const std::shared_ptr<ChannelSubscriptionCore>& p) {
  Outcome out{{}, true};
  std::lock_guard lock(mu_);
  channel_subs_.push_back(p);
  std::set<std::string> known = ctx_.peers.published_topics();
  for (auto& [id, pub] : pubs_) known.insert(pub->channel());
  for (const auto& c : known) expand_locked(c, out);
  return out;
}

std::vector<std::shared_ptr<SubscriberCore>> Pairs::remove_channel_subscription(ChannelSubscriptionCore* p) {
  std::vector<std::shared_ptr<SubscriberCore>> out;
  std::lock_guard lock(mu_);
  p->removed = true;
  std::erase_if(channel_subs_, [&](const auto& x) { return x.get() == p; });
  for (auto& [c, sub] : p->children) out.push_back(std::move(sub));
  p->children.clear();
  return out;
}

std::vector<std::pair<std::string, std::shared_ptr<SubscriberCore>>> Pairs::channel_children(
    const ChannelSubscriptionCore& p) {
  std::lock_guard lock(mu_);
  return {p.children.begin(), p.children.end()};
}

std::uint64_t Pairs::channel_refused(const ChannelSubscriptionCore& p) {
  std::lock_guard lock(mu_);
  return p.refused;
}

// Host scope: everything. Vehicle scope: the same endpoints without what only this host can
// use (shm segment names). Other hosts see neither a bridge's endpoints nor, while a bridge
// runs here, large publishers: those reach them through the bridges (DESIGN.md "Discovery",
// scopes).
void Pairs::describe(bool vehicle, lcmx_msgs::beacon_t& b,
                     const std::function<double(std::uint64_t, std::uint64_t)>& rate) {
  std::lock_guard lock(mu_);
  // A bridge of this host announces its peers' large topics while someone here takes channels
  // by pattern (docs/bridge.md "Pattern subscribers").
  if (!vehicle && !channel_subs_.empty())
    b.flags = static_cast<std::int8_t>(b.flags | lcmx_msgs::beacon_t::FLAG_CHANNELS);
  for (auto& w : nodes_)
    if (auto n = w.lock()) b.nodes.push_back(n->name);
  b.num_nodes = static_cast<std::int32_t>(b.nodes.size());
  if (vehicle && ctx_.options.bridge) {
    b.num_endpoints = 0;
    return;
  }
  for (auto& [id, pub] : pubs_) {
    if (vehicle && pub->bridged_only()) continue;
    lcmx_msgs::endpoint_t e{};
    e.id = static_cast<std::int64_t>(id);
    e.kind = lcmx_msgs::endpoint_t::KIND_PUBLISHER;
    e.node = pub->node->name;
    e.topic = pub->channel();
    e.type_name = pub->type.name;
    e.fingerprint = pub->type.fingerprint;
    if (!vehicle) e.shm_segment = pub->segment_name();
    e.large = pub->large() ? 1 : 0;
    e.max_message_size = static_cast<std::int64_t>(pub->options.max_message_size);
    e.history = static_cast<std::int32_t>(pub->options.history);
    e.messages = static_cast<std::int64_t>(pub->published());
    e.rate_hz = rate(id, pub->published());
    e.errors = pub->errors;
    e.num_errors = static_cast<std::int32_t>(e.errors.size());
    b.endpoints.push_back(std::move(e));
  }
  for (auto& [id, sub] : subs_) {
    lcmx_msgs::endpoint_t e{};
    e.id = static_cast<std::int64_t>(id);
    e.kind = lcmx_msgs::endpoint_t::KIND_SUBSCRIBER;
    e.node = sub->state->node_name;
    e.topic = sub->channel();
    e.type_name = sub->type().name;
    e.fingerprint = sub->type().fingerprint;
    e.messages = static_cast<std::int64_t>(sub->delivered.load());
    e.rate_hz = rate(id, sub->delivered.load());
    std::lock_guard l2(sub->state->mu);
    for (const auto& m : sub->state->matches) {
      lcmx_msgs::match_t mt;
      mt.publisher_participant = static_cast<std::int64_t>(m->publisher_participant);
      mt.publisher_endpoint = static_cast<std::int64_t>(m->publisher_endpoint);
      mt.path = to_string(m->path);
      mt.received = static_cast<std::int64_t>(m->stats->received.load());
      mt.drops = static_cast<std::int64_t>(m->stats->drops.load());
      e.drops += mt.drops;
      e.matches.push_back(std::move(mt));
    }
    e.num_matches = static_cast<std::int32_t>(e.matches.size());
    e.errors = sub->state->errors;
    e.num_errors = static_cast<std::int32_t>(e.errors.size());
    b.endpoints.push_back(std::move(e));
  }
  b.num_endpoints = static_cast<std::int32_t>(b.endpoints.size());
}

}  // namespace lcmx::detail
