// Path selection (docs/ARCHITECTURE.md "Path selection"): which publisher each subscriber
// receives from and over which path (intra, shm, udp, bridge), type checks, and the remote
// subscriber counts publishers go by. RuntimeImpl::mu held throughout.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdlib>

#include "internal.hpp"

namespace lcmx::detail {
namespace {
bool compatible(std::int64_t a, std::int64_t b) { return a == 0 || b == 0 || a == b; }
}  // namespace

void RuntimeImpl::report_mismatch_locked(std::uint64_t local_endpoint,
                                         std::uint64_t remote_participant,
                                         std::uint64_t remote_endpoint,
                                         const std::string& channel, const std::string& text,
                                         std::vector<std::string>& errors,
                                         std::vector<Event>& events) {
  if (!mismatches_reported.insert({local_endpoint, remote_participant, remote_endpoint}).second)
    return;
  errors.push_back(text);
  events.push_back({Event::Kind::type_mismatch, channel, text});
}

void RuntimeImpl::match_local_locked(PublisherImpl& pub, SubscriberCore& sub,
                                     std::vector<Event>& events) {
  if (pub.channel() != sub.channel()) return;
  if (options.bridge && !sub.options().from_bridges) return;  // our own republished messages
  if (options.dds_gateway && !sub.options().from_dds_gateways) return;  // our own imports
  if (!compatible(pub.type.fingerprint, sub.type().fingerprint)) {
    const std::string text = "type mismatch on channel '" + sub.channel() + "': publisher (node '" +
                             pub.node->name + "') has " + pub.type.name + ", subscriber (node '" +
                             sub.state->node_name + "') wants " + sub.type().name +
                             "; not matched";
    {
      std::lock_guard lock(sub.state->mu);
      report_mismatch_locked(sub.id, participant_id, pub.id, sub.channel(), text,
                             sub.state->errors, events);
    }
    report_mismatch_locked(pub.id, participant_id, sub.id, pub.channel(), text, pub.errors,
                           events);
    return;
  }
  auto m = std::make_shared<Match>();
  m->publisher_participant = participant_id;
  m->publisher_endpoint = pub.id;
  m->path = Path::intra;
  m->stats->publisher_participant = participant_id;  // who sends through the pair (PairCounters)
  m->stats->publisher_endpoint = pub.id;
  pub.add_intra(std::static_pointer_cast<SubscriberCore>(subs.at(sub.id)), m->stats);
  {
    std::lock_guard lock(sub.state->mu);
    sub.state->matches.push_back(m);
    ++sub.state->version;
    sub.state->matched_cv.notify_all();
  }
  events.push_back({Event::Kind::publisher_matched, sub.channel(),
                    "channel '" + sub.channel() + "': node '" + sub.state->node_name +
                        "' receives from node '" + pub.node->name + "' (intra)"});
}

// Brings one local subscriber's shm matches in line with what the other participants of
// this host publish: opens readers for new publishers, drops those that went away.
void RuntimeImpl::sync_remote_locked(SubscriberCore& sub, std::vector<Event>& events) {
  auto& st = *sub.state;
  std::set<std::pair<std::uint64_t, std::uint64_t>> wanted;
  std::vector<std::shared_ptr<Match>> added;
  struct Candidate {
    const lcmx_msgs::beacon_t* b;
    const lcmx_msgs::endpoint_t* e;
    Path path;
  };
  std::vector<Candidate> candidates;
  for (const auto* scope_map : {&remotes, &vehicle_remotes, &neighbour_remotes})
  for (const auto& [pid, b] : *scope_map) {
    const Path path = scope_map == &remotes ? Path::shm : Path::udp;
    const bool from_bridge = (b.flags & lcmx_msgs::beacon_t::FLAG_BRIDGE) != 0;
    if (from_bridge && !sub.options().from_bridges) continue;
    if ((b.flags & lcmx_msgs::beacon_t::FLAG_DDS_GATEWAY) && !sub.options().from_dds_gateways) continue;
    for (const auto& e : b.endpoints) {
      if (e.kind != lcmx_msgs::endpoint_t::KIND_PUBLISHER || e.topic != sub.channel()) continue;
      if (!compatible(e.fingerprint, sub.type().fingerprint)) {
        const std::string text = "type mismatch on channel '" + sub.channel() +
                                 "': publisher (process " + b.process_name + " pid " +
                                 std::to_string(b.pid) + ", node '" + e.node + "') has " +
                                 e.type_name + ", subscriber (node '" + st.node_name +
                                 "') wants " + sub.type().name + "; not matched";
        std::lock_guard lock(st.mu);
        report_mismatch_locked(sub.id, static_cast<std::uint64_t>(b.participant_id),
                               static_cast<std::uint64_t>(e.id), sub.channel(), text, st.errors,
                               events);
        continue;
      }
      if (path == Path::shm && e.shm_segment.empty()) continue;  // bridges' segments too
      // Its writer died (OwnerWatch) but its beacon has not expired yet: gone.
      if (path == Path::shm &&
          dead_publishers.count({static_cast<std::uint64_t>(b.participant_id), static_cast<std::uint64_t>(e.id)}))
        continue;
      wanted.insert({static_cast<std::uint64_t>(b.participant_id), static_cast<std::uint64_t>(e.id)});
      candidates.push_back({&b, &e, path == Path::shm && from_bridge ? Path::bridge : path});
    }
  }
  std::lock_guard lock(st.mu);
  const auto before = st.matches.size();
  std::size_t revived = 0;
  std::vector<std::shared_ptr<Match>> removed;
  std::erase_if(st.matches, [&](const std::shared_ptr<Match>& m) {
    if (m->path == Path::intra || m->foreign || m->retiring) return false;
    if (wanted.count({m->publisher_participant, m->publisher_endpoint})) return false;
    removed.push_back(m);
    if (m->reader) {  // keep it until the executor has read what was committed
      m->retiring = true;
      return false;
    }
    return true;
  });
  for (const auto& [b, e, path] : candidates) {
    const auto key = std::make_pair(static_cast<std::uint64_t>(b->participant_id),
                                    static_cast<std::uint64_t>(e->id));
    const auto same = [&](const std::shared_ptr<Match>& m) {
      return m->publisher_participant == key.first && m->publisher_endpoint == key.second;
    };
    if (std::any_of(st.matches.begin(), st.matches.end(),
                    [&](const auto& m) { return !m->retiring && same(m); }))
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
      events.push_back({Event::Kind::publisher_matched, sub.channel(),
                        "channel '" + sub.channel() + "': node '" + st.node_name +
                            "' receives again from process " + b->process_name + " pid " +
                            std::to_string(b->pid) + " node '" + e->node + "' (" +
                            to_string((*it)->path) + ")"});
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
            std::clamp<std::int32_t>(e->history, 0, static_cast<std::int32_t>(PublisherOptions::kMaxHistory)));
        m->reader = std::make_unique<shm::Reader>(shm::Reader::open(e->shm_segment, backlog));
        open_failures.erase(fkey);
        watch_owner_locked(*b, *e);
      } catch (const shm::Error& err) {
        // The publisher may be gone or be creating a new generation: retried on its next
        // beacon. Failing on several beacons in a row is no transient: an error Event, once.
        spdlog::debug("lcmx: channel '{}': cannot open {} yet: {}", sub.channel(), e->shm_segment,
                      err.what());
        if (open_failures.size() >= 4096) open_failures.clear();  // bounded
        // A file refused as untrusted (foreign owner, writable by others) is no transient:
        // said at once.
        const int failures = ++open_failures[fkey];
        if (failures == kOpenFailuresReported ||
            (failures == 1 && err.code() == shm::Errc::untrusted))
          events.push_back({Event::Kind::error, sub.channel(),
                            "channel '" + sub.channel() + "': node '" + st.node_name +
                                "' cannot open the shared memory '" + e->shm_segment +
                                "' of process " + b->process_name + " pid " +
                                std::to_string(b->pid) + ": " + err.what() +
                                "; not matched (retried on its next beacons)"});
        continue;
      }
    }
    st.matches.push_back(m);
    events.push_back({Event::Kind::publisher_matched, sub.channel(),
                      "channel '" + sub.channel() + "': node '" + st.node_name +
                          "' receives from process " + b->process_name + " pid " +
                          std::to_string(b->pid) + " node '" + e->node + "' (" +
                          to_string(path) + ")"});
  }
  for (auto& m : removed)
    events.push_back({Event::Kind::publisher_unmatched, sub.channel(),
                      "channel '" + sub.channel() + "': node '" + st.node_name +
                          "' lost a shm publisher (participant " +
                          std::to_string(m->publisher_participant) + ")"});
  if (st.matches.size() != before || !removed.empty() || revived > 0) {
    ++st.version;
    st.matched_cv.notify_all();
  }
  if (!removed.empty() || st.matches.size() != before) {
    if (st.node) st.node->ring();
  }
}

