// The bridge's status snapshot (lcmx_msgs::bridge_status_t, published on kStatusChannel by the
// control thread and returned by Bridge::status()): peers, links, channels, demand.
#include "engine.hpp"

#include <unistd.h>

namespace lcmx::bridge {

using namespace std::chrono_literals;

lcmx_msgs::bridge_status_t Bridge::Impl::status() const {
  lcmx_msgs::bridge_status_t s{};
  s.timestamp_us = std::chrono::duration_cast<std::chrono::microseconds>(
                       std::chrono::system_clock::now().time_since_epoch()).count();
  s.name = cfg.name;
  s.host_id = runtime ? static_cast<std::int64_t>(runtime->host_id()) : 0;
  s.pid = static_cast<std::int32_t>(::getpid());
  s.curve = cfg.security.curve ? 1 : 0;
  s.bad_frames = static_cast<std::int64_t>(bad_frames.load());
  const auto now = now_ns();
  std::lock_guard lock(view_mu);
  for (const auto& p : peers) {
    lcmx_msgs::bridge_peer_status_t ps{};
    ps.name = p->cfg.name;
    const int active = p->active.load();
    ps.up = active >= 0 ? 1 : 0;
    ps.active_link = active >= 0 ? p->links[static_cast<std::size_t>(active)]->cfg.link : "";
    ps.failovers = static_cast<std::int64_t>(p->failovers.load());
    for (std::size_t i = 0; i < p->links.size(); ++i) {
      const Link& l = *p->links[i];
      lcmx_msgs::bridge_link_status_t ls{};
      ls.name = l.cfg.link;
      ls.address = l.cfg.address;
      ls.up = l.up_flag.load() ? 1 : 0;
      ls.active = static_cast<int>(i) == active ? 1 : 0;
      ls.bytes_sent = static_cast<std::int64_t>(l.bytes_sent.load());
      ls.bytes_received = static_cast<std::int64_t>(l.bytes_received.load());
      const auto lp = l.last_pong_ns.load();
      ls.heartbeat_age_ms = lp < 0 ? -1 : (now - lp) / 1000000;
      ls.rtt_us = l.rtt_us.load();
      ps.links.push_back(std::move(ls));
    }
    ps.num_links = static_cast<std::int32_t>(ps.links.size());
    for (std::size_t c = 0; c < channels.size(); ++c) {
      const PeerChannel& pc = *p->chans[c];
      lcmx_msgs::bridge_channel_status_t cs{};
      cs.name = channels[c]->cfg.name;
      cs.messages_sent = static_cast<std::int64_t>(pc.sent_msgs.load());
      cs.bytes_sent = static_cast<std::int64_t>(pc.sent_bytes.load());
      cs.drops = static_cast<std::int64_t>(pc.drops.load());
      cs.queued = pc.queued.load();
      cs.messages_received = static_cast<std::int64_t>(pc.recv_msgs.load());
      cs.bytes_received = static_cast<std::int64_t>(pc.recv_bytes.load());
      cs.lost = static_cast<std::int64_t>(pc.lost.load());
      ps.channels.push_back(std::move(cs));
    }
    ps.num_channels = static_cast<std::int32_t>(ps.channels.size());
    ps.served.assign(p->served.begin(), p->served.end());
    ps.num_served = static_cast<std::int32_t>(ps.served.size());
    ps.wanted.assign(p->wants.begin(), p->wants.end());
    ps.num_wanted = static_cast<std::int32_t>(ps.wanted.size());
    s.peers.push_back(std::move(ps));
  }
  s.num_peers = static_cast<std::int32_t>(s.peers.size());
  s.demand.assign(demand.begin(), demand.end());
  s.num_demand = static_cast<std::int32_t>(s.demand.size());
  s.zero_copy_sends = static_cast<std::int64_t>(zero_copy_msgs.load(std::memory_order_relaxed));
  s.copied_sends = static_cast<std::int64_t>(copied_msgs.load(std::memory_order_relaxed));
  s.lost_local = static_cast<std::int64_t>(lost_local.load(std::memory_order_relaxed));
  return s;
}

}  // namespace lcmx::bridge
