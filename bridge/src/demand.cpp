// Peers and demand: the local view (which topics this host's non-bridge participants publish
// and subscribe to, whether one has channel subscriptions, from discovery), our catalogue, what
// each peer is served (one shm subscription per topic a peer wants and this host publishes) and
// the republishers' lifetime (also announcing peers' catalogues to pattern subscribers).
#include "engine.hpp"

#include <spdlog/spdlog.h>

namespace lcmx::bridge {

using namespace std::chrono_literals;

void Bridge::Impl::refresh_view() {
  std::set<std::string> d;
  std::map<std::string, bool> pubs;
  std::map<std::string, std::uint32_t> keeps;
  std::map<std::string, std::optional<wire::Control::TopicType>> types;  // nullopt: raw or conflicting
  bool patterns = false;
  const auto self = static_cast<std::int64_t>(runtime->participant_id());
  for (const auto& part : observer->participants()) {
    const auto& b = part.beacon;
    if (b.scope != lcmx_msgs::beacon_t::SCOPE_HOST) continue;
    // One bridge per host: a second one republishes what it carries here too, so this host's
    // subscribers of a topic both carry would get each message twice.
    if ((b.flags & lcmx_msgs::beacon_t::FLAG_BRIDGE) && b.participant_id != self &&
        other_bridges_warned.insert(b.participant_id).second)
      spdlog::warn("bridge {}: another Message Bridge runs on this host ({} pid {}); run one per host "
                   "(docs/bridge.md): subscribers here of a topic both carry get each message twice",
                   cfg.name, b.process_name, b.pid);
    if (b.flags & (lcmx_msgs::beacon_t::FLAG_BRIDGE | lcmx_msgs::beacon_t::FLAG_OBSERVER)) continue;
    if (b.flags & lcmx_msgs::beacon_t::FLAG_CHANNELS) patterns = true;
    for (const auto& e : b.endpoints) {
      if (!wire::valid_topic(e.topic)) continue;
      if (e.kind == lcmx_msgs::endpoint_t::KIND_SUBSCRIBER) d.insert(e.topic);
      else if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER) {
        pubs[e.topic] = pubs[e.topic] || e.large != 0;
        std::optional<wire::Control::TopicType> ty;  // raw, or a name a "type" line cannot carry: none
        if (e.fingerprint != 0 && wire::valid_type_name(e.type_name)) ty = {e.fingerprint, e.type_name};
        if (auto [it, fresh] = types.try_emplace(e.topic, ty); !fresh && it->second != ty) it->second.reset();
        if (e.history > 0)
          keeps[e.topic] = std::max(keeps[e.topic], std::min<std::uint32_t>(static_cast<std::uint32_t>(e.history),
                                                                             wire::Control::kMaxKeep));
      }
    }
  }
  const auto now = Clock::now();
  std::lock_guard lock(view_mu);
  demand = std::move(d);
  std::erase_if(demand_began, [&](const auto& kv) { return !demand.count(kv.first); });
  for (const auto& t : demand) demand_began.emplace(t, now);
  published = std::move(pubs);
  kept = std::move(keeps);
  typed.clear();
  for (auto& [t, ty] : types)
    if (ty) typed.emplace(t, std::move(*ty));
  channel_subscribers = patterns;
}

std::uint32_t Bridge::Impl::max_keep_of(const std::string& topic) const {
  const auto ch = cfg.channel_of(topic);
  return ch ? cfg.channels[*ch].max_keep : 0;
}

std::uint32_t Bridge::Impl::keep_of_locked(const std::string& topic) const {
  std::uint32_t n = 0;
  for (const auto& p : peers)
    if (p->active.load() >= 0)
      if (auto it = p->keeps.find(topic); it != p->keeps.end()) n = std::max(n, it->second);
  return std::min(n, max_keep_of(topic));  // a peer's keep sizes our ring: our cap (Trust)
}

wire::Control::TopicType Bridge::Impl::type_of_locked(const std::string& topic) const {
  std::optional<wire::Control::TopicType> type;
  for (const auto& p : peers) {
    if (p->active.load() < 0) continue;
    const auto it = p->types.find(topic);
    if (it == p->types.end() && !p->offers.count(topic) && !p->has.count(topic)) continue;  // not its topic
    const wire::Control::TopicType ty = it == p->types.end() ? wire::Control::TopicType{} : it->second;
    if (type && *type != ty) return {};  // peers disagree: raw
    type = ty;
  }
  return type.value_or(wire::Control::TopicType{});
}

