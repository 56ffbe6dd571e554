// Links and failover: the answers to our pings (pongs) on every link, each link's up/down state,
// and the active link of every peer (fail over at once, fail back after the hold). The
// decisions: failover.hpp (pure, unit-tested).
#include "engine.hpp"
#include "failover.hpp"

#include <spdlog/spdlog.h>

namespace lcmx::bridge {

using namespace std::chrono_literals;

bool failover::link_up(bool answered, Clock::time_point last_pong, Clock::time_point now, Clock::duration timeout) {
  return answered && now - last_pong < timeout;
}

bool failover::pong_proves_link(std::int64_t age_ns, std::chrono::milliseconds link_timeout) {
  return age_ns >= 0 && age_ns <= std::chrono::duration_cast<std::chrono::nanoseconds>(link_timeout).count();
}

int failover::next_active(std::span<const LinkState> links, int current, Clock::time_point now,
                          Clock::duration failback_hold) {
  int best = -1;
  for (std::size_t i = 0; i < links.size(); ++i)
    if (links[i].up) {
      best = static_cast<int>(i);
      break;
    }
  const bool current_up = current >= 0 && static_cast<std::size_t>(current) < links.size() &&
                          links[static_cast<std::size_t>(current)].up;
  if (!current_up) return best;  // fail over at once (or none is up)
  if (best >= 0 && best < current && now - links[static_cast<std::size_t>(best)].up_since >= failback_hold)
    return best;  // fail back after the hold-down
  return current;
}

void Bridge::Impl::receive_pongs(Peer& p, Link& l) {
  for (std::size_t n = 0; n < kRecvBatch; ++n) {
    zmq::message_t m;
    try {
      if (!l.ctl->recv(m, zmq::recv_flags::dontwait)) return;
      if (m.more()) {  // a pong is one frame: drain and drop the rest
        for (bool more = true; more;) {
          zmq::message_t x;
          (void)l.ctl->recv(x, zmq::recv_flags::none);
          more = x.more();
        }
        count_bad("control: multi-part reply from " + p.cfg.name);
        continue;
      }
    } catch (const zmq::error_t&) {
      return;
    }
    l.bytes_received.fetch_add(m.size(), std::memory_order_relaxed);
    auto c = wire::decode(std::string_view(static_cast<const char*>(m.data()), m.size()));
    if (!c || c->kind != wire::Control::Kind::pong) {
      count_bad("control: malformed reply from " + p.cfg.name + " over " + l.cfg.link);
      continue;
    }
    if (c->from != p.cfg.name) {
      count_bad("control: " + l.cfg.address + " answered as bridge '" + c->from + "', expected " + p.cfg.name);
      continue;
    }
    const auto age = now_ns() - c->t_ns;
    if (!failover::pong_proves_link(age, cfg.link_timeout))
      continue;  // a stale answer (queued while the link was down) proves nothing
    l.last_pong = Clock::now();
    l.answered = true;
    l.last_pong_ns = now_ns();
    l.rtt_us = static_cast<std::int32_t>(age / 1000);
  }
}

void Bridge::Impl::update_links(Clock::time_point now) {
  for (auto& p : peers) {
    for (auto& l : p->links) {
      const bool up = failover::link_up(l->answered, l->last_pong, now, cfg.link_timeout);
      if (up != l->up) {
        l->up = up;
        l->up_flag = up;
        if (up) l->up_since = now;
        spdlog::info("bridge {}: link {} to {} ({}) is {}", cfg.name, l->cfg.link, p->cfg.name, l->cfg.address,
                     up ? "up" : "down");
      }
    }
    std::vector<failover::LinkState> states;
    states.reserve(p->links.size());
    for (const auto& l : p->links) states.push_back({l->up, l->up_since});
    const int cur = p->active.load();
    const int next = failover::next_active(states, cur, now, cfg.failback_hold);
    if (next != cur) {
      p->active = next;
      if (next >= 0 && cur >= 0) p->failovers.fetch_add(1);
      if (next >= 0)
        spdlog::info("bridge {}: peer {}: active link {} ({}){}", cfg.name, p->cfg.name,
                     p->links[static_cast<std::size_t>(next)]->cfg.link, p->links[static_cast<std::size_t>(next)]->cfg.address,
                     cur >= 0 ? " (was " + p->links[static_cast<std::size_t>(cur)]->cfg.link + ")" : "");
      for (auto& ch : channels) ch->wake->ring();
    }
    const bool is_up = next >= 0;
    if (is_up != p->was_up) {
      p->was_up = is_up;
      if (!is_up) spdlog::warn("bridge {}: peer {} unreachable on every link; retrying", cfg.name, p->cfg.name);
    }
  }
}

}  // namespace lcmx::bridge
