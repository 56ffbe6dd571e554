// The control thread: its loop (poll, view refresh, heartbeat tick, status), the pings this
// bridge sends on every link of every peer (heartbeat, and on the active link the demand), the
// pings peers send us (their demand) with our pongs, and the hello check of channel layouts.
#include "engine.hpp"

#include <algorithm>
#include <iterator>

#include <spdlog/spdlog.h>

namespace lcmx::bridge {

using namespace std::chrono_literals;

void Bridge::Impl::control_loop() {
  auto next_ping = Clock::now();
  auto next_status = Clock::now() + cfg.status_period;
  auto next_view = Clock::now();
  std::size_t status_subs = 0;
  std::vector<zmq::pollitem_t> items;
  std::vector<std::pair<Peer*, Link*>> polled;
  while (!stopping.load()) {
    items.clear();
    polled.clear();
    items.push_back({ctl_router->handle(), 0, ZMQ_POLLIN, 0});
    items.push_back({nullptr, ctl_wake->fd(), ZMQ_POLLIN, 0});
    for (auto& p : peers)
      for (auto& l : p->links) {
        items.push_back({l->ctl->handle(), 0, ZMQ_POLLIN, 0});
        polled.emplace_back(p.get(), l.get());
      }
    const auto wait = std::max<Clock::duration>(0ms, next_ping - Clock::now());
    try {
      zmq::poll(items.data(), items.size(), std::chrono::duration_cast<std::chrono::milliseconds>(wait) + 1ms);
    } catch (const zmq::error_t& e) {
      if (e.num() == ETERM) break;
      continue;
    }
    if (items[1].revents & ZMQ_POLLIN) ctl_wake->drain();
    if (items[0].revents & ZMQ_POLLIN) receive_control();
    for (std::size_t i = 0; i < polled.size(); ++i)
      if (items[i + 2].revents & ZMQ_POLLIN) receive_pongs(*polled[i].first, *polled[i].second);

    const auto now = Clock::now();
    if (view_dirty.exchange(false) || now >= next_view) {
      refresh_view();
      next_view = now + 1s;
    }
    if (now >= next_ping) {
      update_links(now);
      reconcile(now);
      send_pings();
      next_ping += cfg.heartbeat;
      if (next_ping < now) next_ping = now + cfg.heartbeat;
    }
    const std::size_t subs = status_pub->subscriber_count();
    if (now >= next_status || subs > status_subs) {
      try {
        status_pub->publish(status());
      } catch (const std::exception& e) {
        spdlog::warn("bridge {}: status publish failed: {}", cfg.name, e.what());
      }
      next_status = now + cfg.status_period;
    }
    status_subs = subs;
  }
}

// Every heartbeat, on every link of every peer: a ping. On the active link it is marked
// active (the peer keeps our demand alive) and carries the full state — channels, what this
// host wants, what we will send it, our catalogue — only when that changed, the link or the peer's
// instance changed, or a second passed: the idle link carries a few dozen bytes per ping.
void Bridge::Impl::send_pings() {
  wire::Control c;
  c.kind = wire::Control::Kind::ping;
  c.from = cfg.name;
  c.instance = instance;
  std::set<std::string> want, have;
  std::map<std::string, std::uint32_t> want_age;  // ms: how long this host has wanted each
  const auto now = Clock::now();
  {
    std::lock_guard lock(view_mu);
    want = demand;
    have = catalogue_locked();
    for (const auto& [t, began] : demand_began) {
      const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now - began).count();
      if (ms > 0) want_age[t] = static_cast<std::uint32_t>(std::min<std::int64_t>(ms, wire::Control::kMaxWantAgeMs));
    }
  }
  // A frame holds at most wire::kMaxDemand want lines (peers refuse more).
  if (want.size() > wire::kMaxDemand) {
    if (!demand_cut_logged)
      spdlog::warn("bridge {}: this host subscribes to more than {} topics: peers are asked for the first {} by name",
                   cfg.name, wire::kMaxDemand, wire::kMaxDemand);
    demand_cut_logged = true;
    want.erase(std::next(want.begin(), static_cast<std::ptrdiff_t>(wire::kMaxDemand)), want.end());
  }
  for (auto& p : peers) {
    const int active = p->active.load();
    // Every topic we serve it, small ones too: its republisher then exists (and its
    // subscribers have matched it) before the topic becomes large, so the message that makes
    // it large, forwarded at once, reaches them (DESIGN.md "Delivery", the large switch).
    std::set<std::string> offer;
    std::map<std::string, std::uint32_t> keep;
    std::map<std::string, wire::Control::TopicType> types;  // of what we offer it and our catalogue
    if (active >= 0) {
      std::lock_guard lock(view_mu);
      for (const auto& t : p->served) {
        offer.insert(t);
        if (auto it = kept.find(t); it != kept.end() && it->second > 0 && keep.size() < wire::kMaxCatalogue)
          keep[t] = it->second;
      }
      for (const auto* topics : {&offer, &have})
        for (const auto& t : *topics)
          if (auto it = typed.find(t); it != typed.end() && types.size() < wire::kMaxCatalogue) types[t] = it->second;
    }
    const bool full = active >= 0 && (want != p->sent_want || offer != p->sent_offer || have != p->sent_have ||
                                      keep != p->sent_keep || types != p->sent_types ||
                                      active != p->full_sent_link || p->instance != p->full_sent_instance ||
                                      now - p->full_sent_at >= kDemandRefresh);
    for (std::size_t i = 0; i < p->links.size(); ++i) {
      Link& l = *p->links[i];
      c.link = l.cfg.link;
      c.t_ns = now_ns();
      c.active = static_cast<int>(i) == active;
      c.has_demand = c.active && full;
      c.want.clear();
      c.want_age_ms.clear();
      c.offer.clear();
      c.keep.clear();
      c.types.clear();
      c.have.clear();
      c.channels.clear();
      if (c.has_demand) {
        c.control_port = cfg.control_port;
        for (const auto& ch : cfg.channels) c.channels.emplace_back(ch.name, ch.port);
        c.want = want;
        c.want_age_ms = want_age;  // the encoder writes the ages of `want`'s topics only
        c.offer = offer;
        c.keep = keep;
        c.types = types;
        c.have = have;
        p->sent_want = want;
        p->sent_offer = offer;
        p->sent_keep = keep;
        p->sent_types = types;
        p->sent_have = have;
        p->full_sent_at = now;
        p->full_sent_link = active;
        p->full_sent_instance = p->instance;
      }
      const std::string text = wire::encode(c);
      try {
        if (l.ctl->send(zmq::buffer(text), zmq::send_flags::dontwait))
          l.bytes_sent.fetch_add(text.size(), std::memory_order_relaxed);
      } catch (const zmq::error_t&) {
      }
    }
  }
}

