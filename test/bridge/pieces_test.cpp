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

namespace {
using Order = datapath::RxOrder<int>;
using H = wire::DataHeader;
// Pushes message `seq` of instance `inst` from `socket` (its payload: seq) and returns what came out.
Order::Out push(Order& rx, std::uint64_t inst, std::uint64_t seq, const char* socket, int link = 0,
                Order::Clock::time_point now = Order::Clock::time_point{}) {
  Order::Out out;
  rx.push(H{inst, seq}, socket, link, static_cast<int>(seq), now, out);
  return out;
}
}  // namespace

TEST_CASE("channel order: in order once, a gap on the same socket lost at once, a restart starts over",
          "[bridge][channels]") {
  Order rx(4, 600ms);
  CHECK(push(rx, 7, 1, "A/x").deliver == std::vector<int>{1});
  CHECK(push(rx, 7, 2, "A/x").deliver == std::vector<int>{2});
  auto o = push(rx, 7, 5, "A/x");  // 3 and 4 were on this socket, which delivers in order: lost
  CHECK(o.deliver == std::vector<int>{5});
  CHECK(o.lost == 2u);
  o = push(rx, 7, 5, "A/x");  // a duplicate
  CHECK(o.deliver.empty());
  CHECK(o.stale == 1u);
  CHECK(push(rx, 7, 4, "A/y").stale == 1u);  // late data of a gap given up on
  CHECK(push(rx, 8, 1, "A/z").deliver == std::vector<int>{1});  // the peer restarted: a new instance
  CHECK(push(rx, 8, 2, "A/z").deliver == std::vector<int>{2});
  o = push(rx, 7, 100, "A/x");  // another instance again: starts over, no loss counted
  CHECK(o.deliver == std::vector<int>{100});
  CHECK(o.lost == 0u);
  Order first(4, 600ms);
  o = push(first, 1, 42, "A/x");  // joining mid-stream is not a loss
  CHECK(o.deliver == std::vector<int>{42});
  CHECK(o.lost == 0u);
  CHECK_FALSE(first.holding());
}

TEST_CASE("channel order: after a switch the new socket's messages wait for the old socket's, none lost",
          "[bridge][channels][failover]") {
  // A planned fail-back: 1..3 went over eth (socket E), then the sender moved to pcie (socket
  // P); 4 and 5 are still on their way over eth when 6 and 7 arrive over pcie.
  Order rx(4, 600ms);
  const auto t0 = Order::Clock::now();
  for (std::uint64_t s = 1; s <= 3; ++s) push(rx, 7, s, "A/E", 1, t0);
  CHECK(rx.last_link() == 1);
  CHECK(push(rx, 7, 6, "A/P", 0, t0).deliver.empty());
  CHECK(push(rx, 7, 7, "A/P", 0, t0).deliver.empty());
  CHECK(rx.holding());
  CHECK(rx.held() == 2u);
  CHECK(rx.due() == t0 + 600ms);
  Order::Out o;
  rx.expire(t0 + 599ms, false, o);  // not yet due
  CHECK(o.deliver.empty());
  CHECK(push(rx, 7, 4, "A/E", 1, t0).deliver == std::vector<int>{4});
  o = push(rx, 7, 5, "A/E", 1, t0);
  CHECK(o.deliver == std::vector<int>{5, 6, 7});
  CHECK(o.lost == 0u);
  CHECK_FALSE(rx.holding());
  CHECK(rx.last_link() == 0);
  CHECK(push(rx, 7, 8, "A/P", 0, t0).deliver == std::vector<int>{8});
}

TEST_CASE("channel order: a gap that never fills is given up on when due, when its link is down, or when full",
          "[bridge][channels][failover]") {
  const auto t0 = Order::Clock::now();
  {  // due: what was in flight on the dead link is counted lost once, then arrives too late
    Order rx(4, 600ms);
    push(rx, 7, 1, "A/P", 0, t0);
    push(rx, 7, 5, "A/E", 1, t0 + 10ms);
    push(rx, 7, 6, "A/E", 1, t0 + 20ms);
    Order::Out o;
    rx.expire(t0 + 610ms, false, o);
    CHECK(o.deliver == std::vector<int>{5, 6});
    CHECK(o.lost == 3u);
    CHECK_FALSE(rx.holding());
    CHECK(push(rx, 7, 3, "A/P", 0, t0).stale == 1u);
  }
  {  // the old socket's link is down (force): at once
    Order rx(4, 600ms);
    push(rx, 7, 1, "A/P", 0, t0);
    push(rx, 7, 3, "A/E", 1, t0);
    Order::Out o;
    rx.expire(t0, true, o);
    CHECK(o.deliver == std::vector<int>{3});
    CHECK(o.lost == 1u);
  }
  {  // more than `cap` held: bounded memory, so given up on
    Order rx(2, 600ms);
    push(rx, 7, 1, "A/P", 0, t0);
    CHECK(push(rx, 7, 4, "A/E", 1, t0).deliver.empty());
    CHECK(push(rx, 7, 5, "A/E", 1, t0).deliver.empty());
    auto o = push(rx, 7, 7, "A/E", 1, t0);  // (6: lost too)
    CHECK(o.deliver == std::vector<int>{4, 5, 7});
    CHECK(o.lost == 3u);
    CHECK_FALSE(rx.holding());
  }
  {  // the held socket goes on beyond a gap of its own: the gap below it is given up on
    Order rx(8, 600ms);
    push(rx, 7, 1, "A/P", 0, t0);
    push(rx, 7, 4, "A/E", 1, t0);       // held: 2, 3 may come over P
    auto o = push(rx, 7, 2, "A/P", 0, t0);
    CHECK(o.deliver == std::vector<int>{2});
    o = push(rx, 7, 6, "A/P", 0, t0);  // P delivers in order: 3 and 5 are not on it
    CHECK(o.deliver == std::vector<int>{4, 6});
    CHECK(o.lost == 2u);
    CHECK_FALSE(rx.holding());
  }
  {  // a restart while holding: the old instance's gap never fills
    Order rx(8, 600ms);
    push(rx, 7, 1, "A/P", 0, t0);
    push(rx, 7, 3, "A/E", 1, t0);
    auto o = push(rx, 9, 1, "A/Q", 0, t0);
    CHECK(o.deliver == std::vector<int>{3, 1});
    CHECK(o.lost == 1u);
  }
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
