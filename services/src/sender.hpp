// Who sent a message a raw subscriber received: the publisher of the pair it came through
// (RetainSource::pair, PairCounters). For services and actions, which take replies and
// statuses only from the server they asked.
#pragma once

#include <cstdint>
#include <optional>

#include "lcmx/core/subscriber.hpp"

namespace lcmx::detail {

struct Sender {
  std::uint64_t participant = 0;
  // The publisher's endpoint id: exact on the intra and shm paths; over UDP the first UDP
  // match of `participant` on the channel (a datagram names its sender's participant, by its
  // address, not its endpoint); over the bridge, this host's bridge republisher.
  std::uint64_t endpoint = 0;
  Path path = Path::intra;
};

// nullopt when the message names no pair (made by hand) or its sender is no lcmx
// participant (a stock LCM program over UDP). Any thread, no lock: the pair's publisher is set
// before any message goes through it and never changes.
inline std::optional<Sender> sender_of(const RawMessage& m) {
  if (m.source == nullptr || m.source->pair == nullptr || m.source->pair->publisher_participant == 0)
    return std::nullopt;
  const auto& p = *m.source->pair;
  return Sender{p.publisher_participant, p.publisher_endpoint, p.path};
}

// Whether a message from `s` can come from the server endpoint (participant, endpoint) that
// was reached over a path that leaves the host (`remote`: UDP or the bridges). intra/shm: the
// exact publisher; UDP: its participant (all UDP can tell); the bridge: this host's bridge
// republishes what the servers of other hosts send and names no origin, so only for a remote
// server (the envelope's own fields then name the server).
inline bool sent_by(const Sender& s, std::uint64_t participant, std::uint64_t endpoint, bool remote) {
  switch (s.path) {
    case Path::intra:
    case Path::shm: return s.participant == participant && s.endpoint == endpoint;
    case Path::udp: return s.participant == participant;
    case Path::bridge: return remote;
  }
  return false;
}

}  // namespace lcmx::detail