// Counts subscribers of other processes that report a match with `pub` (they opened its
// segment), and reports remote subscribers of another type.
void RuntimeImpl::count_remote_locked(PublisherImpl& pub, std::vector<Event>& events) {
  std::size_t counts[3] = {0, 0, 0};  // shm (this host), udp (other hosts), neighbours
  std::size_t unbridged = 0;          // of counts[1]: no bridge republisher matched yet
  std::set<std::pair<std::int64_t, std::int64_t>> seen;  // subscribers given a replay, still here
  for (const auto* scope_map : {&remotes, &vehicle_remotes, &neighbour_remotes})
  for (const auto& [pid, b] : *scope_map) {
    auto& n = counts[scope_map == &remotes ? 0 : scope_map == &vehicle_remotes ? 1 : 2];
    for (const auto& e : b.endpoints) {
      if (e.kind != lcmx_msgs::endpoint_t::KIND_SUBSCRIBER || e.topic != pub.channel()) continue;
      if (!compatible(e.fingerprint, pub.type.fingerprint)) {
        const std::string text = "type mismatch on channel '" + pub.channel() +
                                 "': publisher (node '" + pub.node->name + "') has " +
                                 pub.type.name + ", subscriber (process " + b.process_name +
                                 " pid " + std::to_string(b.pid) + ", node '" + e.node +
                                 "') wants " + e.type_name + "; not matched";
        report_mismatch_locked(pub.id, static_cast<std::uint64_t>(b.participant_id),
                               static_cast<std::uint64_t>(e.id), pub.channel(), text, pub.errors,
                               events);
        continue;
      }
      for (const auto& m : e.matches)
        if (static_cast<std::uint64_t>(m.publisher_participant) == participant_id &&
            static_cast<std::uint64_t>(m.publisher_endpoint) == pub.id) {
          ++n;
          if (scope_map == &vehicle_remotes &&
              std::none_of(e.matches.begin(), e.matches.end(), [](const lcmx_msgs::match_t& o) { return o.path == "bridge"; }))
            ++unbridged;
          if (pub.options.history > 0 && scope_map != &remotes) {
            const auto key = std::make_pair(b.participant_id, e.id);
            seen.insert(key);
            if (pub.replayed.insert(key).second)
              replay_jobs.push_back({pub.id, b.participant_id, e.id, scope_map == &vehicle_remotes});
          }
        }
    }
  }
  // Sent after this (send_replays): the subscriber counts are set first, so every message
  // published after the replay's snapshot is sent live.
  const bool was_bridged_only = pub.bridged_only();
  pub.set_remote_subscribers(counts[0], counts[1], counts[2], unbridged);
  // Leaving the vehicle beacon (bridged_only) is announced at once.
  if (pub.bridged_only() != was_bridged_only) {
    ++revision;
    announce_pending = true;
  }
  std::erase_if(pub.replayed, [&](const auto& k) { return !seen.count(k); });
}

