// Links and failover, the pure part (failover.cpp applies it on the control thread; unit tests:
// test/bridge/pieces_test.cpp). A link is up while its heartbeats are answered; each peer's
// traffic uses its most preferred up link, moves at once when that link goes down, and moves
// back to a more preferred link only after that one has been up for the fail-back hold.
#pragma once

#include <chrono>
#include <cstdint>
#include <span>

namespace lcmx::bridge::failover {

using Clock = std::chrono::steady_clock;

struct LinkState {
  bool up = false;
  Clock::time_point up_since{};  // when it last came up
};

// Whether a link is up: it answered a heartbeat at some time, the last less than `timeout` ago.
bool link_up(bool answered, Clock::time_point last_pong, Clock::time_point now, Clock::duration timeout);

// Whether a pong whose ping was sent `age_ns` ago proves the link: a negative age (clock step,
// forged timestamp) or one older than the link timeout (queued while the link was down) does not.
bool pong_proves_link(std::int64_t age_ns, std::chrono::milliseconds link_timeout);

// The link (index into `links`, in preference order) that should carry a peer's traffic, given
// the one that does (`current`, -1 for none): the first up link when `current` is down or none;
// a more preferred up link once it has been up for `failback_hold`; otherwise `current`.
// -1 when no link is up.
int next_active(std::span<const LinkState> links, int current, Clock::time_point now, Clock::duration failback_hold);

}  // namespace lcmx::bridge::failover
