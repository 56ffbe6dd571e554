// RuntimeImpl: lifetime (create, transports, shutdown), the registry of endpoints and nodes,
// announcements and events; and the public Runtime. Path selection is in matching.cpp, UDP
// receive in udp_receive.cpp, discovery glue (participants, beacons) in participants.cpp,
// RuntimeOptions::from_env in runtime_options.cpp.
#include <fnmatch.h>
#include <spdlog/cfg/env.h>
#include <spdlog/spdlog.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
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
}  // namespace

RuntimeImpl::RuntimeImpl(RuntimeOptions o)
    : options(std::move(o)), participant_id(discovery::random_participant_id()),
      host(discovery::host_id()), own_pid_namespace(discovery::pid_namespace()) {
  // Segment names: "lcmx_<host id hex>_<pid>n<pid-namespace inode hex>_<endpoint>_g<N>".
  // shm::process_tag() ("<pid>n<pidns>") keeps processes of several pid namespaces sharing
  // /dev/shm (containers) apart: equal pids, never equal names.
  own_shm_prefix = std::string(shm::kPrefix) + hex(host) + "_";
  shm_base_prefix = own_shm_prefix + shm::process_tag() + "_";
  for (const auto& glob : options.bridge_carry)
    if (glob.empty() || glob.size() > 255)
      throw Error(Errc::invalid_argument, "bridge_carry: a topic pattern must have 1..255 characters");
  carried = options.bridge_carry;
  for (const auto& glob : options.mirror_channels)
    if (glob.empty() || glob.size() > 255)
      throw Error(Errc::invalid_argument, "mirror_channels: a channel pattern must have 1..255 characters");
  if (options.reclaim_orphans) {
    // Every lcmx segment whose writer is dead (shm's liveness is exact across pid namespaces).
    const auto r = shm::reclaim_orphans();
    if (r.removed > 0) spdlog::info("lcmx: removed {} shared-memory segments of dead processes", r.removed);
  }
}

RuntimeImpl::~RuntimeImpl() {
  shutdown();
  if (rx_wake_fd >= 0) ::close(rx_wake_fd);
}

// Stock LCM programs follow LCM_DEFAULT_URL; lcmx's host-local group is discovery_url
// (LCMX_DISCOVERY_URL, or LCM's default). When the two name different groups, those programs
// are not heard and do not hear the mirror: say so rather than stay silent.
void RuntimeImpl::warn_lcm_default_url() const {
  const char* env = std::getenv("LCM_DEFAULT_URL");
  if (env == nullptr || *env == '\0') return;
  const std::string url = env;
  const auto& ours = local_group->config();
  try {
    const auto theirs = udpm::parse_url(url);
    if (theirs.address == ours.address && theirs.port == ours.port) return;
  } catch (const udpm::Error&) {
    // not a udpm:// URL lcmx reads (memq://, file://...): different from ours all the same
  }
  spdlog::warn("lcmx: LCM_DEFAULT_URL is '{}' but this participant's host-local group is {}:{} "
               "(discovery_url: LCMX_DISCOVERY_URL or LCM's default): stock LCM programs using "
               "LCM_DEFAULT_URL are not heard here; set LCMX_DISCOVERY_URL to the same group to join them",
               url, ours.address, ours.port);
}

