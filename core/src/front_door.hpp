// FrontDoor: the one place every datagram of the groups enters (DESIGN.md "Trust"). It owns
// the receive side of both groups and the receive thread, and for each datagram, in this order:
//  1. checks its source: on the host-local group only this host's own addresses are taken (the
//     kernel drops a LAN packet that claims a local source unless accept_local is set, checked
//     at start), so nothing from the LAN reaches host scope; the receive socket is bound to the
//     group address, so unicast to the port never arrives at all;
//  2. dispatches by channel: beacons to discovery of that scope (on the receive thread only;
//     executors forward them), keep-last-N replays to Pairs::accept_history (decoded bounded),
//     messages to the subscribers Pairs matched with the sender;
//  3. accounts UDP loss per sender and channel (the messages received between two of the
//     sender's data markers against what they say it sent; a stock LCM sender's sequence gaps
//     are logged).
// It keeps each group's receive filter (udpm::ReceiveFilter) in step with what this participant
// reads: the channels it subscribes to (every channel with a channel-pattern subscription), the
// markers of the participants publishing them, and on the vehicle group the discovery datagrams
// only while its vehicle Discovery listens (its host's speaker: Discovery::listening). The
// kernel drops the rest before it wakes anyone (update_filters_locked).
// Before all that, a keyed group (udpm::GroupConfig::keys, docs/keyed-groups.md) has checked
// each datagram's tag and replay window inside udpm::Group::drain, before parsing anything: what
// it refused never reaches the front door. The front door reports it: the first refusal from
// each source as an Event::Kind::error ("vehicle group: unauthenticated traffic from 10.0.0.7:
// wrong key or not lcmx"), then counts in a log line at most every 5 s (report_refusals,
// check_group_drops).
//
// Who drains: the receive thread, and idle node executors waiting for UDP (NodeImpl::wait_udp,
// EPOLLEXCLUSIVE entries ahead of the receive thread's: a datagram wakes one thread). Whoever
// drains holds recv_mu_ (a Group's receive side has one user at a time; arrival order is kept).
// Lock order: recv_mu_ -> discovery's delivery lock -> Pairs::mu -> ...; the host address set
// has a leaf lock of its own.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "lcmx/core/stats.hpp"
#include "lcmx/udpm/udpm.hpp"
#include "lcmx_msgs/beacon_t.hpp"
#include "pairs.hpp"
#include "peers.hpp"

namespace lcmx::detail {

// This host's IPv4 addresses (every interface's, all of 127.0.0.0/8, and 0.0.0.0: see loopback()), re-read within
// a second of a change the kernel tells (RouteWatch) and at once (at most every 100 ms) when a source is not
// among them.
// Threads: thread-safe; leaf lock.
class HostAddresses {
 public:
  HostAddresses();
  bool is_local(std::uint32_t address_be);
  void refresh();

 private:
  std::mutex mu_;
  std::set<std::uint32_t> addresses_;
  std::chrono::steady_clock::time_point read_at_{};
};

// Whether this host's (network namespace's) links, IPv4 addresses or IPv4 routes may have
// changed: an rtnetlink socket subscribed to their notifications (RTMGRP_LINK, _IPV4_IFADDR,
// _IPV4_ROUTE), read without blocking. So the once-a-second route and address checks cost
// nothing while nothing changes (they cost two getifaddrs dumps and two sockets per second per
// process before: a tenth of an idle process's CPU, docs/discovery.md). Without the socket
// (refused) every call says "changed": the checks poll as before.
// Threads: the receive thread only.
class RouteWatch {
 public:
  RouteWatch();  // never throws
  ~RouteWatch();
  RouteWatch(const RouteWatch&) = delete;
  RouteWatch& operator=(const RouteWatch&) = delete;
  // Reads the notifications queued; true if there was any, if some were lost (ENOBUFS), on the
  // first call, or without the socket.
  bool changed();

 private:
  int fd_ = -1;
  bool first_ = true;
};

class FrontDoor {
 public:
  struct Context {
    std::shared_ptr<udpm::Group> local;    // host-local group (always)
    std::shared_ptr<udpm::Group> vehicle;  // vehicle group, or null
    PeerTable& peers;
    Pairs& pairs;
    // A beacon, to the discovery of its scope. Receive thread (or a discovery thread draining
    // before a lease expires), recv_mu_ held.
    std::function<void(bool vehicle, const udpm::Message&)> beacon;
    // What Pairs said: emit its events, announce if asked. recv_mu_ may be held.
    std::function<void(Pairs::Outcome)> settle;
    // About once a second on the receive thread, no lock held.
    std::function<void()> every_second;
    // DeathWatch's fd (-1: none) and what to do when it is readable (receive thread, no lock).
    int death_fd = -1;
    std::function<void()> on_death_fd;
    // Whether the vehicle scope's Discovery takes the group's discovery datagrams now (null:
    // always). Receive thread, recv_mu_ held.
    std::function<bool()> vehicle_discovery_listening;
  };
  explicit FrontDoor(Context context);
  ~FrontDoor();  // stop()
  FrontDoor(const FrontDoor&) = delete;
  FrontDoor& operator=(const FrontDoor&) = delete;

  // Starts the receive thread. Throws Error(transport) if its epoll set cannot be made.
  void start();
  // Stops and joins the receive thread. Idempotent. Executors may still drain afterwards
  // (the beacons they would forward are dropped).
  void stop();

