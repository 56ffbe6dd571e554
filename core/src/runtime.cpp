#include <spdlog/cfg/env.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <cstdlib>
#include <sstream>

#include "internal.hpp"
#include "lcmx/discovery/identity.hpp"

namespace lcmx {
namespace detail {
namespace {
std::atomic<bool> g_runtime_alive{false};

std::string hex(std::uint64_t v) {
  std::ostringstream s;
  s << std::hex << v;
  return s.str();
}

bool compatible(std::int64_t a, std::int64_t b) { return a == 0 || b == 0 || a == b; }
}  // namespace

RuntimeImpl::RuntimeImpl(RuntimeOptions o)
    : options(std::move(o)), participant_id(discovery::random_participant_id()),
      host(discovery::host_id()) {
  shm_base_prefix = std::string(shm::kPrefix) + hex(host) + "_" + std::to_string(::getpid()) + "_";
  if (options.reclaim_orphans) {
    const auto r = shm::reclaim_orphans();
    if (r.removed > 0) spdlog::info("lcmx: removed {} shared-memory segments of dead processes", r.removed);
  }
}

RuntimeImpl::~RuntimeImpl() { shutdown(); }

void RuntimeImpl::start_discovery() {
  discovery::Options d;
  try {
    d.group = udpm::parse_url(options.discovery_url);
  } catch (const std::exception& e) {
    throw Error(Errc::invalid_argument, std::string("discovery_url: ") + e.what());
  }
  d.period = options.beacon_period;
  d.lease = options.lease;
  std::weak_ptr<RuntimeImpl> weak = weak_from_this();
  try {
    disco = std::make_unique<discovery::Discovery>(
        d,
        [weak] {
          auto self = weak.lock();
          return self ? self->build_beacon() : lcmx_msgs::beacon_t{};
        },
        [weak](discovery::Change c, const discovery::Participant& p) {
          if (auto self = weak.lock()) self->on_participant(c, p);
        });
  } catch (const std::exception& e) {
    throw Error(Errc::transport, std::string("cannot start discovery on ") +
                                     options.discovery_url + ": " + e.what());
  }
}

void RuntimeImpl::shutdown() {
  if (stopped.exchange(true)) return;
  if (disco) disco->stop();  // goodbye
  std::vector<std::shared_ptr<NodeImpl>> live;
  {
    std::lock_guard lock(mu);
    for (auto& w : nodes)
      if (auto n = w.lock()) live.push_back(std::move(n));
  }
  for (auto& n : live) n->stop();
  g_runtime_alive.store(false);
}

void RuntimeImpl::changed() {
  {
    std::lock_guard lock(mu);
    ++revision;
  }
  if (disco) disco->announce_now();
}

void RuntimeImpl::emit(std::vector<Event> events) {
  if (events.empty()) return;
  std::function<void(const Event&)> cb;
  {
    std::lock_guard lock(event_mu);
    cb = on_event;
  }
  for (const auto& e : events) {
    if (e.kind == Event::Kind::type_mismatch)
      spdlog::error("lcmx: {}", e.message);
    else
      spdlog::debug("lcmx: {}", e.message);
    if (cb) cb(e);
  }
}

void RuntimeImpl::add_node(const std::shared_ptr<NodeImpl>& node) {
  {
    std::lock_guard lock(mu);
    std::erase_if(nodes, [](const auto& w) { return w.expired(); });
    nodes.push_back(node);
  }
  changed();
}

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
  std::vector<std::pair<const lcmx_msgs::beacon_t*, const lcmx_msgs::endpoint_t*>> candidates;
  for (const auto& [pid, b] : remotes) {
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
      if (e.shm_segment.empty()) continue;
      wanted.insert({static_cast<std::uint64_t>(b.participant_id), static_cast<std::uint64_t>(e.id)});
      candidates.push_back({&b, &e});
    }
  }
  std::lock_guard lock(st.mu);
  const auto before = st.matches.size();
  std::vector<std::shared_ptr<Match>> removed;
  std::erase_if(st.matches, [&](const std::shared_ptr<Match>& m) {
    if (m->path != Path::shm) return false;
    if (wanted.count({m->publisher_participant, m->publisher_endpoint})) return false;
    removed.push_back(m);
    return true;
  });
  for (const auto& [b, e] : candidates) {
    const auto key = std::make_pair(static_cast<std::uint64_t>(b->participant_id),
                                    static_cast<std::uint64_t>(e->id));
    const bool have = std::any_of(st.matches.begin(), st.matches.end(), [&](const auto& m) {
      return m->publisher_participant == key.first && m->publisher_endpoint == key.second;
    });
    if (have) continue;
    auto m = std::make_shared<Match>();
    m->publisher_participant = key.first;
    m->publisher_endpoint = key.second;
    m->path = Path::shm;
    try {
      m->reader = std::make_unique<shm::Reader>(shm::Reader::open(e->shm_segment));
    } catch (const shm::Error& err) {
      // The publisher may be gone or be creating a new generation: retried on its next beacon.
      spdlog::debug("lcmx: channel '{}': cannot open {} yet: {}", sub.channel(), e->shm_segment,
                    err.what());
      continue;
    }
    st.matches.push_back(m);
    events.push_back({Event::Kind::publisher_matched, sub.channel(),
                      "channel '" + sub.channel() + "': node '" + st.node_name +
                          "' receives from process " + b->process_name + " pid " +
                          std::to_string(b->pid) + " node '" + e->node + "' (shm)"});
  }
  for (auto& m : removed)
    events.push_back({Event::Kind::publisher_unmatched, sub.channel(),
                      "channel '" + sub.channel() + "': node '" + st.node_name +
                          "' lost a shm publisher (participant " +
                          std::to_string(m->publisher_participant) + ")"});
  if (st.matches.size() != before || !removed.empty()) {
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
  std::size_t n = 0;
  for (const auto& [pid, b] : remotes) {
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
            static_cast<std::uint64_t>(m.publisher_endpoint) == pub.id)
          ++n;
    }
  }
  pub.set_remote_subscribers(n);
}