bool Bridge::Impl::is_large_locked(const std::string& topic) const {
  auto it = published.find(topic);
  return (it != published.end() && it->second) || sticky_large.count(topic) || cfg.carried(topic);
}

std::set<std::string> Bridge::Impl::catalogue_locked() {
  std::set<std::string> out;
  for (const auto& [t, large] : published) {
    if (!is_large_locked(t) || !cfg.channel_of(t)) continue;
    if (out.size() >= wire::kMaxCatalogue) {
      if (!catalogue_cut_logged)
        spdlog::warn("bridge {}: this host publishes more than {} large topics: peers' pattern subscribers "
                     "see only the first {} by name ({} and later are left out)",
                     cfg.name, wire::kMaxCatalogue, wire::kMaxCatalogue, t);
      catalogue_cut_logged = true;
      break;
    }
    out.insert(t);
  }
  return out;
}

// Subscriptions (what peers want and this host publishes) and republishers.
void Bridge::Impl::note_local_drops(Served& s, bool final) {
  const std::uint64_t d = s.sub.stats().drops;  // a served topic always has its subscription
  if (d > s.drops_counted) {
    lost_local.fetch_add(d - s.drops_counted, std::memory_order_relaxed);
    s.drops_counted = d;
  }
  if (s.drops_counted != s.drops_logged && (final || s.drop_log.allow())) {
    spdlog::warn("bridge {}: {} local message(s) of {} lost before this bridge read them (the publisher's "
                 "shared-memory ring overwrote them: the bridge fell behind, e.g. stopped or short of CPU); "
                 "{} in total for this topic",
                 cfg.name, s.drops_counted - s.drops_logged, printable(s.topic), s.drops_counted);
    s.drops_logged = s.drops_counted;
  }
}