// The bridges of this host (DESIGN.md "Message Bridge"): while one runs, large topics reach
// other hosts only through it, and the topics it carries besides the large class become large
// here (sticky, announced).
void RuntimeImpl::update_bridges_locked() {
  bool seen = false;
  std::vector<std::string> globs = options.bridge_carry;
  for (const auto& [pid, b] : remotes) {
    if (!(b.flags & lcmx_msgs::beacon_t::FLAG_BRIDGE)) continue;
    seen = true;
    for (const auto& g : b.carried)
      if (!g.empty() && std::find(globs.begin(), globs.end(), g) == globs.end()) globs.push_back(g);
  }
  if (seen != bridge_seen.exchange(seen))
    spdlog::info("lcmx: {} Message Bridge on this host", seen ? "a" : "no");
  {
    std::lock_guard lock(carried_mu);
    carried = std::move(globs);
  }
  for (auto& [id, pub] : pubs)
    if (!pub->large() && class_of(pub->channel()) == TopicClass::large) {
      pub->mark_large();
      ++revision;
      announce_pending = true;
    }
}

// A publisher in another pid namespace (no pidfd for it): watch its writer (OwnerWatch) so
// that its death is noticed in milliseconds, not after its lease. One watch per publisher.
void RuntimeImpl::watch_owner_locked(const lcmx_msgs::beacon_t& b, const lcmx_msgs::endpoint_t& e) {
  if (!owner_watch || b.pid_namespace == 0 ||
      static_cast<std::uint64_t>(b.pid_namespace) == own_pid_namespace)
    return;  // same pid namespace: discovery's pidfd says it at once
  const std::pair<std::uint64_t, std::uint64_t> pub{static_cast<std::uint64_t>(b.participant_id),
                                                    static_cast<std::uint64_t>(e.id)};
  if (owner_watched.count(pub) || owner_watched.size() >= 4096) return;  // bounded
  try {
    const auto key = owner_watch->watch(e.shm_segment);
    owner_keys[key] = {pub.first, pub.second, e.shm_segment};
    owner_watched.insert(pub);
  } catch (const shm::Error& err) {
    spdlog::debug("lcmx: cannot watch the writer of {}: {} (its lease applies)", e.shm_segment,
                  err.what());
  }
}

