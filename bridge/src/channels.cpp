// Data channels: the shm subscription callback that queues a message for every wanting peer
// (zero-copy from the pinned slot, or one copy when the pins are held; drop policy), and the channel threads that send the queues to the
// peers' active links and receive peers' data into this host's shared memory (sequence check,
// republishers). The queue and sequence rules: channels.hpp.
#include "engine.hpp"

#include <sched.h>

#include <algorithm>
#include <span>

#include <spdlog/spdlog.h>

namespace lcmx::bridge {

using namespace std::chrono_literals;

std::unique_ptr<zmq::socket_t> Bridge::Impl::make_data_dealer(const Peer& p, const Channel& ch, const Link& l) {
  auto s = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::dealer);
  client_options(*s, p);
  s->set(zmq::sockopt::routing_id, routing_id(cfg.name));
  s->set(zmq::sockopt::sndhwm, 2);  // our own queue holds the rest (drop policy)
  // Nothing is read from a data DEALER: whatever a peer sends back waits in TCP.
  s->set(zmq::sockopt::rcvhwm, 1);
  s->set(zmq::sockopt::maxmsgsize, std::int64_t{4096});
  s->set(zmq::sockopt::affinity, std::uint64_t{1} << ch.index);
  s->set(zmq::sockopt::tos, ch.cfg.priority << 5);
  s->connect("tcp://" + l.cfg.address + ":" + std::to_string(ch.cfg.port));
  return s;
}

// Zero-copy send (issue 15 item 1): the ZeroMQ message points into the pinned shared-memory
// slot (RawMessage::retain_zero_copy: a DetachedSample) and owns it through a heap holder that
// ZeroMQ's free callback deletes once every peer's copy (zmq_msg_copy: refcount) is sent or
// dropped, on whichever thread drops the last reference (usually the channel's ZeroMQ I/O
// thread; DetachedSample's release is thread-safe), then signals the topic's PinWatch.
// When this subscription already holds shm::Reader::kMaxDetached slots of the publisher:
//  - one peer wants the topic and its link is moving (a pin came back within kPinProgress,
//    from a send, not from a queue dropping it, and its socket took a message within
//    kPinProgress): wait for the next release, at most kPinWait, then send zero-copy.
//    Back-pressure into the shm ring instead of a copy that the queue would mostly drop: the
//    publisher never waits, and what its ring overwrites meanwhile is counted as this
//    subscription's drops. (This executor thread serves every topic of the channel: a wait
//    delays them by at most kPinWait, about one message's time on the wire.)
//  - several peers want it, the link is stalled (no pin back, or the peer took nothing, for
//    kPinProgress), or the wait timed out: copy (one copy, counted in copied_msgs). So a slow
//    link never holds more than kMaxDetached slots, never paces the other peers to its
//    speed, and never stops this bridge from serving them.
namespace {
constexpr std::chrono::milliseconds kPinWait{50};
constexpr std::chrono::milliseconds kPinProgress{100};

// Set while on_local_message pushes into the peers' queues: a message freed then was dropped
// by a queue's policy, not sent, so its release says nothing about the link moving (a stalled
// peer's queue dropping its oldest must not make the executor wait for pins).
thread_local bool t_pushing = false;

struct HeldPayload {
  RetainedBytes bytes;
  std::shared_ptr<PinWatch> watch;  // zero-copy only: told when the slot is released
};

void free_payload(void*, void* hint) {
  auto* h = static_cast<HeldPayload*>(hint);
  auto watch = std::move(h->watch);
  delete h;  // releases the pin first, so a waiter woken below finds it free
  if (watch && !t_pushing) watch->on_release();
}
}  // namespace

std::optional<RetainedBytes> Bridge::Impl::wait_for_pin(PinWatch& w, const RawMessage& m) {
  const auto now = std::chrono::steady_clock::now();
  const std::int64_t last = w.last_release_ns.load(std::memory_order_relaxed);
  if (last == 0 || now.time_since_epoch().count() - last > std::chrono::nanoseconds(kPinProgress).count())
    return std::nullopt;  // stalled (or nothing sent yet): no pin is coming back soon
  pin_waits.fetch_add(1, std::memory_order_relaxed);
  const auto deadline = now + kPinWait;
  std::unique_lock lock(w.mu);
  std::uint64_t seen = w.released;
  while (!stopping.load(std::memory_order_relaxed)) {
    if (!w.cv.wait_until(lock, deadline, [&] { return w.released != seen; })) return std::nullopt;
    seen = w.released;
    lock.unlock();
    if (auto r = m.retain_zero_copy()) return r;  // the release may be of another publisher's pin
    lock.lock();
  }
  return std::nullopt;
}

