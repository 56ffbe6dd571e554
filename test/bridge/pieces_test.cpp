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

TEST_CASE("ZAP without CURVE: only from a configured peer's address, as that peer", "[bridge][security]") {
  PeerConfig b, c;
  b.name = "chipB";
  b.endpoints = {{"pcie", "10.1.0.2"}, {"eth", "10.0.0.2"}};
  c.name = "chipC";
  c.endpoints = {{"eth", "10.0.0.3"}};
  const std::vector<PeerConfig> peers{b, c};
  for (const char* addr : {"10.1.0.2", "10.0.0.2"}) {
    const auto ok = security::zap_decide("NULL", {}, addr, false, peers);
    CHECK(ok.status == "200");
    CHECK(ok.user == "chipB");  // the name its messages must claim
  }
  CHECK(security::zap_decide("NULL", {}, "10.0.0.3", false, peers).user == "chipC");
  // A LAN machine that is not part of the robot.
  const auto lan = security::zap_decide("NULL", {}, "10.0.0.99", false, peers);
  CHECK(lan.status == "400");
  CHECK(lan.user.empty());
  CHECK(lan.reason == "not an address of a configured peer");
  CHECK(security::zap_decide("NULL", {}, "", false, peers).status == "400");
  CHECK(security::zap_decide("PLAIN", {}, "10.0.0.2", false, peers).status == "400");
  CHECK(security::zap_decide("NULL", {}, "10.0.0.2", false, {}).status == "400");  // no peers: nobody
}

TEST_CASE("ZAP with CURVE: only a configured peer's public key, from that peer's address, as that peer",
          "[bridge][security][curve]") {
  if (!curve_available()) LCMX_SKIP("this libzmq has no CURVE");
  const auto b = generate_key_pair(), stranger = generate_key_pair(), kc = generate_key_pair();
  PeerConfig peer, other;
  peer.name = "chipB";
  peer.public_key = b.public_key;
  peer.endpoints = {{"eth", "10.0.0.2"}};
  other.name = "chipC";
  other.public_key = kc.public_key;
  other.endpoints = {{"eth", "10.0.0.3"}};
  const std::vector<PeerConfig> peers{peer, other};
  auto raw = [](const std::string& z85) {
    std::array<std::byte, 32> k{};
    REQUIRE(::zmq_z85_decode(reinterpret_cast<std::uint8_t*>(k.data()), z85.c_str()) != nullptr);
    return k;
  };
  const auto kb = raw(b.public_key), ks = raw(stranger.public_key);

  const auto ok = security::zap_decide("CURVE", kb, "10.0.0.2", true, peers);
  CHECK(ok.status == "200");
  CHECK(ok.user == "chipB");
  CHECK(ok.key == b.public_key);

  const auto refused = security::zap_decide("CURVE", ks, "10.0.0.2", true, peers);
  CHECK(refused.status == "400");
  CHECK(refused.user.empty());
  CHECK(refused.key == stranger.public_key);  // logged, so the operator sees who tried
  CHECK(refused.reason == "public key " + stranger.public_key + " is not a configured peer's");

  // B's key from C's address (or a LAN machine's): a stolen key is not enough.
  for (const char* addr : {"10.0.0.3", "10.0.0.99"}) {
    const auto elsewhere = security::zap_decide("CURVE", kb, addr, true, peers);
    CHECK(elsewhere.status == "400");
    CHECK(elsewhere.reason == "the key is chipB's, but " + std::string(addr) + " is not one of chipB's addresses");
  }

  CHECK(security::zap_decide("NULL", {}, "10.0.0.2", true, peers).status == "400");  // CURVE required
  CHECK(security::zap_decide("PLAIN", kb, "10.0.0.2", true, peers).status == "400");
  CHECK(security::zap_decide("CURVE", std::span<const std::byte>(kb.data(), 31), "10.0.0.2", true, peers).status ==
        "400");
  // A peer without a key (CURVE off in its config) is never matched by an empty key.
  PeerConfig keyless;
  keyless.name = "chipD";
  keyless.endpoints = {{"eth", "10.0.0.4"}};
  CHECK(security::zap_decide("CURVE", ks, "10.0.0.4", true, {keyless}).status == "400");
}