  // Drains both groups and dispatches what arrived. Beacons are handled here only when
  // `handle_beacons` (the receive thread, a discovery thread before a lease expires); other
  // callers copy them for the receive thread and wake it. Takes recv_mu_ (blocking, or only
  // if free when `try_only`); call with no lock held. Returns false if try_only and another
  // thread was draining.
  bool drain(bool handle_beacons, bool try_only = false);
  // Adds the group sockets to `epfd` (EPOLLEXCLUSIVE) ahead of the receive thread's entries.
  void add_udp_waiter(int epfd);

  bool is_local_address(std::uint32_t address_be) { return addresses_.is_local(address_be); }

  // What this participant reads changed (a subscription, a match, a peer, its vehicle
  // Discovery's listening): the receive filters are brought in step within kFilterDelay (at
  // most once per kFilterDelay: a launch changes matches thousands of times). Any thread.
  void filters_changed();
  static constexpr auto kFilterDelay = std::chrono::milliseconds(10);

  // Each group's receive counters and filter as of now (takes recv_mu_).
  UdpStats udp_stats();

  struct Counters {
    std::uint64_t refused_not_local = 0;  // host-local datagrams from a non-local source
  };
  Counters counters() const;

 private:
  void receive_loop();
  void drain_locked(bool handle_beacons);
  // Brings the groups' receive filters in step (filters_changed). recv_mu_ held.
  void update_filters_locked();
  udpm::ReceiveFilter filter_for(bool vehicle, const Pairs::UdpWants& wants);
  void dispatch(bool vehicle, const udpm::Message& m);
  void refuse_not_local(const udpm::Source& source);
  // The sources `group` refused for the first time since the last call, as error Events.
  // recv_mu_ held.
  void report_refusals(udpm::Group& group, bool vehicle);
  void check_accept_local();

  // UDP loss of a participant, per (group, sender, channel) (issue 15; docs/ARCHITECTURE.md
  // "UDP loss"): the messages received of it since the sender's last marker, and the count
  // that marker said. Settled at each of its markers (on_marker): each pair's loss exactly,
  // whatever the receive filter drops of the sender's other channels. recv_mu_ held.
  struct ChannelLoss {
    std::uint64_t received = 0;  // messages of it received since `last` was said
    std::int64_t last = -1;      // the sender's count at its last marker (-1: none yet)
    std::uint64_t lost = 0;      // in all, for the log
    std::chrono::steady_clock::time_point logged{};
  };
  using ChannelKey = std::tuple<bool, std::int64_t, std::string>;  // (vehicle, participant, channel)
  static constexpr std::size_t kMaxChannelLoss = 65536;  // channel_loss_ entries (see channel_loss)
  ChannelLoss& channel_loss(bool vehicle, std::int64_t participant, std::string_view channel);
  void on_marker(bool vehicle, const udpm::Message& m, bool local_address);
  // A stock LCM sender's loss (sequence gaps): it announces no channels, so it is logged only.
  struct SourceLoss {
    std::uint64_t unattributed = 0;   // messages lost
    std::chrono::steady_clock::time_point logged{};
  };
  static constexpr std::size_t kMaxSources = 4096;  // source_loss_ entries (see loss_of)
  SourceLoss& loss_of(bool vehicle, const std::string& source);
  void log_foreign_loss(bool vehicle, const std::string& source, std::uint32_t lost);
  // Warns when a group dropped messages no sequence gap reports yet (incomplete, oversize).
  struct GroupDrops {
    std::uint64_t incomplete = 0, oversize = 0;  // last logged counters
    std::uint64_t unauthenticated = 0, replays = 0;  // keyed groups: refused, last logged
    std::chrono::steady_clock::time_point refusals_logged{};
    std::chrono::steady_clock::time_point logged{};
  };
  void check_group_drops(const udpm::Group& group, GroupDrops& last, const char* which);

  const Context ctx_;
  HostAddresses addresses_;
  RouteWatch routes_;  // the receive thread's
  std::atomic<bool> stopped_{false};

  std::mutex recv_mu_;  // guards everything below (whoever drains)
  struct Forwarded {    // a beacon another thread drained, for the receive thread
    bool vehicle;
    std::string channel;
    std::vector<std::byte> data;
    udpm::Source source;
    std::uint32_t sequence;
    std::uint32_t lost_before;
  };
  std::vector<Forwarded> forwarded_;  // handled before anything drained later
  std::map<std::pair<bool, std::string>, SourceLoss> source_loss_;  // (vehicle, "ip:port") of stock senders
  std::map<ChannelKey, ChannelLoss> channel_loss_;
  std::atomic<bool> filters_dirty_{true};
  std::chrono::steady_clock::time_point filters_updated_{};
  std::chrono::steady_clock::time_point filter_error_logged_{};
  GroupDrops local_drops_, vehicle_drops_;
  std::chrono::steady_clock::time_point routes_checked_{};
  std::map<std::uint32_t, std::uint64_t> refused_sources_;  // address -> datagrams (bounded)
  std::uint64_t refused_total_ = 0;
  std::chrono::steady_clock::time_point refused_logged_{};

  std::thread thread_;
  int wake_fd_ = -1;
  int epoll_ = -1;           // wake_fd_ + the group sockets (EPOLLEXCLUSIVE, last) + death_fd
  std::mutex epoll_mu_;      // serialises re-registrations of the sockets in epoll_
  mutable std::mutex counters_mu_;
  Counters counters_;
};

}  // namespace lcmx::detail