void Bridge::Impl::reconcile(Clock::time_point now) {
  const auto demand_ttl = 2 * cfg.link_timeout + cfg.heartbeat;
  std::map<std::string, std::vector<std::size_t>> want;  // topic -> peers
  std::map<std::string, bool> large;
  std::map<std::string, std::uint32_t> keep_local;  // served topic -> local publishers' keep
  std::set<std::string> offered, local_demand;
  std::map<std::string, std::uint32_t> keep_of;  // offered topic -> peers' keep last N
  std::set<std::string> announce;  // peers' catalogues, while a local participant has patterns
  bool announce_cut = false;
  {
    std::lock_guard lock(view_mu);
    for (std::size_t i = 0; i < peers.size(); ++i) {
      Peer& p = *peers[i];
      if (p.demand_at != Clock::time_point{} && now - p.demand_at > demand_ttl) {
        p.wants.clear();
        p.want_since.clear();
        p.offers.clear();
        p.demand_at = {};
      }
      p.served.clear();
      for (const auto& t : p.wants)
        if (published.count(t)) {
          want[t].push_back(i);
          p.served.insert(t);
        }
      if (p.active.load() >= 0) offered.insert(p.offers.begin(), p.offers.end());
      // Each peer's catalogue: its first max_catalogue topics by name (an idle republisher
      // each: a peer's catalogue costs this host at most that many), and all peers' together at
      // most wire::kMaxCatalogue.
      if (channel_subscribers && p.active.load() >= 0) {
        std::size_t from_peer = 0;
        for (const auto& t : p.has) {
          if (from_peer >= cfg.max_catalogue ||
              (announce.size() >= wire::kMaxCatalogue && !announce.count(t))) {
            announce_cut = true;
            break;
          }
          announce.insert(t);
          ++from_peer;
        }
      }
    }
    // When each topic's demand began at the peers' hosts, published here or not yet.
    std::map<std::string, Clock::time_point> wanted_now;
    for (const auto& pp : peers)
      for (const auto& t : pp->wants) {
        const auto ws = pp->want_since.find(t);
        const auto began = ws != pp->want_since.end() ? ws->second : now;
        if (auto [it, fresh] = wanted_now.try_emplace(t, began); !fresh) it->second = std::min(it->second, began);
      }
    std::erase_if(wanted_since, [&](const auto& kv) { return !wanted_now.count(kv.first); });
    for (const auto& [t, began] : wanted_now) wanted_since.emplace(t, began);
    for (const auto& [t, v] : want) {
      large[t] = is_large_locked(t);
      if (auto k = kept.find(t); k != kept.end()) keep_local[t] = k->second;
    }
    for (const auto& t : offered) keep_of[t] = keep_of_locked(t);
    local_demand = demand;
  }
  // Subscribe / update / unsubscribe.
  for (auto it = served.begin(); it != served.end();) {
    const bool gone = !want.count(it->first);
    note_local_drops(*it->second, gone);
    if (gone) {
      it->second->sub.reset();  // waits for a running callback; we hold no lock
      served_end[it->first] = Clock::now();  // it read up to here: a later one starts after
      spdlog::debug("bridge {}: no longer serving {}", cfg.name, printable(it->first));
      it = served.erase(it);
    } else {
      ++it;
    }
  }
  // An end older than any demand's age can be (wire::Control::kMaxWantAgeMs) bounds nothing.
  std::erase_if(served_end, [&](const auto& kv) {
    return now - kv.second > std::chrono::milliseconds(wire::Control::kMaxWantAgeMs);
  });
  for (auto& [t, ps] : want) {
    auto it = served.find(t);
    if (it == served.end()) {
      const auto ch = cfg.channel_of(t);
      if (!ch) {
        if (no_channel_logged.insert(t).second)
          spdlog::warn("bridge {}: topic {} matches no channel's topics: not bridged", cfg.name, printable(t));
        continue;
      }
      auto s = std::make_unique<Served>();
      s->topic = t;
      s->topic_ptr = std::make_shared<const std::string>(t);
      s->channel = *ch;
      s->large = large[t];
      s->keep = keep_local[t];
      s->peers = ps;
      Served* raw = s.get();
      SubscriberOptions so;
      so.from_bridges = false;
      // From when the peers' demand began, but never before what this bridge (or, before it
      // started, its predecessor) may have forwarded already.
      if (auto ws = wanted_since.find(t); ws != wanted_since.end()) {
        so.since = std::max(ws->second, started);
        if (auto se = served_end.find(t); se != served_end.end()) so.since = std::max(so.since, se->second);
      }
      try {
        s->sub = channels[*ch]->node->subscribe_raw(t, [this, raw](const RawMessage& m) { on_local_message(*raw, m); }, so);
      } catch (const std::exception& e) {
        spdlog::warn("bridge {}: cannot subscribe to {}: {}", cfg.name, printable(t), e.what());
        continue;
      }
      spdlog::debug("bridge {}: serving {} on channel {}", cfg.name, printable(t), channels[*ch]->cfg.name);
      served.emplace(t, std::move(s));
    } else {
      if (large[t]) it->second->large = true;
      it->second->keep = keep_local[t];
      std::lock_guard lock(it->second->mu);
      it->second->peers = ps;
    }
  }
  // Republishers: for what an up peer offers and this host wants; gone when unwanted, or
  // neither offered nor used for a while. While a participant of this host has channel
  // subscriptions, also one for every topic of an up peer's catalogue: its publisher endpoint in
  // our beacon is how those subscriptions learn the name (they subscribe by name to what they
  // accept, which is demand as usual); it is republished only once demanded and offered.
  if (announce_cut && !announce_cut_logged)
    spdlog::warn("bridge {}: a peer's catalogue holds more than max_catalogue = {} topics (or all peers' "
                 "together more than {}): the rest are not announced on this host to pattern subscribers",
                 cfg.name, cfg.max_catalogue, wire::kMaxCatalogue);
  announce_cut_logged = announce_cut_logged || announce_cut;
  // Made with the keep the peers' offers give; never remade here for its keep (the data
  // headers' keep decides that, in republish: an offer may lag behind the data), only when the
  // type the peers give the topic changed.
  for (const auto& t : offered)
    if (local_demand.count(t)) ensure_republisher(t, keep_of[t], false);
  for (const auto& t : announce)
    if (!offered.count(t) || !local_demand.count(t)) ensure_republisher(t, 0, false);
  std::vector<std::shared_ptr<Republisher>> dead;  // destroyed outside the lock
  {
    std::lock_guard lock(repub_mu);
    for (auto it = repubs.begin(); it != repubs.end();) {
      const bool keep = (local_demand.count(it->first) &&
                         (offered.count(it->first) || now - it->second->last() < 3 * cfg.link_timeout + 1s)) ||
                        announce.count(it->first);
      if (keep) {
        ++it;
      } else {
        dead.push_back(std::move(it->second));
        it = repubs.erase(it);
      }
    }
  }
}

}  // namespace lcmx::bridge