zmq::message_t Bridge::Impl::retained_payload(Served& s, const RawMessage& m, const std::size_t* targets,
                                              std::size_t n) {
  auto zc = m.retain_zero_copy();
  // Wait only for one wanting peer whose link is moving (its socket took a message within
  // kPinProgress). With several peers the pins may be held by the slowest one, and waiting
  // for it would pace the others to its speed (a slow peer must not hold back the others);
  // a stopped peer's pins sit in its queue, which only our next push drops from.
  if (!zc && n == 1) {
    const std::int64_t now = std::chrono::steady_clock::now().time_since_epoch().count();
    const std::int64_t sent = peers[targets[0]]->chans[s.channel]->last_sent_ns.load(std::memory_order_relaxed);
    if (sent != 0 && now - sent <= std::chrono::nanoseconds(kPinProgress).count()) zc = wait_for_pin(*s.pins, m);
  }
  auto held = std::make_unique<HeldPayload>();
  if (zc) {
    held->bytes = std::move(*zc);
    held->watch = s.pins;
  } else {
    held->bytes = m.retain();  // copies
  }
  (held->bytes.zero_copy ? zero_copy_msgs : copied_msgs).fetch_add(1, std::memory_order_relaxed);
  // ZeroMQ takes a non-const pointer but only reads a message it sends.
  void* data = const_cast<std::byte*>(held->bytes.data.data());
  const std::size_t size = held->bytes.data.size();
  zmq::message_t msg(data, size, free_payload, held.get());
  held.release();  // owned by the message now (zmq_msg_init_data succeeded)
  return msg;
}