void RuntimeImpl::start_transports() {
  auto open_group = [](const std::string& what, const std::string& url) {
    try {
      auto cfg = udpm::parse_url(url);
      // Our own looped-back packets would only be dropped in on_udp(); dropping them in the
      // kernel spares a wake-up of the receive thread per message sent (it competed for a CPU
      // with the subscribers' threads: ~15 µs per small message on 2 vCPUs).
      cfg.receive_own = false;
      return std::make_shared<udpm::Group>(udpm::Group::open(cfg));
    } catch (const udpm::Error& e) {
      const auto code = e.code() == udpm::Error::Code::invalid_config ||
                                e.code() == udpm::Error::Code::no_such_interface
                            ? Errc::invalid_argument
                            : Errc::transport;
      throw Error(code, what + " '" + url + "': " + e.what());
    }
  };
  local_group = open_group("discovery_url", options.discovery_url);
  warn_lcm_default_url();
  host_addresses = local_addresses();
  routes_checked = std::chrono::steady_clock::now();
  if (!options.vehicle_url.empty()) {  // naming an interface (RuntimeOptions::check)
    vehicle_group = open_group("vehicle_url", options.vehicle_url);
    // Our sockets hear only the groups they joined (IP_MULTICAST_ALL = 0), but liblcm's do not
    // set that: a stock LCM program bound to this port hears every group joined on its host
    // with it, the vehicle group's datagrams (beacons and messages of other hosts) included.
    if (vehicle_group->config().port == local_group->config().port)
      spdlog::warn("lcmx: vehicle_url '{}' uses the host-local group's port {}: stock LCM programs on this host "
                   "listening on that port (liblcm sockets hear every group joined on the host for their port) "
                   "will also receive the vehicle group's traffic; give the vehicle group a port of its own "
                   "(e.g. 7668)",
                   options.vehicle_url, local_group->config().port);
  }
  rx_wake_fd = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (rx_wake_fd < 0) throw Error(Errc::transport, "eventfd failed");
  rx_epoll = ::epoll_create1(EPOLL_CLOEXEC);
  if (rx_epoll < 0) throw Error(Errc::transport, "epoll_create1 failed");
  epoll_event ev{};
  ev.events = EPOLLIN;
  ev.data.fd = rx_wake_fd;
  if (::epoll_ctl(rx_epoll, EPOLL_CTL_ADD, rx_wake_fd, &ev) != 0)
    throw Error(Errc::transport, "epoll_ctl failed");
  add_udp_waiter(-1);  // the receive thread's own registration
  try {
    owner_watch = std::make_unique<shm::OwnerWatch>();
    epoll_event oev{};
    oev.events = EPOLLIN;
    oev.data.fd = owner_watch->fd();
    if (::epoll_ctl(rx_epoll, EPOLL_CTL_ADD, owner_watch->fd(), &oev) != 0)
      throw shm::Error(shm::Errc::system, "epoll_ctl failed");
  } catch (const shm::Error& e) {
    owner_watch.reset();
    spdlog::warn("lcmx: no fast death notice for publishers in other pid namespaces (their "
                 "lease applies): {}", e.what());
  }

  // One registry slot for both scopes (docs/discovery.md "Registry").
  std::shared_ptr<discovery::Registry> registry;
  try {
    discovery::RegistryOptions ro;
    ro.host_id = host;
    ro.group = local_group->config();
    registry = discovery::Registry::open(ro);
  } catch (const std::runtime_error& e) {
    throw Error(Errc::transport, e.what());
  }
  std::weak_ptr<RuntimeImpl> weak = weak_from_this();
  auto make = [&](std::int8_t scope, std::shared_ptr<udpm::Group> group) {
    discovery::Options d;
    d.shared_group = std::move(group);
    d.registry = registry;
    d.scope = scope;
    d.period = options.beacon_period;
    d.lease = options.lease;
    // Before a lease expires, the beacons queued in our sockets are read (this process may
    // have been stopped and resumed: its receive thread has not read them yet).
    d.drain_before_expiry = [weak] {
      auto self = weak.lock();
      if (!self || self->stopped.load()) return;
      std::lock_guard lock(self->recv_mu);
      self->drain_locked(true);
    };
    return std::make_unique<discovery::Discovery>(
        d,
        [weak, scope] {
          auto self = weak.lock();
          return self ? self->build_beacon(scope) : lcmx_msgs::beacon_t{};
        },
        [weak, scope](discovery::Change c, const discovery::Participant& p) {
          if (auto self = weak.lock()) self->on_participant(scope, c, p);
        });
  };
  disco = make(lcmx_msgs::beacon_t::SCOPE_HOST, local_group);
  if (vehicle_group) disco_vehicle = make(lcmx_msgs::beacon_t::SCOPE_VEHICLE, vehicle_group);
  rx_thread = std::thread([this] { receive_loop(); });
}

bool RuntimeImpl::mirrored(const std::string& channel) const {
  if (options.mirror) return true;
  for (const auto& glob : options.mirror_channels)
    if (::fnmatch(glob.c_str(), channel.c_str(), 0) == 0) return true;
  return false;
}

TopicClass RuntimeImpl::class_of(const std::string& channel) const {
  if (auto it = options.topic_class.find(channel); it != options.topic_class.end()) return it->second;
  std::lock_guard lock(carried_mu);
  for (const auto& glob : carried)
    if (::fnmatch(glob.c_str(), channel.c_str(), 0) == 0) return TopicClass::large;
  return TopicClass::automatic;
}

void RuntimeImpl::shutdown() {
  if (stopped.exchange(true)) return;
  if (rx_thread.joinable()) {
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(rx_wake_fd, &one, sizeof one);
    rx_thread.join();
  }
  {
    std::lock_guard lock(rx_epoll_mu);
    if (rx_epoll >= 0) ::close(rx_epoll), rx_epoll = -1;
  }
  // rx_wake_fd stays open until the destructor: an executor may still drain until its node
  // stops (the beacons it would forward are dropped once stopped).
  if (disco_vehicle) disco_vehicle->stop();  // goodbyes
  if (disco) disco->stop();
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
  ++revision;
  if (disco) disco->announce_now();
  if (disco_vehicle) disco_vehicle->announce_now();
}