void RuntimeImpl::add_publisher(PublisherImpl* pub) {
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    pubs[pub->id] = pub;
    for (auto& [id, sub] : subs) match_local_locked(*pub, *sub, events);
    count_remote_locked(*pub, events);
  }
  changed();
  emit(std::move(events));
}

void RuntimeImpl::remove_publisher(PublisherImpl* pub) {
  {
    std::lock_guard lock(mu);
    pubs.erase(pub->id);
    rates.erase(pub->id);
    for (auto& [id, sub] : subs) {
      auto& st = *sub->state;
      std::lock_guard l2(st.mu);
      const auto n = std::erase_if(st.matches, [&](const auto& m) {
        return m->path == Path::intra && m->publisher_endpoint == pub->id;
      });
      if (n) {
        ++st.version;
        st.matched_cv.notify_all();
      }
    }
  }
  changed();
}

void RuntimeImpl::add_subscriber(const std::shared_ptr<SubscriberCore>& sub) {
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    subs[sub->id] = sub;
    for (auto& [id, pub] : pubs) match_local_locked(*pub, *sub, events);
    sync_remote_locked(*sub, events);
  }
  changed();
  emit(std::move(events));
}

void RuntimeImpl::remove_subscriber(const SubscriberCore* sub) {
  {
    std::lock_guard lock(mu);
    for (auto& [id, pub] : pubs) pub->remove_intra(sub);
    subs.erase(sub->id);
    rates.erase(sub->id);
  }
  changed();
}

void RuntimeImpl::on_participant(discovery::Change change, const discovery::Participant& p) {
  const auto& b = p.beacon;
  if (static_cast<std::uint64_t>(b.host_id) != host) return;  // other hosts: issue 3
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    if (change == discovery::Change::left) {
      remotes.erase(b.participant_id);
      events.push_back({Event::Kind::participant_left, "",
                        "participant " + b.process_name + " pid " + std::to_string(b.pid) + " left"});
    } else {
      if (change == discovery::Change::joined)
        events.push_back({Event::Kind::participant_joined, "",
                          "participant " + b.process_name + " pid " + std::to_string(b.pid) +
                              " joined"});
      remotes[b.participant_id] = b;
    }
    const auto before_matches = [&] {
      std::size_t n = 0;
      for (auto& [id, sub] : subs) {
        std::lock_guard l2(sub->state->mu);
        n += sub->state->matches.size();
      }
      return n;
    };
    const auto n0 = before_matches();
    for (auto& [id, sub] : subs) sync_remote_locked(*sub, events);
    for (auto& [id, pub] : pubs) count_remote_locked(*pub, events);
    if (before_matches() != n0) ++revision, announce_pending = true;
  }
  if (announce_pending.exchange(false) && disco) disco->announce_now();
  // A participant of this host that vanished without a goodbye may have left shared memory.
  if (change == discovery::Change::left && options.reclaim_orphans) {
    const auto r = shm::reclaim_orphans();
    if (r.removed > 0)
      spdlog::info("lcmx: removed {} shared-memory segments of {} pid {}", r.removed,
                   b.process_name, b.pid);
  }
  emit(std::move(events));
}