void Bridge::Impl::on_local_message(Served& s, const RawMessage& m) {
  thread_local int niced = -1;
  const int want_nice = channels[s.channel]->nice;
  if (niced != want_nice) {
    set_thread_nice(want_nice);
    niced = want_nice;
  }
  // One class per message, the publisher's (docs/bridge.md "One class per message"): an lcmx
  // publisher stamps each message it writes into shared memory with the class it routed it by.
  // A large one it leaves to the bridges to reach other hosts: forwarded. A small one it sends
  // over UDP itself where other hosts want it: not forwarded, whatever this bridge's own
  // udp_limit or carry say (forwarding it too reached those hosts twice; a publisher whose
  // limit is lower than ours had its first large messages forwarded by nobody). Only a message
  // without a stamp (not from an lcmx publisher's shared memory) is judged here, as before:
  // large when its topic is, or over udp_limit.
  const std::optional<bool> said = m.published_large();
  if (said ? !*said : !s.large.load(std::memory_order_relaxed) && m.data.size() <= rt_options.udp_limit) {
    if (said && !s.small_said_logged && (m.data.size() > rt_options.udp_limit || cfg.carried(s.topic))) {
      s.small_said_logged = true;  // once per topic: both sides' settings stay as they are
      if (m.data.size() > rt_options.udp_limit)
        spdlog::warn("bridge {}: topic {}: a {}-byte message over this bridge's udp_limit ({}) that its publisher "
                     "classes small (its LCMX_UDP_LIMIT is higher, or LCMX_SMALL_TOPICS names it): not bridged, it "
                     "reaches other hosts over LCM UDP (the publisher's class wins)",
                     cfg.name, printable(s.topic), m.data.size(), rt_options.udp_limit);
      else
        spdlog::warn("bridge {}: topic {} matches carry, but its publisher classes small what it publishes "
                     "(LCMX_SMALL_TOPICS names it?): not bridged, it reaches other hosts over LCM UDP (the "
                     "publisher's class wins)",
                     cfg.name, printable(s.topic));
    }
    return;  // small: UDP carries it
  }
  if (!s.large.exchange(true)) {
    {
      std::lock_guard lock(view_mu);
      sticky_large.insert(s.topic);
    }
    if (said)
      spdlog::info("bridge {}: topic {} is large (its publisher says so, at a {}-byte message): bridged from now on",
                   cfg.name, printable(s.topic), m.data.size());
    else
      spdlog::info("bridge {}: topic {} is large ({} bytes > udp_limit {}): bridged from now on", cfg.name,
                   printable(s.topic), m.data.size(), rt_options.udp_limit);
  }
  std::size_t targets[kMaxPeers];  // load_config() allows at most kMaxPeers peers
  std::size_t n = 0;
  {
    std::lock_guard lock(s.mu);
    for (auto p : s.peers)
      if (n < std::size(targets)) targets[n++] = p;
  }
  if (n == 0) return;
  zmq::message_t payload = retained_payload(s, m, targets, n);
  Channel& ch = *channels[s.channel];
  struct Pushing {
    Pushing() { t_pushing = true; }
    ~Pushing() { t_pushing = false; }
  } pushing;
  bool queued = false;
  for (std::size_t i = 0; i < n; ++i) {
    Peer& p = *peers[targets[i]];
    PeerChannel& pc = *p.chans[s.channel];
    Outgoing out{s.topic_ptr, zmq::message_t(), s.keep.load(std::memory_order_relaxed)};
    out.payload.copy(payload);  // zmq_msg_copy: shares the buffer (refcount), no byte copy
    std::lock_guard lock(pc.mu);
    // Nothing queued before it: send it from here, saving the channel thread's wake-up (~20 µs
    // on a 2-vCPU host). The channel thread may hold sock_mu (flushing, reconnecting): then
    // queue it, and its flush, which loops until the queue is empty, sends it next.
    if (pc.queue.empty()) {
      std::unique_lock sock(pc.sock_mu, std::try_to_lock);
      if (sock.owns_lock() && pc.dealer && send_now(ch, p, pc, out)) {
        sent_from_callback.fetch_add(1, std::memory_order_relaxed);
        continue;
      }
    }
    if (datapath::push_bounded(pc.queue, std::move(out), ch.cfg.hwm, ch.cfg.drop))
      pc.drops.fetch_add(1, std::memory_order_relaxed);
    pc.queued.store(static_cast<std::int32_t>(pc.queue.size()), std::memory_order_relaxed);
    queued = true;
  }
  payload.rebuild();  // our reference goes while t_pushing (a message every queue refused)
  if (queued) ch.wake->ring();
}

void Bridge::Impl::channel_loop(Channel& ch) {
  set_thread_nice(ch.nice);
  std::vector<zmq::pollitem_t> items;
  Clock::time_point held_due = Clock::time_point::max();  // expire_held
  while (!stopping.load()) {
    // Follow the active links. The socket of the link left is kept, not closed: it still
    // sends what it was handed (ZeroMQ's pipe, ZMQ_SNDHWM 2, and the message being written),
    // so a planned switch loses nothing; the receiver orders the two sockets' messages
    // (datapath::RxOrder). On a dead link its pipe goes with the connection (ZMQ_IMMEDIATE).
    for (auto& p : peers) {
      PeerChannel& pc = *p->chans[ch.index];
      const int want = p->active.load();
      std::lock_guard sock(pc.sock_mu);
      if (want >= 0 && want != pc.connected_link) {
        try {
          auto& d = pc.dealers[static_cast<std::size_t>(want)];
          if (!d) d = make_data_dealer(*p, ch, *p->links[static_cast<std::size_t>(want)]);
          pc.dealer = d.get();
          pc.connected_link = want;
        } catch (const zmq::error_t& e) {
          spdlog::error("bridge {}: channel {}: cannot connect to {}: {}", cfg.name, ch.cfg.name, p->cfg.name, e.what());
        }
      }
    }
    items.clear();
    items.push_back({ch.router->handle(), 0, ZMQ_POLLIN, 0});
    items.push_back({nullptr, ch.wake->fd(), ZMQ_POLLIN, 0});
    for (auto& p : peers) {
      PeerChannel& pc = *p->chans[ch.index];
      if (pc.dealer && pc.queued.load(std::memory_order_relaxed) > 0) {
        items.push_back({pc.dealer->handle(), 0, ZMQ_POLLOUT, 0});  // see PeerChannel::sock_mu
      }
    }
    // Wake for the earliest hold that falls due (a gap given up on), at the latest in 100 ms.
    auto timeout = std::chrono::milliseconds(100);
    if (held_due != Clock::time_point::max()) {
      const auto left = std::chrono::ceil<std::chrono::milliseconds>(held_due - Clock::now());
      timeout = std::clamp(left, std::chrono::milliseconds(0), timeout);
    }
    try {
      zmq::poll(items.data(), items.size(), timeout);
    } catch (const zmq::error_t& e) {
      if (e.num() == ETERM) break;
      continue;
    }
    if (items[1].revents & ZMQ_POLLIN) ch.wake->drain();
    if (items[0].revents & ZMQ_POLLIN) receive_data(ch);
    held_due = expire_held(ch, Clock::now());
    for (auto& p : peers) flush(ch, *p);
  }
}

