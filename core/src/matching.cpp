// Pairs, path selection (docs/ARCHITECTURE.md "Path selection"): which publisher each
// subscriber receives from and over which path (intra, shm, udp, bridge), type checks, and the
// remote subscriber counts publishers go by. Pairs::mu_ held throughout the *_locked helpers.
#include <spdlog/spdlog.h>

#include <algorithm>

#include "pairs.hpp"

namespace lcmx::detail {
namespace {
bool compatible(std::int64_t a, std::int64_t b) { return a == 0 || b == 0 || a == b; }
}  // namespace

Pairs::Pairs(Context context) : ctx_(context) {}

std::vector<std::shared_ptr<SubscriberCore>> Pairs::subscribers_of_locked(const std::string& channel) {
  std::vector<std::shared_ptr<SubscriberCore>> out;
  auto [a, b] = subs_by_channel_.equal_range(channel);
  for (auto it = a; it != b; ++it)
    if (auto s = subs_.find(it->second); s != subs_.end()) out.push_back(s->second);
  return out;
}

std::vector<PublisherImpl*> Pairs::publishers_of_locked(const std::string& channel) {
  std::vector<PublisherImpl*> out;
  auto [a, b] = pubs_by_channel_.equal_range(channel);
  for (auto it = a; it != b; ++it)
    if (auto p = pubs_.find(it->second); p != pubs_.end()) out.push_back(p->second);
  return out;
}

// Publishers count subscribers by the matches subscribers announce: any change of ours is
// announced at once (versions only grow, so their sum tells).
std::uint64_t Pairs::match_versions_locked() {
  std::uint64_t v = 0;
  for (auto& [id, sub] : subs_) v += sub->state->version.load();
  return v;
}

void Pairs::report_mismatch_locked(std::uint64_t local_endpoint, std::uint64_t remote_participant,
                                   std::uint64_t remote_endpoint, const std::string& channel,
                                   const std::string& text, std::vector<std::string>& errors,
                                   Outcome& out) {
  if (!mismatches_reported_.insert({local_endpoint, remote_participant, remote_endpoint}).second) return;
  if (mismatches_reported_.size() > 65536) mismatches_reported_.clear();  // bounded (hostile beacons)
  if (errors.size() < 64) errors.push_back(text);
  out.events.push_back({Event::Kind::type_mismatch, channel, text});
}

void Pairs::match_local_locked(PublisherImpl& pub, SubscriberCore& sub, Outcome& out) {
  if (pub.channel() != sub.channel()) return;
  if (ctx_.options.bridge && !sub.options().from_bridges) return;  // our own republished messages
  if (ctx_.options.dds_gateway && !sub.options().from_dds_gateways) return;  // our own imports
  if (!compatible(pub.type.fingerprint, sub.type().fingerprint)) {
    const std::string text = "type mismatch on channel '" + sub.channel() + "': publisher (node '" +
                             pub.node->name + "') has " + pub.type.name + ", subscriber (node '" +
                             sub.state->node_name + "') wants " + sub.type().name + "; not matched";
    {
      std::lock_guard lock(sub.state->mu);
      report_mismatch_locked(sub.id, ctx_.participant_id, pub.id, sub.channel(), text, sub.state->errors, out);
    }
    report_mismatch_locked(pub.id, ctx_.participant_id, sub.id, pub.channel(), text, pub.errors, out);
    return;
  }
  auto m = std::make_shared<Match>();
  m->publisher_participant = ctx_.participant_id;
  m->publisher_endpoint = pub.id;
  m->path = Path::intra;
  m->stats->publisher_participant = ctx_.participant_id;  // who sends through the pair (PairCounters)
  m->stats->publisher_endpoint = pub.id;
  pub.add_intra(subs_.at(sub.id), m->stats);
  {
    std::lock_guard lock(sub.state->mu);
    sub.state->matches.push_back(m);
    ++sub.state->version;
    sub.state->matched_cv.notify_all();
  }
  out.events.push_back({Event::Kind::publisher_matched, sub.channel(),
                        "channel '" + sub.channel() + "': node '" + sub.state->node_name +
                            "' receives from node '" + pub.node->name + "' (intra)"});
}

// Brings one local subscriber's matches with other participants in line with what they
// publish on its channel now: opens readers for new publishers, retires those that went away.
void Pairs::sync_remote_locked(SubscriberCore& sub, Outcome& out) {
  auto& st = *sub.state;
  std::set<std::pair<std::uint64_t, std::uint64_t>> wanted;
  struct Candidate {
    PeerTable::Endpoint p;
    Path path;
  };
  std::vector<Candidate> candidates;
  // The sockets of the other hosts' (and neighbours') publishers on the channel: a foreign match
  // made for one before its record came (deliver_udp, the start-up race) ends now — the
  // pair is matched below, or refused.
  std::vector<udpm::Source> announced;
  for (auto& p : ctx_.peers.endpoints_on(sub.channel(), lcmx_msgs::endpoint_t::KIND_PUBLISHER)) {
    const Path path = p.scope == Scope::host ? Path::shm : Path::udp;
    if (p.scope != Scope::host)
      if (auto from = ctx_.peers.source_of(p.participant, p.scope == Scope::vehicle)) announced.push_back(*from);
    const bool from_bridge = (p.flags & lcmx_msgs::beacon_t::FLAG_BRIDGE) != 0;
    if (from_bridge && !sub.options().from_bridges) continue;
    if ((p.flags & lcmx_msgs::beacon_t::FLAG_DDS_GATEWAY) && !sub.options().from_dds_gateways) continue;
    const auto& e = p.e;
    if (!compatible(e.fingerprint, sub.type().fingerprint)) {
      const std::string text = "type mismatch on channel '" + sub.channel() + "': publisher (process " +
                               p.process_name + " pid " + std::to_string(p.pid) + ", node '" + e.node +
                               "') has " + e.type_name + ", subscriber (node '" + st.node_name + "') wants " +
                               sub.type().name + "; not matched";
      std::lock_guard lock(st.mu);
      report_mismatch_locked(sub.id, static_cast<std::uint64_t>(p.participant), static_cast<std::uint64_t>(e.id),
                             sub.channel(), text, st.errors, out);
      continue;
    }
    if (path == Path::shm && e.shm_segment.empty()) continue;  // bridges' segments too
    // Its writer died (DeathWatch) but its beacon has not expired yet: gone.
    if (path == Path::shm &&
        dead_publishers_.count({static_cast<std::uint64_t>(p.participant), static_cast<std::uint64_t>(e.id)}))
      continue;
    const Path chosen = path == Path::shm && from_bridge ? Path::bridge : path;
    candidates.push_back({std::move(p), chosen});
  }
  // A subscriber that a bridge of its host serves the channel takes no large topic of another
  // host over UDP: a large publisher sends UDP only for the subscribers without a bridge (on
  // a host where none runs, or whose bridge does not republish it), on the vehicle group this
  // host hears too, and its bridge forwards the same messages here (each arrived twice).
  if (std::any_of(candidates.begin(), candidates.end(), [](const Candidate& c) { return c.path == Path::bridge; }))
    std::erase_if(candidates, [](const Candidate& c) { return c.path == Path::udp && c.p.e.large != 0; });
  for (const auto& c : candidates)
    wanted.insert({static_cast<std::uint64_t>(c.p.participant), static_cast<std::uint64_t>(c.p.e.id)});
  std::lock_guard lock(st.mu);
  const auto before = st.matches.size();
  std::size_t revived = 0;
  bool removed_foreign = false;
  std::vector<std::shared_ptr<Match>> removed;
  std::erase_if(st.matches, [&](const std::shared_ptr<Match>& m) {
    if (m->foreign) {
      if (std::find(announced.begin(), announced.end(), m->foreign_source) == announced.end()) return false;
      st.retired_drops += m->stats->drops.load();
      removed_foreign = true;
      return true;
    }
    if (m->path == Path::intra || m->retiring) return false;
    if (wanted.count({m->publisher_participant, m->publisher_endpoint})) return false;
    removed.push_back(m);
    if (m->reader) {  // keep it until the executor has read what was committed
      m->retiring = true;
      return false;
    }
    return true;
  });
  for (const auto& [p, path] : candidates) {
    const auto& e = p.e;
    const auto key = std::make_pair(static_cast<std::uint64_t>(p.participant), static_cast<std::uint64_t>(e.id));
    const auto same = [&](const std::shared_ptr<Match>& m) {
      return m->publisher_participant == key.first && m->publisher_endpoint == key.second;
    };
    if (std::any_of(st.matches.begin(), st.matches.end(), [&](const auto& m) { return !m->retiring && same(m); }))
      continue;
    // The publisher is back (e.g. it was stopped past its lease): its retiring match is still
    // registered in its segment and has every message since, so it carries on. A second
    // Reader would deliver what the first still holds twice, and lose what was committed
    // between the two.
    if (auto it = std::find_if(st.matches.begin(), st.matches.end(),
                               [&](const auto& m) { return m->retiring && same(m); });
        it != st.matches.end()) {
      (*it)->retiring = false;
      std::erase_if(removed, [&](const auto& m) { return m == *it; });
      ++revived;
      out.events.push_back({Event::Kind::publisher_matched, sub.channel(),
                            "channel '" + sub.channel() + "': node '" + st.node_name +
                                "' receives again from process " + p.process_name + " pid " +
                                std::to_string(p.pid) + " node '" + e.node + "' (" + to_string((*it)->path) + ")"});
      continue;
    }
    auto m = std::make_shared<Match>();
    m->publisher_participant = key.first;
    m->publisher_endpoint = key.second;
    m->path = path;
    m->stats->publisher_participant = key.first;  // who sends through the pair (PairCounters)
    m->stats->publisher_endpoint = key.second;
    m->stats->path = path;
    if (path == Path::shm || path == Path::bridge) {
      const auto fkey = std::make_tuple(sub.id, key.first, key.second);
      try {
        // Keep last N: the publisher's kept messages are still in its ring (bounded: the
        // beacon is not trusted).
        const auto backlog = static_cast<std::uint32_t>(
            std::clamp<std::int32_t>(e.history, 0, static_cast<std::int32_t>(PublisherOptions::kMaxHistory)));
        // The start-up race: what it committed since this subscription began, too.
        m->reader = std::make_unique<shm::Reader>(shm::Reader::open(e.shm_segment, backlog, st.since_ns));
        open_failures_.erase(fkey);
        ctx_.deaths.watch(key.first, key.second, p.pid_namespace, e.shm_segment);
      } catch (const shm::Error& err) {
        // The publisher may be gone or be creating a new generation: retried on its next
        // beacon. Failing on several beacons in a row is no transient: an error Event, once.
        spdlog::debug("lcmx: channel '{}': cannot open {} yet: {}", sub.channel(), e.shm_segment, err.what());
        if (open_failures_.size() >= 4096) open_failures_.clear();  // bounded
        // A file refused as untrusted (foreign owner, writable by others) is no transient:
        // said at once.
        const int failures = ++open_failures_[fkey];
        if (failures == kOpenFailuresReported || (failures == 1 && err.code() == shm::Errc::untrusted))
          out.events.push_back({Event::Kind::error, sub.channel(),
                                "channel '" + sub.channel() + "': node '" + st.node_name +
                                    "' cannot open the shared memory '" + e.shm_segment + "' of process " +
                                    p.process_name + " pid " + std::to_string(p.pid) + ": " + err.what() +
                                    "; not matched (retried on its next beacons)"});
        continue;
      }
    }
    st.matches.push_back(m);
    out.events.push_back({Event::Kind::publisher_matched, sub.channel(),
                          "channel '" + sub.channel() + "': node '" + st.node_name + "' receives from process " +
                              p.process_name + " pid " + std::to_string(p.pid) + " node '" + e.node + "' (" +
                              to_string(path) + ")"});
  }
  for (auto& m : removed)
    out.events.push_back({Event::Kind::publisher_unmatched, sub.channel(),
                          "channel '" + sub.channel() + "': node '" + st.node_name +
                              "' lost a shm publisher (participant " + std::to_string(m->publisher_participant) +
                              ")"});
  if (st.matches.size() != before || !removed.empty() || revived > 0 || removed_foreign) {
    ++st.version;
    st.matched_cv.notify_all();
  }
  if (!removed.empty() || st.matches.size() != before) {
    if (st.node) st.node->ring();
  }
}

// Counts subscribers of other processes that report a match with `pub` (they opened its
// segment, or receive it over UDP), and reports remote subscribers of another type.
void Pairs::count_remote_locked(PublisherImpl& pub, Outcome& out) {
  std::size_t counts[3] = {0, 0, 0};  // shm (this host), udp (other hosts), neighbours
  std::size_t unbridged = 0;          // of counts[1]: no bridge republisher matched yet
  std::size_t unbridged_elsewhere = 0;  // on other hosts, no bridge match, matched with us or not
  std::set<std::pair<std::int64_t, std::int64_t>> seen;  // subscribers given a replay, still here
  for (const auto& p : ctx_.peers.endpoints_on(pub.channel(), lcmx_msgs::endpoint_t::KIND_SUBSCRIBER)) {
    const auto& e = p.e;
    auto& n = counts[p.scope == Scope::host ? 0 : p.scope == Scope::vehicle ? 1 : 2];
    if (!compatible(e.fingerprint, pub.type.fingerprint)) {
      const std::string text = "type mismatch on channel '" + pub.channel() + "': publisher (node '" +
                               pub.node->name + "') has " + pub.type.name + ", subscriber (process " +
                               p.process_name + " pid " + std::to_string(p.pid) + ", node '" + e.node +
                               "') wants " + e.type_name + "; not matched";
      report_mismatch_locked(pub.id, static_cast<std::uint64_t>(p.participant), static_cast<std::uint64_t>(e.id),
                             pub.channel(), text, pub.errors, out);
      continue;
    }
    const bool bridged =
        std::any_of(e.matches.begin(), e.matches.end(), [](const lcmx_msgs::match_t& o) { return o.path == "bridge"; });
    if (p.scope == Scope::vehicle && !bridged) ++unbridged_elsewhere;
    for (const auto& m : e.matches)
      if (static_cast<std::uint64_t>(m.publisher_participant) == ctx_.participant_id &&
          static_cast<std::uint64_t>(m.publisher_endpoint) == pub.id) {
        ++n;
        if (p.scope == Scope::vehicle && !bridged) ++unbridged;
        if (pub.options.history > 0 && p.scope != Scope::host) {
          const auto key = std::make_pair(p.participant, e.id);
          seen.insert(key);
          if (!pub.replayed.count(key) &&
              ctx_.replays.queue({pub.id, p.participant, e.id, p.scope == Scope::vehicle}))
            pub.replayed.insert(key);
        }
        break;
      }
  }
  // Sent after this (Replays::send): the subscriber counts are set first, so every message
  // published after the replay's snapshot is sent live.
  const bool was_bridged_only = pub.bridged_only();
  pub.set_remote_subscribers(counts[0], counts[1], counts[2], unbridged, unbridged_elsewhere);
  // Leaving the vehicle beacon (bridged_only) is announced at once.
  if (pub.bridged_only() != was_bridged_only) out.announce = true;
  std::erase_if(pub.replayed, [&](const auto& k) { return !seen.count(k); });
}

// The bridges of this host (DESIGN.md "Message Bridge"): while one runs, large topics reach
// other hosts only through it, and the topics it carries besides the large class become large
// here (sticky, announced).
void Pairs::update_bridges_locked(Outcome& out) {
  auto bridges = ctx_.peers.host_bridges();
  std::vector<std::string> globs = ctx_.options.bridge_carry;
  for (auto& g : bridges.carried)
    if (std::find(globs.begin(), globs.end(), g) == globs.end()) globs.push_back(std::move(g));
  if (ctx_.policy.set_bridges(bridges.seen, std::move(globs)))
    spdlog::info("lcmx: {} Message Bridge on this host", bridges.seen ? "a" : "no");
  for (auto& [id, pub] : pubs_)
    if (!pub->large() && ctx_.policy.class_of(pub->channel()) == TopicClass::large) {
      pub->mark_large();
      out.announce = true;
    }
}

// A peer joined, changed shape, or left: only the topics it touched are matched again.
Pairs::Outcome Pairs::on_peer(const PeerTable::Delta& d, const lcmx_msgs::beacon_t& b,
                              const std::function<bool(std::uint32_t)>& is_local_address) {
  Outcome out;
  const bool left = d.change == discovery::Change::left;
  const std::string where = d.scope == Scope::vehicle ? " on host " + std::to_string(b.host_id) : "";
  if (left)
    out.events.push_back({Event::Kind::participant_left, "",
                          "participant " + b.process_name + " pid " + std::to_string(b.pid) + where + " left"});
  else if (d.change == discovery::Change::joined)
    out.events.push_back({Event::Kind::participant_joined, "",
                          "participant " + b.process_name + " pid " + std::to_string(b.pid) + where + " joined"});
  std::lock_guard lock(mu_);
  if (!d.structural) {
    // Nothing it announces changed, but a segment of it we could not open is tried again on
    // each of its beacons (the error Event comes after kOpenFailuresReported in a row).
    std::set<std::uint64_t> retry;
    for (const auto& [key, failures] : open_failures_)
      if (std::get<1>(key) == static_cast<std::uint64_t>(b.participant_id)) retry.insert(std::get<0>(key));
    for (const auto id : retry)
      if (auto it = subs_.find(id); it != subs_.end()) sync_remote_locked(*it->second, out);
    return out;
  }
  if (left && d.scope == Scope::host) {
    ctx_.deaths.forget(static_cast<std::uint64_t>(b.participant_id));
    std::erase_if(dead_publishers_, [&](const auto& p) { return p.first == static_cast<std::uint64_t>(b.participant_id); });
  }
  const auto v0 = match_versions_locked();
  if (!left) {
    // Its messages may have arrived before its beacon and been taken for a stock LCM sender's:
    // now that we know who it is, that foreign match goes (its real one, if its type matches,
    // comes from the beacon). Its sources: its sockets, and (host-local group) its port from
    // any address of this host (the mirror).
    const auto local = parse_source(b.local_source);
    const auto vehicle = parse_source(b.vehicle_source);
    auto is_its = [&](const udpm::Source& s) {
      if ((local && s == *local) || (vehicle && s == *vehicle)) return true;
      return d.scope != Scope::vehicle && local && s.port_be == local->port_be && is_local_address(s.address_be);
    };
    for (auto& [id, sub] : subs_) {
      auto& st = *sub->state;
      std::lock_guard l2(st.mu);
      if (std::erase_if(st.matches, [&](const auto& m) { return m->foreign && is_its(m->foreign_source); })) {
        ++st.version;
        st.matched_cv.notify_all();
        out.announce = true;
      }
    }
    if (!channel_subs_.empty())
      for (const auto& e : b.endpoints)
        if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER) expand_locked(e.topic, out);
  }
  if (d.scope == Scope::host && d.bridge) update_bridges_locked(out);
  for (const auto& topic : d.publisher_topics)
    for (auto& sub : subscribers_of_locked(topic)) sync_remote_locked(*sub, out);
  if (d.scope == Scope::host && d.bridge) {
    // A bridge came or went: every large publisher may now (or no longer) reach other hosts
    // only through it (bridged_only), whatever its topic.
    for (auto& [id, pub] : pubs_) count_remote_locked(*pub, out);
  } else {
    for (const auto& topic : d.subscriber_topics)
      for (auto* pub : publishers_of_locked(topic)) count_remote_locked(*pub, out);
  }
  if (match_versions_locked() != v0) out.announce = true;
  return out;
}

Pairs::Outcome Pairs::writers_died(const std::vector<DeathWatch::Dead>& dead) {
  Outcome out;
  std::lock_guard lock(mu_);
  std::set<std::string> channels;
  for (const auto& d : dead) {
    auto now = ctx_.peers.host_endpoint(d.participant, d.endpoint);
    if (d.grew) {  // grew (or closed an old generation): watch the current one
      if (now && !now->e.shm_segment.empty())
        ctx_.deaths.watch(d.participant, d.endpoint, now->pid_namespace, now->e.shm_segment);
      continue;
    }
    dead_publishers_.insert({d.participant, d.endpoint});
    if (now) channels.insert(now->e.topic);
    else
      for (auto& [id, sub] : subs_) channels.insert(sub->channel());  // gone from the table: look everywhere
  }
  if (channels.empty()) return out;
  for (const auto& c : channels)
    for (auto& sub : subscribers_of_locked(c)) sync_remote_locked(*sub, out);
  out.announce = true;
  return out;
}

}  // namespace lcmx::detail
