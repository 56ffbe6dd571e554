// PeerTable: the other participants this runtime knows, as discovery tells them, by scope,
// with the indexes the receive path and matching need (sender address -> participant, topic
// -> endpoints). It holds what peers announce; it decides nothing about pairs (Pairs does).
//
// Scopes (DESIGN.md "Discovery"): `host`, participants of this host (host-scope beacons with
// our host id: shared memory); `vehicle`, participants of other hosts (vehicle-scope beacons);
// `neighbour`, participants of this network namespace with another host id (another /dev/shm:
// a container) when there is no vehicle group (reached over UDP on the host-local group).
//
// Threads: every member is thread-safe. Its lock is a leaf (taken under Pairs::mu and the
// front door's recv_mu, never the other way round). Lookups copy what they return.
#pragma once

#include <cstdint>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "lcmx/discovery/discovery.hpp"
#include "lcmx/udpm/udpm.hpp"
#include "lcmx_msgs/beacon_t.hpp"

namespace lcmx::detail {

enum class Scope : std::uint8_t { host, vehicle, neighbour };

class PeerTable {
 public:
  // What a change of one peer means for matching.
  struct Delta {
    Scope scope = Scope::host;
    discovery::Change change = discovery::Change::updated;
    // Joined, left, or its announced shape changed (endpoints, their classes, segments,
    // matches, flags): pairs on the topics below must be looked at again. False for a beacon
    // that only refreshed statistics (messages, rates, drops): nothing to match.
    bool structural = false;
    // Topics it publishes or subscribes to, before or after the change.
    std::set<std::string> publisher_topics, subscriber_topics;
    bool bridge = false;  // it is (or was) a Message Bridge of this host
    lcmx_msgs::beacon_t before;  // its previous beacon (empty when it joined)
  };
  Delta apply(Scope scope, discovery::Change change, const lcmx_msgs::beacon_t& beacon);

  // An endpoint of a peer, copied for matching.
  struct Endpoint {
    Scope scope = Scope::host;
    std::int64_t participant = 0;
    std::int8_t flags = 0;
    std::string process_name;
    std::int32_t pid = 0;
    std::int64_t pid_namespace = 0;
    lcmx_msgs::endpoint_t e;
  };
  // Every peer endpoint of `kind` (endpoint_t::KIND_*) on `topic`, in participant order.
  std::vector<Endpoint> endpoints_on(const std::string& topic, std::int8_t kind) const;
  // Every topic a host or vehicle peer publishes (channel subscriptions expand them).
  std::set<std::string> published_topics() const;
  // The channels participant `id` publishes (UDP loss settlement), empty if unknown.
  std::set<std::string> published_by(std::int64_t id) const;
  // What participant `id` announces of `topic`: whether it publishes it, and its flags
  // (beacon_t::FLAG_*). A new publisher's first messages may come before its record says so
  // (the start-up race, Pairs::deliver_udp).
  struct Publishing {
    bool publishes = false;
    std::int8_t flags = 0;
  };
  Publishing publishing(std::int64_t id, const std::string& topic) const;

  // Who sent a datagram from `source`: on the vehicle group (`vehicle`), or on the host-local
  // group, where `local_address` says whether the source address is one of this host's.
  struct Sender {
    std::int64_t participant = 0;  // 0: no participant we know (a stock LCM program)
    bool same_host = false;        // a participant of this host (its subscribers read shm)
  };
  Sender sender(bool vehicle, const udpm::Source& source, bool local_address) const;
  // The address participant `id` sends from on the vehicle group (`vehicle`) or the
  // host-local group; nullopt if unknown. Keep-last-N replays are taken only from there.
  std::optional<udpm::Source> source_of(std::int64_t id, bool vehicle) const;

  // Whether a peer of any scope announces endpoint `endpoint` now.
  bool announced(std::uint64_t participant, std::uint64_t endpoint) const;
  // A host peer's endpoint as announced now (its current shm segment), if any.
  std::optional<Endpoint> host_endpoint(std::uint64_t participant, std::uint64_t endpoint) const;
  // The Message Bridges of this host: whether any, and the globs they carry.
  struct Bridges {
    bool seen = false;
    std::vector<std::string> carried;
  };
  Bridges host_bridges() const;

 private:
  struct Peer {
    Scope scope = Scope::host;
    lcmx_msgs::beacon_t beacon;
    std::uint64_t shape = 0;  // hash of what matching reads (see shape_of)
    std::optional<udpm::Source> local_source, vehicle_source;
  };
  static std::uint64_t shape_of(const lcmx_msgs::beacon_t& b);
  void index(const Peer& p, bool add);  // mu_ held

  mutable std::mutex mu_;
  std::map<std::int64_t, Peer> peers_;  // by participant id (ids are random 63-bit)
  // Topic -> participants with a publisher / a subscriber on it (any scope).
  std::map<std::string, std::map<std::int64_t, int>> publishers_, subscribers_;
  // Senders: "ip:port" of a participant's sockets, per group, and (host-local group) the
  // port its mirror uses from another address of this host.
  std::map<std::pair<std::uint32_t, std::uint16_t>, std::int64_t> vehicle_sources_, local_sources_;
  std::map<std::uint16_t, std::int64_t> local_ports_;
};

// "a.b.c.d:port" -> Source (network order); nullopt if it is not that.
std::optional<udpm::Source> parse_source(const std::string& text);

}  // namespace lcmx::detail