void Bridge::Impl::flush(Channel& ch, Peer& p) {
  PeerChannel& pc = *p.chans[ch.index];
  {
    std::lock_guard sock(pc.sock_mu);  // held from pop to send: a direct send cannot overtake
    if (!pc.dealer) return;
    for (;;) {
      Outgoing out;
      {
        std::lock_guard lock(pc.mu);
        if (pc.queue.empty()) break;
        out = std::move(pc.queue.front());
        pc.queue.pop_front();
        pc.queued.store(static_cast<std::int32_t>(pc.queue.size()), std::memory_order_relaxed);
      }
      if (!send_now(ch, p, pc, out)) {  // would block: put it back at the front, try again when writable
        std::lock_guard lock(pc.mu);
        pc.queue.push_front(std::move(out));
        pc.queued.store(static_cast<std::int32_t>(pc.queue.size()), std::memory_order_relaxed);
        break;
      }
      sent_from_queue.fetch_add(1, std::memory_order_relaxed);
    }
  }
  const auto d = pc.drops.load(std::memory_order_relaxed);
  if (d != pc.drops_logged && pc.drop_log.allow()) {
    spdlog::warn("bridge {}: {} message(s) to {} dropped on channel {} (queue full: hwm {}, drop {}); {} in total",
                 cfg.name, d - pc.drops_logged, p.cfg.name, ch.cfg.name, ch.cfg.hwm,
                 ch.cfg.drop == DropPolicy::oldest ? "oldest" : "newest", d);
    pc.drops_logged = d;
  }
}

bool Bridge::Impl::send_now(Channel& ch, Peer& p, PeerChannel& pc, Outgoing& out) {
  unsigned char hdr[wire::kDataHeader];
  wire::encode_header({instance, pc.seq + 1, out.keep}, hdr);
  const std::size_t bytes = out.topic->size() + out.payload.size();
  try {
    // All parts of a message are queued together once the first is accepted.
    // A socket learns that its I/O thread has taken earlier messages (ZMQ_SNDHWM is 2) only
    // when it processes its commands, which send() does at most every ~1 ms; ZMQ_EVENTS
    // processes them at once. Without it, one message in four of a 1 MB request/reply
    // exchange went through the queue and the forwarding thread's wake-up.
    const auto first = zmq::send_flags::sndmore | zmq::send_flags::dontwait;
    if (!pc.dealer->send(zmq::buffer(*out.topic), first) &&
        ((pc.dealer->get(zmq::sockopt::events) & ZMQ_POLLOUT) == 0 || !pc.dealer->send(zmq::buffer(*out.topic), first)))
      return false;
    pc.dealer->send(zmq::buffer(hdr, sizeof hdr), zmq::send_flags::sndmore);
    pc.dealer->send(out.payload, zmq::send_flags::none);
  } catch (const zmq::error_t& e) {
    spdlog::warn("bridge {}: channel {}: send to {} failed: {}", cfg.name, ch.cfg.name, p.cfg.name, e.what());
    return false;
  }
  ++pc.seq;
  pc.last_sent_ns.store(std::chrono::steady_clock::now().time_since_epoch().count(), std::memory_order_relaxed);
  pc.sent_msgs.fetch_add(1, std::memory_order_relaxed);
  pc.sent_bytes.fetch_add(bytes, std::memory_order_relaxed);
  if (pc.connected_link >= 0)
    p.links[static_cast<std::size_t>(pc.connected_link)]->bytes_sent.fetch_add(bytes, std::memory_order_relaxed);
  return true;
}