void RuntimeImpl::emit(std::vector<Event> events) {
  if (events.empty()) return;
  std::function<void(const Event&)> cb;
  {
    std::lock_guard lock(event_mu);
    cb = on_event;
  }
  std::vector<std::shared_ptr<const std::function<void(const Event&)>>> taps;
  {
    std::lock_guard lock(event_mu);
    for (const auto& [id, t] : event_taps) taps.push_back(t);
  }
  for (const auto& e : events) {
    for (const auto& t : taps) (*t)(e);
    if (e.kind == Event::Kind::type_mismatch || e.kind == Event::Kind::error)
      spdlog::error("lcmx: {}", e.message);
    else
      spdlog::debug("lcmx: {}", e.message);
    // The user's callback runs on lcmx's threads: what it throws must not end them.
    try {
      if (cb) cb(e);
    } catch (const std::exception& x) {
      spdlog::error("lcmx: the on_event callback threw: {}", x.what());
    } catch (...) {
      spdlog::error("lcmx: the on_event callback threw");
    }
  }
}

bool RuntimeImpl::endpoint_announced(std::uint64_t participant, std::uint64_t endpoint) {
  std::lock_guard lock(mu);
  const auto id = static_cast<std::int64_t>(participant);
  for (const auto* table : {&remotes, &vehicle_remotes, &neighbour_remotes}) {
    auto it = table->find(id);
    if (it == table->end()) continue;
    for (const auto& e : it->second.endpoints)
      if (static_cast<std::uint64_t>(e.id) == endpoint) return true;
  }
  return false;
}

std::uint64_t RuntimeImpl::add_event_tap(std::function<void(const Event&)> tap) {
  std::lock_guard lock(event_mu);
  const auto id = ++last_tap;
  event_taps[id] = std::make_shared<const std::function<void(const Event&)>>(std::move(tap));
  return id;
}

std::uint64_t RuntimeImpl::add_housekeeping(std::function<void()> job) {
  std::lock_guard lock(event_mu);
  const auto id = ++last_tap;
  housekeeping[id] = std::make_shared<const std::function<void()>>(std::move(job));
  return id;
}

void RuntimeImpl::remove_housekeeping(std::uint64_t id) {
  std::lock_guard lock(event_mu);
  housekeeping.erase(id);
}

void RuntimeImpl::run_housekeeping() {
  std::vector<std::shared_ptr<const std::function<void()>>> jobs;
  {
    std::lock_guard lock(event_mu);
    for (const auto& [id, j] : housekeeping) jobs.push_back(j);
  }
  for (const auto& j : jobs) {
    try {
      (*j)();
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: housekeeping failed: {}", e.what());
    }
  }
}

void RuntimeImpl::remove_event_tap(std::uint64_t id) {
  std::lock_guard lock(event_mu);
  event_taps.erase(id);
}

void RuntimeImpl::add_node(const std::shared_ptr<NodeImpl>& node) {
  {
    std::lock_guard lock(mu);
    std::erase_if(nodes, [](const auto& w) { return w.expired(); });
    nodes.push_back(node);
  }
  changed();
}

void RuntimeImpl::add_publisher(PublisherImpl* pub) {
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    expand_locked(pub->channel(), events);  // before: the loop below matches the new subscribers
    pubs[pub->id] = pub;
    for (auto& [id, sub] : subs) match_local_locked(*pub, *sub, events);
    count_remote_locked(*pub, events);
  }
  changed();
  emit(std::move(events));
}

void RuntimeImpl::remove_publisher(PublisherImpl* pub) {
  std::vector<Event> events;
  {
    std::lock_guard lock(mu);
    pubs.erase(pub->id);
    rates.erase(pub->id * 2), rates.erase(pub->id * 2 + 1);
    for (auto& [id, sub] : subs) {
      auto& st = *sub->state;
      std::lock_guard l2(st.mu);
      const auto n = std::erase_if(st.matches, [&](const auto& m) {
        return m->path == Path::intra && m->publisher_endpoint == pub->id;
      });
      if (n) {
        ++st.version;
        st.matched_cv.notify_all();
        events.push_back({Event::Kind::publisher_unmatched, sub->channel(),
                          fmt::format("'{}': in-process publisher {} is gone", sub->channel(), pub->id)});
      }
    }
  }
  changed();
  emit(std::move(events));
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
    rates.erase(sub->id * 2), rates.erase(sub->id * 2 + 1);
  }
  changed();
}

}  // namespace detail

// ---------------------------------------------------------------- Runtime

Runtime Runtime::create(RuntimeOptions options) {
  static std::once_flag log_env;
  std::call_once(log_env, [] { spdlog::cfg::load_env_levels(); });
  options.check();
  if (detail::g_runtime_alive.exchange(true))
    throw Error(Errc::already_exists, "a lcmx::Runtime already exists in this process");
  try {
    auto impl = std::make_shared<detail::RuntimeImpl>(std::move(options));
    impl->start_transports();
    return Runtime(std::move(impl));
  } catch (const std::invalid_argument& e) {  // discovery::host_id(): a bad LCMX_HOST_ID
    detail::g_runtime_alive.store(false);
    throw Error(Errc::invalid_argument, e.what());
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