lcmx_msgs::beacon_t RuntimeImpl::build_beacon() {
  lcmx_msgs::beacon_t b;
  b.version = 1;
  b.participant_id = static_cast<std::int64_t>(participant_id);
  b.host_id = static_cast<std::int64_t>(host);
  b.pid = static_cast<std::int32_t>(::getpid());
  b.process_name = discovery::process_name();
  b.flags = 0;
  const auto now = std::chrono::steady_clock::now();
  auto rate = [&](std::uint64_t id, std::uint64_t count) {
    auto& r = rates[id];
    double hz = 0;
    if (r.when != std::chrono::steady_clock::time_point{}) {
      const double dt = std::chrono::duration<double>(now - r.when).count();
      if (dt > 0.05) hz = static_cast<double>(count - r.count) / dt;
      else return 0.0;
    }
    r.count = count;
    r.when = now;
    return hz;
  };
  std::lock_guard lock(mu);
  b.revision = revision;
  for (auto& w : nodes)
    if (auto n = w.lock()) b.nodes.push_back(n->name);
  b.num_nodes = static_cast<std::int32_t>(b.nodes.size());
  for (auto& [id, pub] : pubs) {
    lcmx_msgs::endpoint_t e{};
    e.id = static_cast<std::int64_t>(id);
    e.kind = lcmx_msgs::endpoint_t::KIND_PUBLISHER;
    e.node = pub->node->name;
    e.topic = pub->channel();
    e.type_name = pub->type.name;
    e.fingerprint = pub->type.fingerprint;
    e.shm_segment = pub->segment_name();
    e.max_message_size = static_cast<std::int64_t>(pub->options.max_message_size);
    e.messages = static_cast<std::int64_t>(pub->published());
    e.rate_hz = rate(id, pub->published());
    e.errors = pub->errors;
    e.num_errors = static_cast<std::int32_t>(e.errors.size());
    b.endpoints.push_back(std::move(e));
  }
  for (auto& [id, sub] : subs) {
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
  return b;
}

}  // namespace detail

// ---------------------------------------------------------------- RuntimeOptions

namespace {
long env_number(const char* name, long fallback, long min, long max) {
  const char* v = std::getenv(name);
  if (!v || !*v) return fallback;
  char* end = nullptr;
  errno = 0;
  const long n = std::strtol(v, &end, 10);
  if (errno || end == v || *end || n < min || n > max)
    throw Error(Errc::invalid_argument, std::string(name) + "='" + v + "': expected an integer in [" +
                                            std::to_string(min) + ", " + std::to_string(max) + "]");
  return n;
}
}  // namespace

RuntimeOptions RuntimeOptions::from_env() {
  RuntimeOptions o;
  if (const char* url = std::getenv("LCMX_DISCOVERY_URL"); url && *url) o.discovery_url = url;
  o.beacon_period = std::chrono::milliseconds(env_number("LCMX_BEACON_PERIOD_MS", o.beacon_period.count(), 10, 60000));
  o.lease = std::chrono::milliseconds(env_number("LCMX_LEASE_MS", o.lease.count(), 50, 600000));
  return o;
}

// ---------------------------------------------------------------- Runtime

Runtime Runtime::create(RuntimeOptions options) {
  static std::once_flag log_env;
  std::call_once(log_env, [] { spdlog::cfg::load_env_levels(); });
  if (options.lease <= options.beacon_period)
    throw Error(Errc::invalid_argument, "lease must be longer than beacon_period");
  if (detail::g_runtime_alive.exchange(true))
    throw Error(Errc::already_exists, "a lcmx::Runtime already exists in this process");
  try {
    auto impl = std::make_shared<detail::RuntimeImpl>(std::move(options));
    impl->start_discovery();
    return Runtime(std::move(impl));
  } catch (...) {
    detail::g_runtime_alive.store(false);
    throw;
  }
}

Runtime::~Runtime() {
  if (impl_) impl_->shutdown();
}

Node Runtime::create_node(std::string name, NodeOptions options) {
  auto n = std::make_shared<detail::NodeImpl>(impl_, std::move(name), options);
  n->start();
  impl_->add_node(n);
  return Node(std::move(n));
}

void Runtime::on_event(std::function<void(const Event&)> callback) {
  std::lock_guard lock(impl_->event_mu);
  impl_->on_event = std::move(callback);
}

std::uint64_t Runtime::participant_id() const { return impl_->participant_id; }
std::uint64_t Runtime::host_id() const { return impl_->host; }

}  // namespace lcmx