void Bridge::Impl::receive_data(Channel& ch) {
  for (std::size_t n = 0; n < kRecvBatch; ++n) {
    zmq::message_t parts[4];
    std::size_t count = 0;
    bool got = false, extra = false;
    for (;;) {
      zmq::message_t m;
      std::optional<std::size_t> r;
      try {
        r = ch.router->recv(m, count == 0 ? zmq::recv_flags::dontwait : zmq::recv_flags::none);
      } catch (const zmq::error_t&) {
        return;
      }
      if (!r) break;
      got = true;
      const bool more = m.more();
      if (count < 4) parts[count] = std::move(m);
      else extra = true;
      ++count;
      if (!more) break;
    }
    if (!got) return;
    if (count != 4 || extra) {
      count_bad("channel " + ch.cfg.name + ": " + std::to_string(count) + " frames (expected 4)");
      continue;
    }
    // The front door: sizes first (nothing is copied out of a frame before its size is
    // checked), then the sender's name against its connection's, then the contents.
    const std::string_view id_view = routing_name(parts[0].to_string_view());
    auto it = id_view.size() <= 32 ? peer_by_name.find(std::string(id_view)) : peer_by_name.end();
    if (it == peer_by_name.end()) {
      count_bad("channel " + ch.cfg.name + ": data from unknown bridge '" + printable(parts[0].to_string_view(), 40) +
                "'");
      continue;
    }
    const std::string& id = it->first;
    // The routing id names the sender; the ZAP handler named the connection (by its address,
    // and with CURVE its key): they must agree, or a peer (or anyone) could publish into this
    // host's shared memory in another peer's name.
    if (!authentic(parts[3], id)) {
      count_bad("channel " + ch.cfg.name + ": data from " + user_of(parts[3]) + "'s connection claiming to be " + id);
      continue;
    }
    Peer& p = *peers[it->second];
    if (parts[1].size() > wire::kMaxTopic || parts[2].size() != wire::kDataHeader ||
        !wire::valid_topic(parts[1].to_string_view())) {
      count_bad("channel " + ch.cfg.name + ": bad topic or header from " + id);
      continue;
    }
    const auto h = wire::decode_header(static_cast<const unsigned char*>(parts[2].data()));
    PeerChannel& pc = *p.chans[ch.index];
    const std::size_t bytes = parts[1].size() + parts[3].size();
    const int link = link_of(p, peer_address(parts[3]));
    if (link >= 0) p.links[static_cast<std::size_t>(link)]->bytes_received.fetch_add(bytes, std::memory_order_relaxed);
    // In order, once (datapath::RxOrder): a message that overtook what another link of the
    // peer still carries waits for it. A peer's keep sizes a ring of this host: at most this
    // channel's max_keep (docs/bridge.md "Trust").
    Incoming in{parts[1].to_string(), std::move(parts[3]),
                static_cast<std::uint32_t>(std::min<std::uint64_t>(h.keep, ch.cfg.max_keep))};
    datapath::RxOrder<Incoming>::Out out;
    pc.rx.push(h, parts[0].to_string_view(), link, std::move(in), Clock::now(), out);
    deliver_received(ch, pc, out);
  }
}

void Bridge::Impl::deliver_received(Channel& ch, PeerChannel& pc, datapath::RxOrder<Incoming>::Out& out) {
  if (out.lost > 0) pc.lost.fetch_add(out.lost, std::memory_order_relaxed);
  if (out.stale > 0) {
    // Late data of a link given up on (its gap is counted in `lost`), or a replay: not
    // delivered, never twice nor out of order.
    pc.stale += out.stale;
    spdlog::debug("bridge {}: channel {}: {} message(s) not above the last delivered one dropped ({} so far)", cfg.name,
                  ch.cfg.name, out.stale, pc.stale);
  }
  for (auto& m : out.deliver) {
    pc.recv_msgs.fetch_add(1, std::memory_order_relaxed);
    pc.recv_bytes.fetch_add(m.topic.size() + m.payload.size(), std::memory_order_relaxed);
    republish(m.topic, m.payload, m.keep);
  }
}

