// RuntimeImpl: lifetime (create, transports, shutdown) and the wiring of its components
// (runtime_impl.hpp); the public Runtime. Discovery glue (participants, beacons) is in
// participants.cpp, RuntimeOptions::from_env in runtime_options.cpp.
#include <spdlog/cfg/env.h>
#include <spdlog/spdlog.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/stat.h>
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

// What tells a changed key file: a rename over it (new inode), a write (size, mtime).
RuntimeImpl::KeyWatch::stat_sig key_file_sig(const std::string& file) {
  struct stat st {};
  if (::stat(file.c_str(), &st) != 0) return {};
  return {static_cast<unsigned long>(st.st_dev), static_cast<unsigned long>(st.st_ino),
          static_cast<long long>(st.st_size),
          static_cast<long long>(st.st_mtim.tv_sec) * 1000000000LL + st.st_mtim.tv_nsec};
}

// "keyed (authenticated, key 1a2b3c4d; also accepts 5e6f7a8b)" or "unkeyed".
std::string keys_text(const udpm::GroupKeys* k) {
  if (!k) return "unkeyed";
  char id[16];
  std::string s = std::string("keyed (") + (k->encrypt ? "encrypted" : "authenticated");
  std::snprintf(id, sizeof id, "%08x", k->keys[0].id);
  s += ", sealing with key " + std::string(id);
  for (std::size_t i = 1; i < k->keys.size(); ++i) {
    std::snprintf(id, sizeof id, "%08x", k->keys[i].id);
    s += ", also accepting " + std::string(id);
  }
  return s + ")";
}
}  // namespace

RuntimeImpl::RuntimeImpl(RuntimeOptions o)
    : options(std::move(o)), participant_id(discovery::random_participant_id()),
      host(discovery::host_id()), own_pid_namespace(discovery::pid_namespace()),
      policy(options), deaths(own_pid_namespace), replays(options.lease),
      pairs(Pairs::Context{options, participant_id, peers, policy, deaths, replays}) {
  // Segment names: "lcmx_<host id hex>_<pid>n<pid-namespace inode hex>_<endpoint>_g<N>".
  // shm::process_tag() ("<pid>n<pidns>") keeps processes of several pid namespaces sharing
  // /dev/shm (containers) apart: equal pids, never equal names.
  own_shm_prefix = std::string(shm::kPrefix) + hex(host) + "_";
  shm_base_prefix = own_shm_prefix + shm::process_tag() + "_";
}

