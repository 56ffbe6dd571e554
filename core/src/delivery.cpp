// Pairs, the receive side (docs/ARCHITECTURE.md "UDP receive"): messages the front door took
// from the groups go to the subscribers matched with their sender; keep-last-N replays to the
// subscriber they name; UDP loss to the pairs it hit. The front door calls these with its
// recv_mu held; Pairs::mu_ is taken here.
#include <algorithm>
#include <spdlog/spdlog.h>

#include "pairs.hpp"

namespace lcmx::detail {
namespace {
std::int64_t now_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}
}  // namespace

// Exactly one path per pair: the front door drops messages of participants of this host (their
// subscribers here read shm); from a matched participant of another host (or a neighbour)
// they go to the subscribers matched with it, and from senders that are not lcmx participants
// (stock LCM programs) to every subscriber of the channel that takes their type.
//
// The start-up race (docs/ARCHITECTURE.md): a new publisher sends its first messages on the
// vehicle group before its record has reached this host, and its participant may be known
// already (it joined a moment before) or not. Until its record lists the publisher, its
// messages are taken as from a stock sender's socket (a foreign match, the type checked by
// fingerprint); once it does, the pair's matching takes over (sync_remote_locked ends the
// foreign match): each datagram is delivered once, by one of the two.
Pairs::Outcome Pairs::deliver_udp(bool vehicle, std::int64_t sender, const udpm::Source& source,
                                  const udpm::Message& m, std::vector<Target>& targets) {
  Outcome out;
  const std::string channel(m.channel);
  std::lock_guard lock(mu_);
  if (!channel_subs_.empty()) expand_locked(channel, out);
  std::optional<PeerTable::Publishing> announced;  // of `sender`, looked up once
  for (auto& sub : subscribers_of_locked(channel)) {
    auto& st = *sub->state;
    std::lock_guard l2(st.mu);
    std::shared_ptr<Match> match, by_source;
    for (auto& x : st.matches) {
      if (x->path != Path::udp) continue;
      if (sender != 0 && x->publisher_participant == static_cast<std::uint64_t>(sender)) {
        match = x;
        break;
      }
      if (x->foreign && x->foreign_source == source) by_source = x;
    }
    if (!match && sender != 0) {
      // Not matched with it: refused (a bridge's or DDS gateway's publisher this subscriber
      // does not take, its type, a large topic a bridge of this host carries), or not yet.
      if (!announced) announced = ctx_.peers.publishing(sender, channel);
      if ((announced->flags & lcmx_msgs::beacon_t::FLAG_BRIDGE) && !sub->options().from_bridges) continue;
      if ((announced->flags & lcmx_msgs::beacon_t::FLAG_DDS_GATEWAY) && !sub->options().from_dds_gateways) continue;
      if (announced->publishes) continue;  // its record says so, and matching refused it
    }
    if (!match) match = by_source;
    const std::string source_text = udpm::to_string(source);
    if (!match && !sub->type().raw() && !fingerprint_is(m.data, sub->type().fingerprint)) {
      // A stock LCM sender of another type on this channel: not delivered, reported once.
      const std::string text = "type mismatch on channel '" + sub->channel() + "': LCM sender " + source_text +
                               " sends another type than " + sub->type().name + "; not delivered";
      report_mismatch_locked(sub->id, 0, std::hash<std::string>{}(source_text), sub->channel(), text, st.errors, out);
      continue;
    }
    if (!match) {
      const auto foreign = std::count_if(st.matches.begin(), st.matches.end(), [](const auto& x) { return x->foreign; });
      if (static_cast<std::size_t>(foreign) >= kMaxForeign) {
        // Bounded (a flood of spoofed sources): the first kMaxForeign senders keep their place
        // until they fall silent (expire_foreign); the others are not delivered, counted.
        ++foreign_refused_;
        const auto now = std::chrono::steady_clock::now();
        if (now - foreign_refused_logged_ >= std::chrono::seconds(5)) {
          foreign_refused_logged_ = now;
          spdlog::warn("lcmx: channel '{}': LCM sender {} not received: the subscriber already receives from {} "
                       "stock LCM senders ({} refused so far)",
                       sub->channel(), source_text, kMaxForeign, foreign_refused_);
        }
        continue;
      }
      match = std::make_shared<Match>();
      match->path = Path::udp;
      match->foreign = true;
      match->foreign_source = source;
      match->publisher_endpoint = std::hash<std::string>{}(source_text);
      st.matches.push_back(match);
      ++st.version;
      st.matched_cv.notify_all();
      if (sender == 0)
        spdlog::info("lcmx: channel '{}': receiving from LCM sender {} ({} group)", sub->channel(), source_text,
                     vehicle ? "vehicle" : "host-local");
      else
        spdlog::debug("lcmx: channel '{}': receiving from participant {} ({}) before its record lists the publisher",
                      sub->channel(), sender, source_text);
    }
    if (match->foreign) match->foreign_seen_ns.store(now_ns(), std::memory_order_relaxed);
    {  // keep last N: see accept_history
      auto& src = st.udp_source(source_text, static_cast<std::uint64_t>(sender));
      if (src.replay_floor && serial_before(m.sequence, *src.replay_floor)) continue;
      if (!src.first_live) src.first_live = m.sequence;
    }
    targets.push_back({sub, match->stats});
  }
  return out;
}