Clock::time_point Bridge::Impl::expire_held(Channel& ch, Clock::time_point now) {
  Clock::time_point due = Clock::time_point::max();
  for (auto& p : peers) {
    PeerChannel& pc = *p->chans[ch.index];
    if (!pc.rx.holding()) continue;
    // The gap would come over the link of the last delivered message: when this bridge sees
    // that link down (its own heartbeats unanswered), nothing more comes over it.
    const int l = pc.rx.last_link();
    const bool down = l >= 0 && !p->links[static_cast<std::size_t>(l)]->up_flag.load(std::memory_order_relaxed);
    datapath::RxOrder<Incoming>::Out out;
    pc.rx.expire(now, down, out);
    deliver_received(ch, pc, out);
    if (pc.rx.holding()) due = std::min(due, pc.rx.due());
  }
  return due;
}

// Channel threads: into this host's shared memory.
// `keep`: the topic's keep last N at its origin, from the data header: it decides the
// republisher's (remade when it differs: the origin's publishers changed).
void Bridge::Impl::republish(const std::string& topic, const zmq::message_t& payload, std::uint32_t keep) {
  std::shared_ptr<Republisher> r;
  {
    std::lock_guard lock(repub_mu);
    auto it = repubs.find(topic);
    if (it != repubs.end() && it->second->history == keep) r = it->second;
  }
  if (!r) {
    {
      std::lock_guard lock(view_mu);
      if (!demand.count(topic)) return;  // nobody here wants it (any more)
    }
    r = ensure_republisher(topic, keep, true);
    if (!r) return;
  }
  r->touch();
  try {
    r->pub.publish(std::span<const std::byte>(static_cast<const std::byte*>(payload.data()), payload.size()));
  } catch (const std::exception& e) {
    spdlog::warn("bridge {}: republishing {} failed: {}", cfg.name, printable(topic), e.what());
    return;
  }
  // The commit woke every subscriber of this host at once. Subscribers woken onto this
  // thread's CPU should all run their callbacks before this thread carries on (its next
  // receive, flush, poll): without this, the scheduler (EEVDF) often picks this thread again
  // between the first and the second subscriber, adding its remaining work (~15 µs) to
  // their callback-time difference. With nothing else runnable here it returns at once.
  ::sched_yield();
}

std::shared_ptr<Bridge::Impl::Republisher> Bridge::Impl::ensure_republisher(const std::string& topic,
                                                                           std::uint32_t history,
                                                                           bool remake_for_history) {
  wire::Control::TopicType type;
  {
    std::lock_guard lock(view_mu);
    type = type_of_locked(topic);
  }
  std::shared_ptr<Republisher> old;  // destroyed outside the lock
  std::lock_guard lock(repub_mu);
  auto& slot = repubs[topic];
  if (slot && ((remake_for_history && slot->history != history) || slot->type != type)) {
    if (slot->type != type)
      spdlog::info("bridge {}: {} is now of type {} at its origin (was {})", cfg.name, printable(topic),
                   type.name.empty() ? "raw" : type.name, slot->type.name.empty() ? "raw" : slot->type.name);
    if (!remake_for_history) history = slot->history;
    old = std::move(slot);
  }
  if (!slot) {
    try {
      auto r = std::make_shared<Republisher>();
      PublisherOptions po;
      po.history = history;  // a late subscriber here gets the origin's last N from our ring
      // The origin's type, so tools here show it and a subscriber of another type is told.
      r->pub = type.name.empty() ? repub_node->advertise_raw(topic, po)
                                 : repub_node->advertise_raw(topic, type.name, type.fingerprint, po);
      r->history = po.history;
      r->type = type;
      r->touch();
      slot = std::move(r);
    } catch (const std::exception& e) {
      spdlog::warn("bridge {}: cannot republish {}: {}", cfg.name, printable(topic), e.what());
      repubs.erase(topic);
      return nullptr;
    }
  }
  return slot;
}

}  // namespace lcmx::bridge