void RuntimeImpl::forget_owner_locked(std::uint64_t participant) {
  for (auto it = owner_keys.begin(); it != owner_keys.end();) {
    if (it->second.participant != participant) {
      ++it;
      continue;
    }
    if (owner_watch) owner_watch->unwatch(it->first);
    owner_watched.erase({it->second.participant, it->second.endpoint});
    it = owner_keys.erase(it);
  }
  std::erase_if(dead_publishers, [&](const auto& p) { return p.first == participant; });
}

namespace {
// Whether the writer of `segment` ("<base>_g<N>") or of one of its next generations runs: a
// writer that grew closes older generations without dying.
bool writer_runs(const std::string& segment) {
  const auto g = segment.rfind("_g");
  if (g == std::string::npos) return shm::owner_alive(segment);
  const std::string base = segment.substr(0, g + 2);
  const long n = std::strtol(segment.c_str() + g + 2, nullptr, 10);
  for (long k = n; k < n + 8; ++k)
    if (shm::owner_alive(base + std::to_string(k))) return true;
  return false;
}
}  // namespace

// Receive thread: OwnerWatch says writers died (or closed). A writer that only moved to a
// newer generation is watched there instead; the others' publishers are gone at once, as on a
// goodbye: their matches retire (the executor still reads what they committed).
void RuntimeImpl::on_owner_death() {
  std::vector<Event> events;
  bool any = false;
  {
    std::lock_guard lock(mu);
    if (!owner_watch) return;
    std::vector<std::uint64_t> keys;
    try {
      keys = owner_watch->take_dead();
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: OwnerWatch: {}", e.what());
      return;
    }
    for (const auto key : keys) {
      auto it = owner_keys.find(key);
      if (it == owner_keys.end()) continue;
      const auto w = it->second;
      owner_keys.erase(it);
      owner_watched.erase({w.participant, w.endpoint});
      if (writer_runs(w.segment)) {  // grew (or closed an old generation): watch the current one
        if (auto b = remotes.find(static_cast<std::int64_t>(w.participant)); b != remotes.end())
          for (const auto& e : b->second.endpoints)
            if (static_cast<std::uint64_t>(e.id) == w.endpoint && !e.shm_segment.empty())
              watch_owner_locked(b->second, e);
        continue;
      }
      dead_publishers.insert({w.participant, w.endpoint});
      any = true;
      spdlog::info("lcmx: the writer of {} died: its publisher is gone", w.segment);
    }
    if (any) {
      for (auto& [id, sub] : subs) sync_remote_locked(*sub, events);
      ++revision;
      announce_pending = true;
    }
  }
  if (!any) return;
  if (announce_pending.exchange(false)) {
    if (disco) disco->announce_now();
    if (disco_vehicle) disco_vehicle->announce_now();
  }
  if (options.reclaim_orphans) shm::reclaim_orphans(own_shm_prefix);
  emit(std::move(events));
}

}  // namespace lcmx::detail
