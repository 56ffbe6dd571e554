#pragma once
// Group configuration and LCM-style URLs ("udpm://239.255.76.67:7667?ttl=0", "...&iface=eth0").

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

namespace lcmx::udpm {

struct GroupKeys;
class Refusals;

struct GroupConfig {
  std::string address = "239.255.76.67";  // IPv4 multicast group (224.0.0.0/4)
  std::uint16_t port = 7667;              // 1..65535
  int ttl = 0;                            // IP_MULTICAST_TTL 0..255; 0 = this host only
  // Interface NAME: the group is joined on it (IP_ADD_MEMBERSHIP, ip_mreqn ifindex) and packets
  // are sent on it (IP_MULTICAST_IF) from its first IPv4 address ("pinned").
  // Empty (a URL without iface=): the host-local mode, which works like liblcm's whatever the
  // routing table says: joined on lo AND on the interface the kernel routes the group to (the one
  // liblcm joins and sends on), publish() on lo, publish_routed() where the kernel routes the
  // group (see Group).
  std::string interface;
  // SO_RCVBUF request in bytes (SO_RCVBUFFORCE first when permitted); 0 keeps the kernel default.
  int recv_buffer_bytes = 4 << 20;
  bool multicast_loop = true;  // IP_MULTICAST_LOOP on the sending socket

  // Not part of the URL: false attaches a socket filter to the receive socket that drops, in
  // the kernel, this Group's own looped-back datagrams (source = local_source()). They are
  // never read, counted or delivered, and above all never wake the receiving thread; other
  // programs on this host still hear them (multicast_loop stays as configured).
  bool receive_own = true;

  // Not part of the URL: limits of fragment reassembly (LC03).
  // Sum of the declared sizes of all partially received messages; the oldest partial messages
  // are dropped (counted incomplete) to make room. A message larger than this is dropped.
  std::size_t max_reassembly_bytes = std::size_t{1} << 28;
  std::size_t max_partial_messages = 256;  // at most this many partial messages at once
  // A partial message that got no fragment for this long is dropped (counted incomplete).
  std::chrono::milliseconds reassembly_timeout{1000};

  // Not part of the URL: the group key (lcmx/udpm/keys.hpp, docs/keyed-groups.md). Null: the
  // group speaks LCM's wire format, open to anyone on it. Set: every datagram sent is sealed
  // in an lcmx envelope, and only envelopes that verify under one of these keys, once, are
  // received; everything else is refused (counted per source in `refusals`). Must hold 1 or 2
  // keys. Group::set_keys replaces it while the Group runs (rotation).
  std::shared_ptr<const GroupKeys> keys;
  // Where a keyed group records what it refused, per source. Null: the Group makes its own
  // (Group::refusals()); give one to read it while the Group is owned elsewhere (an observer).
  std::shared_ptr<Refusals> refusals;
  // Keyed groups: a datagram of a sender this Group has not heard yet is taken only when the
  // time the sender stamped in it is within this of this host's clock (a capture replayed to
  // a process started later is refused after this long; docs/keyed-groups.md "Replay"); once
  // a sender is known, its counter alone decides. 0 turns the check off (hosts whose clocks are
  // not kept in sync). Hosts' clocks must agree within it.
  std::chrono::seconds keyed_max_skew{60};
};

// Parses "udpm://[ADDRESS][:PORT][?key=value&...]". Missing address or port take GroupConfig's
// defaults; no iface= gives the host-local mode (interface empty). Keys: ttl, iface,
// recv_buf_size, multicast_loop (true/false/1/0). Unknown or repeated keys are errors. The
// reassembly fields keep their defaults.
// Throws: Error(invalid_config) whose message names the bad part.
GroupConfig parse_url(std::string_view url);

// The URL of cfg's URL fields; parse_url(to_url(cfg)) gives them back. Does not validate.
std::string to_url(const GroupConfig& cfg);

}  // namespace lcmx::udpm
