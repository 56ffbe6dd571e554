#include "front_door.hpp"

#include <arpa/inet.h>
#include <ifaddrs.h>
#include <linux/netlink.h>
#include <linux/rtnetlink.h>
#include <netinet/in.h>
#include <spdlog/spdlog.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <fstream>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/lcmtypes/envelope.hpp"
#include "lcmx_msgs/history_t.hpp"
#include "lcmx_msgs/marker_t.hpp"

namespace lcmx::detail {

// Where marker_t's channel lies in its encoding: after the fingerprint (8), version (4),
// participant (8) and host (8).
constexpr std::size_t kMarkerChannelAt = 28;

// Serial number order (RFC 1982) of LCM's 32-bit sequence numbers: a comes before b.
bool serial_before(std::uint32_t a, std::uint32_t b) { return static_cast<std::int32_t>(a - b) < 0; }

// The LCM encoding starts with the type's fingerprint, big-endian.
bool fingerprint_is(std::span<const std::byte> data, std::int64_t fingerprint) {
  if (data.size() < 8) return false;
  std::uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | std::to_integer<std::uint8_t>(data[i]);
  return static_cast<std::int64_t>(v) == fingerprint;
}

// ---------------------------------------------------------------- HostAddresses

namespace {
std::set<std::uint32_t> read_local_addresses() {
  std::set<std::uint32_t> out;
  ifaddrs* list = nullptr;
  if (::getifaddrs(&list) != 0) return out;
  for (ifaddrs* i = list; i != nullptr; i = i->ifa_next)
    if (i->ifa_addr != nullptr && i->ifa_addr->sa_family == AF_INET)
      out.insert(reinterpret_cast<const sockaddr_in*>(i->ifa_addr)->sin_addr.s_addr);
  ::freeifaddrs(list);
  return out;
}
// 127.0.0.0/8 is this host's. So is 0.0.0.0: a program that sends to a multicast group routed
// to lo in a namespace with no other interface (liblcm's unbound socket) goes out with no source
// address, 127.0.0.1 being of host scope; the kernel refuses a zero source arriving from any
// network for a group beyond 224.0.0.x (ip_mc_validate_source), so it cannot come from the LAN.
bool loopback(std::uint32_t address_be) {
  const auto a = ntohl(address_be) >> 24;
  return a == 127 || address_be == 0;
}
}  // namespace

HostAddresses::HostAddresses() { refresh(); }

void HostAddresses::refresh() {
  auto a = read_local_addresses();
  std::lock_guard lock(mu_);
  read_at_ = std::chrono::steady_clock::now();
  if (!a.empty()) addresses_ = std::move(a);
}

bool HostAddresses::is_local(std::uint32_t address_be) {
  if (loopback(address_be)) return true;
  {
    std::lock_guard lock(mu_);
    if (addresses_.count(address_be)) return true;
    // An address added since the last read (a link that came up): read again, not too often.
    if (std::chrono::steady_clock::now() - read_at_ < std::chrono::milliseconds(100)) return false;
  }
  refresh();
  std::lock_guard lock(mu_);
  return addresses_.count(address_be) > 0;
}

// ---------------------------------------------------------------- RouteWatch

RouteWatch::RouteWatch() {
  fd_ = ::socket(AF_NETLINK, SOCK_RAW | SOCK_CLOEXEC | SOCK_NONBLOCK, NETLINK_ROUTE);
  if (fd_ < 0) {
    spdlog::debug("lcmx: no rtnetlink socket ({}): routes and addresses are re-read every second", std::strerror(errno));
    return;
  }
  sockaddr_nl sa{};
  sa.nl_family = AF_NETLINK;
  sa.nl_groups = RTMGRP_LINK | RTMGRP_IPV4_IFADDR | RTMGRP_IPV4_ROUTE;
  if (::bind(fd_, reinterpret_cast<const sockaddr*>(&sa), sizeof sa) != 0) {
    spdlog::debug("lcmx: cannot listen to rtnetlink ({}): routes and addresses are re-read every second",
                  std::strerror(errno));
    ::close(fd_);
    fd_ = -1;
  }
}

RouteWatch::~RouteWatch() {
  if (fd_ >= 0) ::close(fd_);
}

bool RouteWatch::changed() {
  if (fd_ < 0) return true;
  bool any = first_;
  first_ = false;
  char buf[8192];
  for (int reads = 0; reads < 1024; ++reads) {  // bounded: a flood is "changed" all the same
    const ssize_t r = ::recv(fd_, buf, sizeof buf, MSG_DONTWAIT);
    if (r > 0) {
      any = true;
      continue;
    }
    if (r < 0 && errno == EINTR) continue;
    if (r < 0 && errno == ENOBUFS) {  // notifications were lost: something changed
      any = true;
      continue;
    }
    break;  // EAGAIN: all read
  }
  return any;
}

// ---------------------------------------------------------------- FrontDoor

FrontDoor::FrontDoor(Context context) : ctx_(std::move(context)) { check_accept_local(); }

FrontDoor::~FrontDoor() {
  stop();
  if (wake_fd_ >= 0) ::close(wake_fd_);
}

// The host-local group is the host's own because the kernel refuses, on a LAN interface, a
// packet whose source is one of this host's addresses (a "martian") — unless accept_local is
// set on that interface. Said once at start.
void FrontDoor::check_accept_local() {
  std::error_code ec;
  std::vector<std::string> on;
  for (const auto& dir : std::filesystem::directory_iterator("/proc/sys/net/ipv4/conf", ec)) {
    std::ifstream f(dir.path() / "accept_local");
    int v = 0;
    if (f >> v && v != 0 && dir.path().filename() != "lo") on.push_back(dir.path().filename().string());
  }
  if (on.empty()) return;
  std::string list;
  for (const auto& n : on) list += (list.empty() ? "" : ", ") + n;
  spdlog::warn("lcmx: net.ipv4.conf.{{{}}}.accept_local is set: a machine on that network can send packets "
               "with this host's own address as source, which lcmx's host-local group takes as local "
               "(host scope). Unset it (sysctl -w net.ipv4.conf.<if>.accept_local=0) unless you need it",
               list);
}

void FrontDoor::start() {
  wake_fd_ = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (wake_fd_ < 0) throw Error(Errc::transport, "eventfd failed");
  epoll_ = ::epoll_create1(EPOLL_CLOEXEC);
  if (epoll_ < 0) throw Error(Errc::transport, "epoll_create1 failed");
  auto add = [&](int fd) {
    epoll_event ev{};
    ev.events = EPOLLIN;
    ev.data.fd = fd;
    if (::epoll_ctl(epoll_, EPOLL_CTL_ADD, fd, &ev) != 0) throw Error(Errc::transport, "epoll_ctl failed");
  };
  add(wake_fd_);
  if (ctx_.death_fd >= 0) add(ctx_.death_fd);
  add_udp_waiter(-1);  // the receive thread's own registration
  routes_checked_ = std::chrono::steady_clock::now();
  thread_ = std::thread([this] { receive_loop(); });
}

void FrontDoor::stop() {
  if (stopped_.exchange(true)) return;
  if (thread_.joinable()) {
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(wake_fd_, &one, sizeof one);
    thread_.join();
  }
  std::lock_guard lock(epoll_mu_);
  if (epoll_ >= 0) ::close(epoll_), epoll_ = -1;
}

FrontDoor::Counters FrontDoor::counters() const {
  std::lock_guard lock(counters_mu_);
  return counters_;
}

// The receive thread: beacons go to discovery, messages to subscribers' queues. An idle node
// executor with UDP matches waits on the same sockets (NodeImpl::wait_udp) and is woken
// first, so it receives and runs its callbacks with no second wake-up; this thread gets the
// datagrams that arrive while no executor waits, and the beacons executors drained.
void FrontDoor::receive_loop() {
  while (!stopped_.load()) {
    epoll_event evs[4];
    // A filter change waits for its turn (kFilterDelay) with no datagram to wake us.
    const int n = ::epoll_wait(epoll_, evs, 4, filters_dirty_.load() ? static_cast<int>(kFilterDelay.count()) : 1000);
    if (std::chrono::steady_clock::now() - routes_checked_ >= std::chrono::seconds(1)) {
      {
        std::lock_guard lock(recv_mu_);
        routes_checked_ = std::chrono::steady_clock::now();
        // Routes change (a laptop joins a network, a robot's DHCP comes late): stock programs
        // started since then join and send where the group routes now. Looked up again only
        // when the kernel told of a change.
        if (routes_.changed()) {
          spdlog::debug("lcmx: routes and addresses re-read (first look, or the kernel told of a change)");
          ctx_.local->refresh();
          addresses_.refresh();
        }
        // A drain also expires partial messages past their reassembly timeout: with no datagram
        // arriving after them (a sender whose large messages never complete), nothing else would.
        drain_locked(true);
        check_group_drops(*ctx_.local, local_drops_, "host-local");
        if (ctx_.vehicle) check_group_drops(*ctx_.vehicle, vehicle_drops_, "vehicle");
      }
      if (!stopped_.load() && ctx_.every_second) ctx_.every_second();
    }
    if (n <= 0) continue;
    bool death = false;
    for (int i = 0; i < n; ++i) {
      if (evs[i].data.fd == wake_fd_) {
        std::uint64_t v;
        [[maybe_unused]] auto r = ::read(wake_fd_, &v, sizeof v);
      }
      if (ctx_.death_fd >= 0 && evs[i].data.fd == ctx_.death_fd) death = true;
    }
    if (stopped_.load()) break;
    if (death && ctx_.on_death_fd) ctx_.on_death_fd();
    std::lock_guard lock(recv_mu_);
    drain_locked(true);
  }
}

bool FrontDoor::drain(bool handle_beacons, bool try_only) {
  std::unique_lock lock(recv_mu_, std::defer_lock);
  if (try_only) {
    if (!lock.try_lock()) return false;
  } else {
    lock.lock();
  }
  drain_locked(handle_beacons);
  return true;
}

void FrontDoor::drain_locked(bool handle_beacons) {
  if (filters_dirty_.load() && std::chrono::steady_clock::now() - filters_updated_ >= kFilterDelay)
    update_filters_locked();
  if (handle_beacons) {
    // Beacons other threads drained first: they arrived before anything drained now.
    auto pending = std::move(forwarded_);
    forwarded_.clear();
    for (const auto& f : pending) {
      const udpm::Message m{f.channel, f.data, f.source, f.sequence, f.lost_before, nullptr};
      try {
        dispatch(f.vehicle, m);
      } catch (const std::exception& e) {
        spdlog::warn("lcmx: beacon handling failed: {}", e.what());
      }
    }
  }
  auto one = [&](udpm::Group& group, bool vehicle) {
    try {
      group.drain([&](const udpm::Message& m) {
        // (A data marker is handled here, in order with the data around it: it settles their loss.)
        if (!handle_beacons && m.channel == discovery::kBeaconChannel &&
            !fingerprint_is(m.data, lcmx_msgs::marker_t::getHash())) {
          // Only from a source the front door takes (checked again when handled).
          if (!vehicle && !addresses_.is_local(m.source.address_be)) return refuse_not_local(m.source);
          // Beacons repeat every period: dropping some when the receive thread lags (or has
          // stopped) loses nothing for good, and keeps this bounded.
          if (stopped_.load() || forwarded_.size() >= 256) return;
          forwarded_.push_back({vehicle, std::string(m.channel), {m.data.begin(), m.data.end()}, m.source,
                                m.sequence, m.lost_before});
          const std::uint64_t v = 1;
          [[maybe_unused]] auto r = ::write(wake_fd_, &v, sizeof v);
          return;
        }
        dispatch(vehicle, m);
      });
    } catch (const std::exception& e) {
      spdlog::warn("lcmx: UDP receive failed: {}", e.what());
    }
  };
  one(*ctx_.local, false);
  report_refusals(*ctx_.local, false);
  if (ctx_.vehicle) {
    one(*ctx_.vehicle, true);
    report_refusals(*ctx_.vehicle, true);
  }
}

void FrontDoor::filters_changed() {
  if (filters_dirty_.exchange(true)) return;
  const std::uint64_t one = 1;
  if (wake_fd_ >= 0) [[maybe_unused]] auto r = ::write(wake_fd_, &one, sizeof one);
}

// What a group's socket takes: the channels we subscribe to (every channel with a channel-
// pattern subscription) and keep-last-N replays; on LCMX_BEACON, on the vehicle group while its
// Discovery follows the vehicle table, only the data markers of those channels, whoever sends
// them (marker_t names its channel 28 bytes into its payload; docs/discovery.md "Vehicle
// table"); the host-local group's discovery is always taken (host scope hears neighbours).
// recv_mu_ held.
udpm::ReceiveFilter FrontDoor::filter_for(bool vehicle, const Pairs::UdpWants& wants) {
  udpm::ReceiveFilter f;
  if (!wants.all) {
    std::vector<std::string> channels(wants.channels.begin(), wants.channels.end());
    channels.push_back(kHistoryChannel);
    f.channels = std::move(channels);
  }
  f.control_channel = discovery::kBeaconChannel;
  if (vehicle && ctx_.vehicle_discovery_listening && !ctx_.vehicle_discovery_listening()) {
    f.control_all = false;
    const auto fp = static_cast<std::uint64_t>(lcmx_msgs::marker_t::getHash());
    for (int i = 7; i >= 0; --i) f.mark_prefix.push_back(static_cast<std::byte>(fp >> (8 * i)));
    f.mark_channel_at = kMarkerChannelAt;
  }
  return f;
}

void FrontDoor::update_filters_locked() {
  filters_dirty_.store(false);
  filters_updated_ = std::chrono::steady_clock::now();
  const auto wants = ctx_.pairs.udp_wants();
  for (const auto& [group, vehicle] : {std::pair{ctx_.local, false}, std::pair{ctx_.vehicle, true}}) {
    if (!group) continue;
    auto f = filter_for(vehicle, wants);
    if (f == group->filter()) continue;
    try {
      group->set_filter(f);
    } catch (const udpm::Error& e) {
      // The filter in force stays (it takes more, never less: nothing is lost, wake-ups cost).
      const auto now = std::chrono::steady_clock::now();
      if (now - filter_error_logged_ >= std::chrono::seconds(5)) {
        filter_error_logged_ = now;
        spdlog::warn("lcmx: the {} group's receive filter could not be set: {}", vehicle ? "vehicle" : "host-local",
                     e.what());
      }
    }
  }
}

UdpStats FrontDoor::udp_stats() {
  std::lock_guard lock(recv_mu_);
  UdpStats out;
  for (const auto& [group, stats] : {std::pair{ctx_.local.get(), &out.host_local}, std::pair{ctx_.vehicle.get(), &out.vehicle}}) {
    if (!group) continue;
    const auto& c = group->counters();
    const auto& f = group->filter();
    stats->open = true;
    stats->packets_received = c.packets_received;
    stats->messages_received = c.messages_received;
    stats->packets_sent = c.packets_sent;
    stats->filtered_dropped = c.filtered_dropped;
    stats->kernel_dropped = c.kernel_dropped;
    stats->kernel_filtered = group->kernel_filtered();
    stats->all_channels = !f.channels;
    stats->channels = f.channels ? f.channels->size() : 0;
    stats->discovery = f.control_channel.empty() || f.control_all;
    stats->markers_by_channel = f.mark_channel_at.has_value();
  }
  return out;
}

void FrontDoor::report_refusals(udpm::Group& group, bool vehicle) {
  auto fresh = group.refusals().take_new();
  if (fresh.empty()) return;
  Pairs::Outcome out;
  for (const auto& s : fresh)
    out.events.push_back(
        Event{Event::Kind::error, "", std::string(vehicle ? "vehicle" : "host-local") + " group: " + udpm::describe(s)});
  ctx_.settle(std::move(out));
}

// EPOLLEXCLUSIVE entries are woken in the order they were added to a socket's wait queue,
// skipping epoll sets nobody waits on; re-adding the receive thread's entries puts them last.
void FrontDoor::add_udp_waiter(int epfd) {
  std::lock_guard lock(epoll_mu_);
  if (epoll_ < 0) return;
  for (const auto& g : {ctx_.local, ctx_.vehicle}) {
    if (!g) continue;
    epoll_event ev{};
    ev.events = EPOLLIN | EPOLLEXCLUSIVE;
    ev.data.fd = g->fd();
    if (epfd >= 0 && ::epoll_ctl(epfd, EPOLL_CTL_ADD, g->fd(), &ev) != 0)
      throw Error(Errc::transport, std::string("epoll_ctl: ") + std::strerror(errno));
    if (epfd >= 0) ::epoll_ctl(epoll_, EPOLL_CTL_DEL, g->fd(), nullptr);
    // A socket already readable wakes the receive thread at once (no datagram is stranded).
    if (::epoll_ctl(epoll_, EPOLL_CTL_ADD, g->fd(), &ev) != 0)
      throw Error(Errc::transport, std::string("epoll_ctl: ") + std::strerror(errno));
  }
}

void FrontDoor::refuse_not_local(const udpm::Source& source) {
  {
    std::lock_guard lock(counters_mu_);
    ++counters_.refused_not_local;
  }
  ++refused_total_;
  if (refused_sources_.size() < 4096 || refused_sources_.count(source.address_be)) ++refused_sources_[source.address_be];
  const auto now = std::chrono::steady_clock::now();
  if (now - refused_logged_ < std::chrono::seconds(5)) return;
  refused_logged_ = now;
  spdlog::warn("lcmx: refused datagrams on the host-local group from {} (not an address of this host; {} refused "
               "so far): the host-local group is this host's own; other hosts use the vehicle group",
               udpm::to_string(source), refused_total_);
}

namespace {
// A keep-last-N replay, decoded bounded: nothing is sized from the datagram before it is
// checked against the bytes there are.
std::optional<lcmx_msgs::history_t> decode_history(std::span<const std::byte> data) {
  lcmx_msgs::history_t h;
  if (!lcmtypes::decode(data, h)) return std::nullopt;  // lcmx/lcmtypes/envelope.hpp
  return h;
}
}  // namespace

void FrontDoor::dispatch(bool vehicle, const udpm::Message& m) {
  // 1. Source: the host-local group is this host's.
  const bool local_address = addresses_.is_local(m.source.address_be);
  if (!vehicle && !local_address) return refuse_not_local(m.source);
  auto& group = vehicle ? *ctx_.vehicle : *ctx_.local;
  // 2. By channel.
  if (m.channel == discovery::kBeaconChannel) {
    // A data marker (Markers) settles UDP loss; everything else on the channel is discovery's
    // (only a registry's speaker sends it, docs/discovery.md).
    if (fingerprint_is(m.data, lcmx_msgs::marker_t::getHash())) return on_marker(vehicle, m, local_address);
    ctx_.beacon(vehicle, m);
    return;
  }
  if (group.is_own(m.source)) return;  // our own, looped back
  const auto sender = ctx_.peers.sender(vehicle, m.source, local_address);
  if (sender.same_host) return;  // a participant of this host: its subscribers here read shm
  // On the vehicle group, from one of this host's addresses and no participant we know: a
  // participant of this host whose record we have not read yet (a new publisher sends there
  // during its start-up window, and a subscriber made a moment ago has not read the registry).
  // Its subscribers here read its ring, from when they began: taken here too, its first
  // messages would arrive twice. Stock LCM programs on this host use the host-local group.
  if (vehicle && sender.participant == 0 && local_address) return;
  if (m.channel == kHistoryChannel) {
    auto h = decode_history(m.data);
    if (!h) return;  // not ours to judge
    for (auto& [target, bytes] : ctx_.pairs.accept_history(vehicle, m.source, *h)) {
      const std::span<const std::byte> view(*bytes);
      push_intra(*target.first, IntraItem{std::move(bytes), &raw_type_info(), target.second, view});
    }
    return;
  }
  std::vector<Pairs::Target> targets;
  ctx_.settle(ctx_.pairs.deliver_udp(vehicle, sender.participant, m.source, m, targets));
  if (targets.empty()) return;
  // UDP loss: a participant's is settled per channel at its markers (on_marker); a stock LCM
  // sender's sequence gaps are logged, while the socket takes every channel (a filtered socket
  // does not see the sequence numbers of the channels it refuses).
  if (sender.participant != 0) ++channel_loss(vehicle, sender.participant, m.channel).received;
  else if (m.lost_before > 0 && !group.filter().channels)
    log_foreign_loss(vehicle, udpm::to_string(m.source), m.lost_before);
  // A reassembled message is handed over in its reassembly buffer; a single datagram's bytes
  // live in the socket's receive slot, reused by the next read: copied.
  std::shared_ptr<const void> owner = m.buffer;
  if (!owner) owner = make_bytes(m.data);
  const auto bytes = m.buffer ? m.data : std::span<const std::byte>(*std::static_pointer_cast<const Bytes>(owner));
  for (auto& [sub, stats] : targets) {
    if (sub->udp_inline && !sub->state->removed.load()) {
      RetainSource src;
      src.owner = owner;
      src.pair = stats.get();  // who sent it (services take replies only from their server)
      if (sub->udp_inline(RawMessage{sub->channel(), bytes, &src})) {
        stats->received.fetch_add(1, std::memory_order_relaxed);
        sub->delivered.fetch_add(1, std::memory_order_relaxed);
        continue;
      }
    }
    push_intra(*sub, IntraItem{owner, &raw_type_info(), stats, bytes});
  }
}

// A participant's marker (lcmx_msgs::marker_t, Markers): for one channel it sends, the messages
// it sent on it so far. Between two markers of one sender, what was sent and not received here
// is that channel's loss, counted in the drops of our subscribers matched with it (each pair
// exactly: a sender's channels are told apart). The first marker of a channel (or one whose
// count went back: the sender restarted on the same port) only sets the count to start from.
void FrontDoor::on_marker(bool vehicle, const udpm::Message& m, bool local_address) {
  auto& group = vehicle ? *ctx_.vehicle : *ctx_.local;
  if (group.is_own(m.source)) return;
  const auto sender = ctx_.peers.sender(vehicle, m.source, local_address);
  if (sender.participant == 0 || sender.same_host) return;  // (this host's: its subscribers here read shm)
  lcmx_msgs::marker_t mk;
  if (!lcmtypes::decode(m.data, mk) || mk.participant_id != sender.participant || mk.count < 0) return;
  const auto& channel = mk.channel;
  const auto count = mk.count;
  auto it = channel_loss_.find(ChannelKey{vehicle, sender.participant, channel});
  if (it == channel_loss_.end()) {
    // Nothing of it received here yet: counted from this marker on if we receive it.
    if (ctx_.pairs.charge_loss(sender.participant, {channel}, 0).empty()) return;
    channel_loss(vehicle, sender.participant, channel).last = count;
    return;
  }
  auto& l = it->second;
  const auto received = std::exchange(l.received, 0);
  if (l.last < 0 || count < l.last) {
    l.last = count;
    return;
  }
  const auto expected = static_cast<std::uint64_t>(count - l.last);
  l.last = count;
  if (expected <= received) return;
  const auto lost = expected - received;
  l.lost += lost;
  if (ctx_.pairs.charge_loss(sender.participant, {channel}, lost).empty()) return;
  const auto now = std::chrono::steady_clock::now();
  if (now - l.logged < std::chrono::seconds(5)) return;
  l.logged = now;
  spdlog::warn("lcmx: {} message(s) on channel '{}' from participant {} ({}) lost on the {} group ({} so far); "
               "counted in its subscribers' drops",
               lost, channel, sender.participant, udpm::to_string(m.source), vehicle ? "vehicle" : "host-local",
               l.lost);
}

FrontDoor::ChannelLoss& FrontDoor::channel_loss(bool vehicle, std::int64_t participant, std::string_view channel) {
  ChannelKey key{vehicle, participant, std::string(channel)};
  auto it = channel_loss_.find(key);
  if (it != channel_loss_.end()) return it->second;
  // Bounded: past kMaxChannelLoss (senders x channels) all start over from their next marker.
  if (channel_loss_.size() >= kMaxChannelLoss) channel_loss_.clear();
  return channel_loss_[std::move(key)];
}

// Bounded: a stock LCM sender stays until kMaxSources senders were seen, then all start over
// (their unattributed totals are lost).
FrontDoor::SourceLoss& FrontDoor::loss_of(bool vehicle, const std::string& source) {
  if (source_loss_.size() >= kMaxSources && !source_loss_.count({vehicle, source})) source_loss_.clear();
  return source_loss_[{vehicle, source}];
}

void FrontDoor::check_group_drops(const udpm::Group& group, GroupDrops& last, const char* which) {
  // Not kernel_dropped: the socket's drop count includes this participant's own datagrams,
  // which its socket filter drops by design (udpm/group.cpp drop_own_datagrams).
  const auto& c = group.counters();
  const auto now = std::chrono::steady_clock::now();
  if ((c.unauthenticated_dropped != last.unauthenticated || c.replays_dropped != last.replays) &&
      now - last.refusals_logged >= std::chrono::seconds(5)) {
    // The first refusal of each source was an error Event; from then on, counted.
    spdlog::warn("lcmx: keyed {} group: {} unauthenticated and {} replayed datagram(s) refused since the last report "
                 "({} / {} in all, from {} source(s))",
                 which, c.unauthenticated_dropped - last.unauthenticated, c.replays_dropped - last.replays,
                 c.unauthenticated_dropped, c.replays_dropped, group.refusals().sources().size());
    last.unauthenticated = c.unauthenticated_dropped;
    last.replays = c.replays_dropped;
    last.refusals_logged = now;
  }
  if (c.incomplete_dropped == last.incomplete && c.oversize_dropped == last.oversize) return;
  if (now - last.logged < std::chrono::seconds(5)) return;  // a later check reports the sum
  spdlog::warn("lcmx: {} UDP group: {} incomplete message(s) dropped (fragments lost, e.g. a receive buffer too "
               "small: net.core.rmem_max) and {} over the reassembly limit ({} bytes) since the last report ({} / {} "
               "in all). A subscription counts such a loss only when its sender's next message arrives",
               which, c.incomplete_dropped - last.incomplete, c.oversize_dropped - last.oversize,
               group.config().max_reassembly_bytes, c.incomplete_dropped, c.oversize_dropped);
  last.incomplete = c.incomplete_dropped;
  last.oversize = c.oversize_dropped;
  last.logged = now;
}

void FrontDoor::log_foreign_loss(bool vehicle, const std::string& source, std::uint32_t lost) {
  auto& s = loss_of(vehicle, source);
  s.unattributed += lost;
  const auto now = std::chrono::steady_clock::now();
  if (now - s.logged < std::chrono::seconds(5)) return;
  s.logged = now;
  spdlog::warn("lcmx: {} message(s) from LCM sender {} lost on the {} group ({} so far); a stock LCM sender "
               "announces no channel list, so the loss cannot be given to one subscription",
               lost, source, vehicle ? "vehicle" : "host-local", s.unattributed);
}

}  // namespace lcmx::detail