// Pings from peers (on our control ROUTER): remember their demand/offers, answer.
void Bridge::Impl::receive_control() {
  for (std::size_t n = 0; n < kRecvBatch; ++n) {
    zmq::message_t id, body;
    bool extra = false;
    try {
      if (!ctl_router->recv(id, zmq::recv_flags::dontwait)) return;
      if (!id.more()) {
        count_bad("control: a message without body");
        continue;
      }
      (void)ctl_router->recv(body, zmq::recv_flags::none);
      for (bool more = body.more(); more;) {  // drain unexpected parts
        zmq::message_t x;
        (void)ctl_router->recv(x, zmq::recv_flags::none);
        more = x.more();
        extra = true;
      }
    } catch (const zmq::error_t&) {
      return;
    }
    if (extra) {
      count_bad("control: more than one frame");
      continue;
    }
    auto c = wire::decode(std::string_view(static_cast<const char*>(body.data()), body.size()));
    if (!c || c->kind != wire::Control::Kind::ping) {
      count_bad("control: malformed message");
      continue;
    }
    auto it = peer_by_name.find(c->from);
    if (it == peer_by_name.end()) {
      count_bad("control: ping from unknown bridge '" + c->from + "' (not in this bridge's peers)");
      continue;
    }
    // The name a ping claims (`from`) must be the connection's: the peer the ZAP handler
    // admitted it as (User-Id: its address, and with CURVE its key), and the routing id its
    // control DEALER set ("<name>/<link>/<random>", engine.hpp routing_id), which our pong goes
    // back to.
    const std::string claimed_id = c->from + "/" + c->link + "/";
    if (id.to_string_view().substr(0, claimed_id.size()) != claimed_id || !authentic(body, c->from)) {
      count_bad("control: ping from " + user_of(body) + "'s connection claiming to be " + c->from + " (routing id '" +
                printable(id.to_string_view()) + "')");
      continue;
    }
    Peer& p = *peers[it->second];
    if (int l = link_of(p, peer_address(body)); l >= 0)
      p.links[static_cast<std::size_t>(l)]->bytes_received.fetch_add(body.size(), std::memory_order_relaxed);
    if (p.instance != c->instance) {
      if (p.instance != 0)
        spdlog::info("bridge {}: peer {} restarted (instance {} -> {})", cfg.name, p.cfg.name, hex64(p.instance),
                     hex64(c->instance));
      p.instance = c->instance;
      std::lock_guard lock(view_mu);
      p.wants.clear();
      p.want_since.clear();
      p.offers.clear();
      p.keeps.clear();
      p.types.clear();
      p.has.clear();
    }
    if (c->has_demand && p.hello_checked_instance != c->instance) {
      p.hello_checked_instance = c->instance;
      check_hello(p, *c);
    }
    if (c->has_demand) {
      // A newly wanted topic has been wanted at the peer's host since its age before now (the
      // network's delay is not in it: we serve a little later than the demand began, never
      // earlier). A topic wanted already keeps its time.
      const auto now = Clock::now();
      std::map<std::string, Clock::time_point> since;
      std::lock_guard lock(view_mu);
      for (const auto& t : c->want) {
        if (auto it = p.want_since.find(t); it != p.want_since.end()) {
          since.insert(*it);
        } else {
          const auto a = c->want_age_ms.find(t);
          since.emplace(t, now - std::chrono::milliseconds(a == c->want_age_ms.end() ? 0 : a->second));
        }
      }
      p.want_since = std::move(since);
      p.wants = std::move(c->want);
      p.offers = std::move(c->offer);
      p.keeps = std::move(c->keep);
      p.types = std::move(c->types);
      p.has = std::move(c->have);
      p.demand_at = Clock::now();
    } else if (c->active) {
      std::lock_guard lock(view_mu);
      if (p.demand_at != Clock::time_point{}) p.demand_at = Clock::now();  // still wanted
    }
    wire::Control pong;
    pong.kind = wire::Control::Kind::pong;
    pong.from = cfg.name;
    pong.instance = instance;
    pong.link = c->link;
    pong.t_ns = c->t_ns;
    const std::string text = wire::encode(pong);
    try {
      ctl_router->send(id, zmq::send_flags::sndmore | zmq::send_flags::dontwait);
      ctl_router->send(zmq::buffer(text), zmq::send_flags::dontwait);
      if (int l = link_of(p, peer_address(body)); l >= 0)
        p.links[static_cast<std::size_t>(l)]->bytes_sent.fetch_add(text.size(), std::memory_order_relaxed);
    } catch (const zmq::error_t&) {
      // EHOSTUNREACH (ROUTER_MANDATORY): the peer went away meanwhile; it pings again.
    }
  }
}

void Bridge::Impl::check_hello(const Peer& p, const wire::Control& c) {
  std::vector<std::pair<std::string, int>> ours;
  for (const auto& ch : cfg.channels) ours.emplace_back(ch.name, ch.port);
  if (c.control_port == cfg.control_port && c.channels == ours) return;
  auto text = [](int control, const std::vector<std::pair<std::string, int>>& v) {
    std::string s = "control:" + std::to_string(control);
    for (const auto& [n, port] : v) s += " " + n + ":" + std::to_string(port);
    return s;
  };
  spdlog::error("bridge {}: peer {} has other channels than this bridge (theirs: {}; ours: {}): every bridge of a "
                "vehicle must use the same channel names, ports and control_port",
                cfg.name, p.cfg.name, text(c.control_port, c.channels), text(cfg.control_port, ours));
}

}  // namespace lcmx::bridge
