// Whether a message can come from a given server: services and actions take replies and
// statuses only from the server they asked (docs/services.md "Trust"). Who sent a message is
// the runtime's answer (hook::sender_of, lcmx/core/detail/service_hook.hpp).
#pragma once

#include <cstdint>

#include "lcmx/core/detail/service_hook.hpp"

namespace lcmx::detail {

using hook::Sender;
using hook::sender_of;

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