RuntimeImpl::~RuntimeImpl() { shutdown(); }

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
  auto open_group = [this](const std::string& what, const std::string& url) {
    const bool vehicle = what == "vehicle_url";
    auto& watch = key_watch_[vehicle ? 1 : 0];
    watch.file = vehicle ? options.vehicle_key : options.host_key;
    watch.seen = watch.file.empty() ? KeyWatch::stat_sig{} : key_file_sig(watch.file);
    auto cfg = options.group_config(vehicle);  // throws Error(invalid_argument) naming a bad key file
    if (cfg.keys)
      spdlog::info("lcmx: the {} group {} is {}", vehicle ? "vehicle" : "host-local", url, keys_text(cfg.keys.get()));
    try {
      // Our own looped-back packets would only be dropped by the front door; dropping them in
      // the kernel spares a wake-up of the receive thread per message sent (it competed for a
      // CPU with the subscribers' threads: ~15 µs per small message on 2 vCPUs).
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
  if (options.reclaim_orphans && registry->created()) {
    // The first lcmx process of this host (and group): every lcmx segment whose writer is dead
    // goes (shm's liveness is exact across pid namespaces). Not at every start: a scan of
    // /dev/shm per process made a host's start quadratic (issue 33: 500 processes, 10,000
    // segments); while the registry lives, its speaker reclaims a dead participant's
    // segments by name (discovery/src/registry.cpp).
    const auto r = shm::reclaim_orphans();
    if (r.removed > 0) spdlog::info("lcmx: removed {} shared-memory segments of dead processes", r.removed);
  }
  std::weak_ptr<RuntimeImpl> weak = weak_from_this();
  front_door = std::make_unique<FrontDoor>(FrontDoor::Context{
      local_group, vehicle_group, peers, pairs,
      [this](bool vehicle, const udpm::Message& m) {
        auto& d = vehicle ? disco_vehicle_ : disco_;
        if (d) d->deliver(m);
      },
      [this](Pairs::Outcome o) { settle(std::move(o)); },
      [this] { every_second(); },
      deaths.fd(),
      [this] { on_death_fd(); },
      [this] { return vehicle_listening.load(); }});

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
      if (!self || self->stopped_.load() || !self->front_door) return;
      self->front_door->drain(true);
    };
    if (scope == lcmx_msgs::beacon_t::SCOPE_VEHICLE)
      d.on_listening = [weak](bool listening) {
        auto self = weak.lock();
        if (!self) return;
        self->vehicle_listening.store(listening);
        if (self->front_door) self->front_door->filters_changed();
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
  disco_ = make(lcmx_msgs::beacon_t::SCOPE_HOST, local_group);
  if (vehicle_group) disco_vehicle_ = make(lcmx_msgs::beacon_t::SCOPE_VEHICLE, vehicle_group);
  front_door->start();
}

void RuntimeImpl::shutdown() {
  if (stopped_.exchange(true)) return;
  if (front_door) front_door->stop();
  // Executors may still drain until their node stops (the beacons they would forward are
  // dropped once stopped).
  if (disco_vehicle_) disco_vehicle_->stop();  // goodbyes
  if (disco_) disco_->stop();
  for (auto& n : pairs.live_nodes()) n->stop();
  g_runtime_alive.store(false);
}

void RuntimeImpl::changed() {
  ++revision_;
  if (disco_) disco_->announce_now();
  if (disco_vehicle_) disco_vehicle_->announce_now();
}

void RuntimeImpl::settle(Pairs::Outcome outcome) {
  if (outcome.announce) {
    changed();
    if (front_door) front_door->filters_changed();  // (our endpoints or matches: what we read)
  }
  events.emit(std::move(outcome.events));
}

// Once a second on the receive thread, no lock held: housekeeping jobs (services), stock LCM
// senders silent for a minute forgotten.
void RuntimeImpl::every_second() {
  watch_keys();
  events.run_housekeeping();
  replays.tick();  // replays that waited for their publisher's budget
  replays.send(pairs, participant_id, *local_group, vehicle_group.get());
  settle(pairs.expire_foreign(std::chrono::seconds(60)));
  markers.tick(*local_group, false, pairs.udp_read_channels(false));
  if (vehicle_group) markers.tick(*vehicle_group, true, pairs.udp_read_channels(true));
}

void RuntimeImpl::watch_keys() {
  for (int i = 0; i < 2; ++i) {
    auto& w = key_watch_[i];
    const bool vehicle = i == 1;
    const auto& group = vehicle ? vehicle_group : local_group;
    if (w.file.empty() || !group) continue;
    const auto sig = key_file_sig(w.file);
    if (sig == w.seen) continue;
    w.seen = sig;
    const char* which = vehicle ? "vehicle" : "host-local";
    try {
      auto keys = options.group_keys(vehicle);
      const bool same = [&] {
        const auto old = group->keys();
        if (!old || old->keys.size() != keys->keys.size() || old->encrypt != keys->encrypt) return false;
        for (std::size_t k = 0; k < keys->keys.size(); ++k)
          if (old->keys[k].bytes != keys->keys[k].bytes) return false;
        return true;
      }();
      w.failed = false;
      if (same) continue;
      spdlog::info("lcmx: the {} group's key file {} changed: now {}", which, w.file, keys_text(keys.get()));
      group->set_keys(std::move(keys));
    } catch (const std::exception& e) {
      if (w.failed) continue;
      w.failed = true;
      emit({Event{Event::Kind::error, "",
                  std::string("the ") + which + " group's key file changed and cannot be used (the keys in use stay): " +
                      e.what()}});
    }
  }
}

// The receive thread: DeathWatch's fd is readable.
void RuntimeImpl::on_death_fd() {
  auto dead = deaths.take_dead();
  if (dead.empty()) return;
  auto out = pairs.writers_died(dead);
  const bool any = out.announce;
  settle(std::move(out));
  if (any && options.reclaim_orphans) shm::reclaim_orphans(own_shm_prefix);
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
  impl_->events.set_callback(std::move(callback));
}

std::uint64_t Runtime::participant_id() const { return impl_->participant_id; }
std::uint64_t Runtime::host_id() const { return impl_->host; }
UdpStats Runtime::udp_stats() const { return impl_->front_door ? impl_->front_door->udp_stats() : UdpStats{}; }

}  // namespace lcmx
