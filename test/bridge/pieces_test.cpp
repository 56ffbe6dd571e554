// Unit tests of the bridge engine's pure pieces (bridge/src: failover.hpp, channels.hpp,
// security.hpp), which the multi-host tests (bridge_test.cpp) cover only end to end.
#include <catch2/catch.hpp>
#include <zmq.h>

#include <array>
#include <chrono>
#include <cstring>
#include <deque>
#include <vector>

#include "channels.hpp"
#include "failover.hpp"
#include "lcmx/bridge/config.hpp"
#include "lcmx/test/skip.hpp"
#include "security.hpp"

using namespace lcmx::bridge;
using namespace std::chrono_literals;

TEST_CASE("failover: the most preferred up link, at once on loss, back after the hold", "[bridge][failover]") {
  using failover::LinkState;
  const auto t0 = failover::Clock::now();
  const auto hold = 1000ms;
  // pcie (0) preferred over eth (1).
  std::vector<LinkState> links{{false, {}}, {false, {}}};
  CHECK(failover::next_active(links, -1, t0, hold) == -1);  // nothing up
  links[1] = {true, t0};
  CHECK(failover::next_active(links, -1, t0, hold) == 1);  // eth comes up first: used at once
  links[0] = {true, t0 + 10ms};
  CHECK(failover::next_active(links, 1, t0 + 10ms, hold) == 1);          // pcie up, but not for long
  CHECK(failover::next_active(links, 1, t0 + 1009ms, hold) == 1);        // still within the hold
  CHECK(failover::next_active(links, 1, t0 + 1010ms, hold) == 0);        // fail back after it
  links[0].up = false;
  CHECK(failover::next_active(links, 0, t0 + 2s, hold) == 1);            // fail over at once
  links[1].up = false;
  CHECK(failover::next_active(links, 1, t0 + 2s, hold) == -1);           // peer unreachable
  // A less preferred link never takes over from an up preferred one.
  links = {{true, t0}, {true, t0}};
  CHECK(failover::next_active(links, 0, t0 + 5s, hold) == 0);
  // An index beyond the links (never happens; must not read past them) counts as down.
  CHECK(failover::next_active(links, 7, t0, hold) == 0);
  // Zero hold: back at once.
  links = {{true, t0}, {true, t0}};
  CHECK(failover::next_active(links, 1, t0, 0ms) == 0);
}

TEST_CASE("failover: a link is up while answered within the timeout, stale pongs prove nothing", "[bridge][failover]") {
  const auto t0 = failover::Clock::now();
  CHECK_FALSE(failover::link_up(false, t0, t0, 500ms));  // never answered
  CHECK(failover::link_up(true, t0, t0 + 499ms, 500ms));
  CHECK_FALSE(failover::link_up(true, t0, t0 + 500ms, 500ms));
  CHECK(failover::pong_proves_link(0, 500ms));
  CHECK(failover::pong_proves_link(500'000'000, 500ms));
  CHECK_FALSE(failover::pong_proves_link(500'000'001, 500ms));  // queued while the link was down
  CHECK_FALSE(failover::pong_proves_link(-1, 500ms));           // from the future: forged or a clock step
}

TEST_CASE("channel queues: bounded by hwm, drop oldest or newest, drops reported", "[bridge][channels]") {
  std::deque<int> q;
  int dropped = 0;
  for (int i = 1; i <= 5; ++i) dropped += datapath::push_bounded(q, int{i}, 3, DropPolicy::oldest);
  CHECK(dropped == 2);
  CHECK(q == std::deque<int>{3, 4, 5});  // the newest kept
  q.clear();
  dropped = 0;
  for (int i = 1; i <= 5; ++i) dropped += datapath::push_bounded(q, int{i}, 3, DropPolicy::newest);
  CHECK(dropped == 2);
  CHECK(q == std::deque<int>{1, 2, 3});  // what was queued kept
  q.clear();
  CHECK_FALSE(datapath::push_bounded(q, 9, 1, DropPolicy::oldest));
  CHECK(datapath::push_bounded(q, 10, 1, DropPolicy::oldest));
  CHECK(q == std::deque<int>{10});
}

TEST_CASE("channel sequence check: in order once, gaps counted, a restart starts over", "[bridge][channels]") {
  datapath::RxSequence rx;
  using H = wire::DataHeader;
  CHECK(rx.accept(H{7, 1}) == 0u);
  CHECK(rx.accept(H{7, 2}) == 0u);
  CHECK(rx.accept(H{7, 5}) == 2u);            // 3 and 4 lost
  CHECK_FALSE(rx.accept(H{7, 5}));            // a duplicate
  CHECK_FALSE(rx.accept(H{7, 4}));            // late data of an old link
  CHECK(rx.accept(H{8, 1}) == 0u);            // the peer restarted: a new instance
  CHECK(rx.accept(H{8, 2}) == 0u);
  CHECK(rx.accept(H{7, 100}) == 0u);          // another instance again: starts over, no loss counted
  datapath::RxSequence first;
  CHECK(first.accept(H{1, 42}) == 0u);        // joining mid-stream is not a loss
}

TEST_CASE("ZAP: only CURVE with a configured peer's public key, as that peer", "[bridge][security][curve]") {
  if (!curve_available()) LCMX_SKIP("this libzmq has no CURVE");
  const auto b = generate_key_pair(), stranger = generate_key_pair();
  PeerConfig peer;
  peer.name = "chipB";
  peer.public_key = b.public_key;
  const std::vector<PeerConfig> peers{peer};
  auto raw = [](const std::string& z85) {
    std::array<std::byte, 32> k{};
    REQUIRE(::zmq_z85_decode(reinterpret_cast<std::uint8_t*>(k.data()), z85.c_str()) != nullptr);
    return k;
  };
  const auto kb = raw(b.public_key), ks = raw(stranger.public_key);

  const auto ok = security::zap_decide("CURVE", kb, peers);
  CHECK(ok.status == "200");
  CHECK(ok.user == "chipB");
  CHECK(ok.key == b.public_key);

  const auto refused = security::zap_decide("CURVE", ks, peers);
  CHECK(refused.status == "400");
  CHECK(refused.user.empty());
  CHECK(refused.key == stranger.public_key);  // logged, so the operator sees who tried

  CHECK(security::zap_decide("NULL", {}, peers).status == "400");
  CHECK(security::zap_decide("PLAIN", kb, peers).status == "400");
  CHECK(security::zap_decide("CURVE", std::span<const std::byte>(kb.data(), 31), peers).status == "400");
  // A peer without a key (CURVE off in its config) is never matched by an empty key.
  PeerConfig keyless;
  keyless.name = "chipC";
  CHECK(security::zap_decide("CURVE", ks, {keyless}).status == "400");
}