Pairs::Outcome Pairs::expire_foreign(std::chrono::steady_clock::duration idle) {
  Outcome out;
  const auto limit = now_ns() - std::chrono::duration_cast<std::chrono::nanoseconds>(idle).count();
  std::lock_guard lock(mu_);
  for (auto& [id, sub] : subs_) {
    auto& st = *sub->state;
    std::lock_guard l2(st.mu);
    const auto n = std::erase_if(st.matches, [&](const auto& m) {
      if (!m->foreign || m->foreign_seen_ns.load(std::memory_order_relaxed) >= limit) return false;
      st.retired_drops += m->stats->drops.load();
      return true;
    });
    if (n > 0) {
      ++st.version;
      st.matched_cv.notify_all();
      out.announce = true;
    }
  }
  return out;
}

// A keep-last-N replay (Replays::send) for one of our subscribers: its messages go to the
// subscriber's queue, oldest first, except those it received live (sent with a sequence
// number at or after the first it received live from the publisher's socket, known as a
// participant or not yet); live messages that arrive later, already delivered by the replay,
// are dropped (SubscriberState::UdpSource).
std::vector<std::pair<Pairs::Target, std::shared_ptr<const Bytes>>> Pairs::accept_history(
    bool vehicle, const udpm::Source& source, const lcmx_msgs::history_t& h) {
  std::vector<std::pair<Target, std::shared_ptr<const Bytes>>> deliver;
  if (h.subscriber_participant != static_cast<std::int64_t>(ctx_.participant_id)) return deliver;
  // Only from the publisher's own socket on that group: a replay raises the subscriber's
  // replay floor, so a forged one could otherwise mute live messages.
  const auto from = ctx_.peers.source_of(h.publisher_participant, vehicle);
  if (!from || !(*from == source)) {
    spdlog::debug("lcmx: ignored a keep-last-N replay from {}: not the socket of publisher {}",
                  udpm::to_string(source), h.publisher_participant);
    return deliver;
  }
  std::lock_guard lock(mu_);
  auto it = subs_.find(static_cast<std::uint64_t>(h.subscriber_endpoint));
  if (it == subs_.end() || it->second->channel() != h.channel) return deliver;
  auto sub = it->second;
  auto& st = *sub->state;
  std::lock_guard l2(st.mu);
  std::shared_ptr<Match> match;
  for (auto& x : st.matches)  // as deliver_udp picks it: live messages carry no endpoint
    if (x->path == Path::udp && x->publisher_participant == static_cast<std::uint64_t>(h.publisher_participant)) {
      match = x;
      break;
    }
  if (!match) return deliver;  // unmatched since: nothing to hand over
  // Per socket: what came live before the publisher was known (its beacon not yet here) went
  // to a match of the socket as an unknown LCM sender.
  auto& src = st.udp_source(udpm::to_string(source), static_cast<std::uint64_t>(h.publisher_participant));
  for (const auto& x : h.messages) {
    const auto seq = static_cast<std::uint32_t>(x.sequence);
    if (x.sent && src.first_live && !serial_before(seq, *src.first_live)) continue;  // had it live
    if (x.sent && (!src.replay_floor || serial_before(*src.replay_floor, seq + 1))) src.replay_floor = seq + 1;
    deliver.push_back({{sub, match->stats},
                       std::make_shared<const Bytes>(reinterpret_cast<const std::byte*>(x.data.data()),
                                                     reinterpret_cast<const std::byte*>(x.data.data()) + x.data.size())});
  }
  return deliver;
}

std::vector<std::string> Pairs::charge_loss(std::int64_t sender, const std::set<std::string>& channels,
                                            std::uint64_t lost) {
  std::vector<std::string> subscribed;
  std::lock_guard lock(mu_);
  for (const auto& channel : channels)
    for (auto& sub : subscribers_of_locked(channel)) {
      auto& st = *sub->state;
      std::lock_guard l2(st.mu);
      for (auto& x : st.matches) {
        if (x->path != Path::udp || x->publisher_participant != static_cast<std::uint64_t>(sender)) continue;
        if (channels.size() == 1) x->stats->drops.fetch_add(lost, std::memory_order_relaxed);
        subscribed.push_back(sub->channel());
      }
    }
  return subscribed;
}

Pairs::UdpWants Pairs::udp_wants() {
  UdpWants out;
  std::lock_guard lock(mu_);
  out.all = !channel_subs_.empty();
  if (out.all) return out;
  for (const auto& [channel, id] : subs_by_channel_) out.channels.insert(channel);
  return out;
}

std::set<std::string> Pairs::udp_read_channels(bool vehicle) {
  std::set<std::string> out;
  std::lock_guard lock(mu_);
  for (const auto& [id, pub] : pubs_)
    if (pub->udp_readers(vehicle) > 0) out.insert(pub->channel());
  return out;
}

std::optional<Pairs::Kept> Pairs::kept_for_replay(std::uint64_t publisher, bool vehicle) {
  std::lock_guard lock(mu_);  // the publisher cannot go away meanwhile
  auto it = pubs_.find(publisher);
  if (it == pubs_.end()) return std::nullopt;
  return Kept{it->second->channel(), it->second->kept_for_udp(vehicle)};
}

}  // namespace lcmx::detail
