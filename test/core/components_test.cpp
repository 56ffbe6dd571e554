// core's components, each alone (core/src: the private headers of the runtime's components).
#include <arpa/inet.h>

#include <catch2/catch.hpp>
#include <thread>

#include "peers.hpp"
#include "replays.hpp"
#include "topic_policy.hpp"

using lcmx::detail::PeerTable;
using lcmx::detail::Replays;
using lcmx::detail::Scope;
using Change = lcmx::discovery::Change;

namespace {

lcmx_msgs::endpoint_t endpoint(std::int64_t id, std::int8_t kind, const std::string& topic) {
  lcmx_msgs::endpoint_t e{};
  e.id = id;
  e.kind = kind;
  e.node = "n";
  e.topic = topic;
  e.type_name = "t";
  e.fingerprint = 42;
  return e;
}

lcmx_msgs::beacon_t beacon(std::int64_t id, const std::string& local, std::vector<lcmx_msgs::endpoint_t> es) {
  lcmx_msgs::beacon_t b{};
  b.participant_id = id;
  b.process_name = "p";
  b.local_source = local;
  b.endpoints = std::move(es);
  b.num_endpoints = static_cast<std::int32_t>(b.endpoints.size());
  return b;
}

lcmx::udpm::Source src(const char* a, int port) {
  lcmx::udpm::Source s{};
  ::inet_pton(AF_INET, a, &s.address_be);
  s.port_be = htons(static_cast<std::uint16_t>(port));
  return s;
}

constexpr auto kPub = lcmx_msgs::endpoint_t::KIND_PUBLISHER;
constexpr auto kSub = lcmx_msgs::endpoint_t::KIND_SUBSCRIBER;

}  // namespace

TEST_CASE("PeerTable: a beacon that only refreshes statistics is no structural change, a new endpoint is, with "
          "its topics",
          "[components]") {
  PeerTable t;
  auto b = beacon(7, "127.0.0.1:5000", {endpoint(1, kPub, "A"), endpoint(2, kSub, "B")});
  auto d = t.apply(Scope::host, Change::joined, b);
  CHECK(d.structural);
  CHECK(d.publisher_topics == std::set<std::string>{"A"});
  CHECK(d.subscriber_topics == std::set<std::string>{"B"});
  b.endpoints[0].messages = 100;  // traffic
  b.endpoints[0].rate_hz = 10;
  b.revision = 99;                // a revision alone changes nothing matching reads
  d = t.apply(Scope::host, Change::updated, b);
  CHECK_FALSE(d.structural);
  b.endpoints.push_back(endpoint(3, kPub, "C"));
  b.num_endpoints = 3;
  d = t.apply(Scope::host, Change::updated, b);
  CHECK(d.structural);
  CHECK(d.publisher_topics == std::set<std::string>{"A", "C"});
  CHECK(t.endpoints_on("C", kPub).size() == 1);
  CHECK(t.endpoints_on("A", kSub).empty());
  d = t.apply(Scope::host, Change::left, b);
  CHECK(d.structural);
  CHECK(t.endpoints_on("A", kPub).empty());
  CHECK_FALSE(t.announced(7, 1));
}

TEST_CASE("PeerTable: senders by address - the socket, the mirror's port from another local address, a same-host "
          "participant, a stranger",
          "[components]") {
  PeerTable t;
  t.apply(Scope::host, Change::joined, beacon(7, "127.0.0.1:5000", {endpoint(1, kPub, "A")}));
  auto n = beacon(8, "127.0.0.1:6000", {endpoint(1, kPub, "A")});
  n.host_id = 5;
  t.apply(Scope::neighbour, Change::joined, n);
  auto v = beacon(9, "127.0.0.1:7000", {endpoint(1, kPub, "A")});
  v.vehicle_source = "10.0.0.2:7001";
  t.apply(Scope::vehicle, Change::joined, v);

  auto s = t.sender(false, src("127.0.0.1", 5000), true);
  CHECK(s.participant == 7);
  CHECK(s.same_host);
  s = t.sender(false, src("192.168.1.5", 5000), true);  // its mirror, from the routed interface
  CHECK(s.participant == 7);
  s = t.sender(false, src("192.168.1.5", 5000), false);  // the same port from elsewhere: nobody
  CHECK(s.participant == 0);
  s = t.sender(false, src("127.0.0.1", 6000), true);
  CHECK(s.participant == 8);
  CHECK_FALSE(s.same_host);
  s = t.sender(true, src("10.0.0.2", 7001), false);
  CHECK(s.participant == 9);
  CHECK(t.sender(true, src("10.0.0.3", 7001), false).participant == 0);
  CHECK(t.source_of(9, true) == src("10.0.0.2", 7001));
  CHECK_FALSE(t.source_of(10, true).has_value());
}

TEST_CASE("Replays: a subscriber endpoint gets one replay per lease, a publisher sends at most kMaxPerLease per "
          "lease and the others wait (forged beacons rotating endpoint ids)",
          "[components]") {
  Replays r(std::chrono::milliseconds(200));
  CHECK(r.queue({1, 100, 1, true}));
  CHECK_FALSE(r.queue({1, 100, 1, true}));  // the same subscriber again within the lease
  CHECK(r.refused() == 1);
  CHECK(r.queue({2, 100, 1, true}));        // another publisher
  for (std::int64_t e = 2; e < 100; ++e) CHECK(r.queue({1, 100, e, true}));
  CHECK(r.ready() == Replays::kMaxPerLease + 1);  // publisher 1's budget, and publisher 2's one
  CHECK(r.waiting() == 99 - Replays::kMaxPerLease);
  r.tick();  // the lease has not passed: nothing more
  CHECK(r.ready() == Replays::kMaxPerLease + 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(250));  // the lease itself is what is tested
  r.tick();
  CHECK(r.ready() == 2 * Replays::kMaxPerLease + 1);
  CHECK(r.waiting() == 99 - 2 * Replays::kMaxPerLease);
  CHECK(r.queue({1, 100, 1, true}));  // a lease later, the same subscriber may have one again
}

TEST_CASE("TopicPolicy: configured classes win, a bridge's globs make topics large, mirror globs", "[components]") {
  lcmx::RuntimeOptions o;
  o.topic_class["FORCED"] = lcmx::TopicClass::small;
  o.mirror_channels = {"CAM_*"};
  lcmx::detail::TopicPolicy p(o);
  CHECK(p.class_of("X") == lcmx::TopicClass::automatic);
  CHECK(p.set_bridges(true, {"IMG*", "FORCED"}));
  CHECK(p.bridge_on_host());
  CHECK(p.class_of("IMG_1") == lcmx::TopicClass::large);
  CHECK(p.class_of("FORCED") == lcmx::TopicClass::small);
  CHECK_FALSE(p.set_bridges(true, {}));
  CHECK(p.mirrored("CAM_1"));
  CHECK_FALSE(p.mirrored("POSE"));
  lcmx::RuntimeOptions bad;
  bad.mirror_channels = {""};
  CHECK_THROWS_AS(lcmx::detail::TopicPolicy(bad), lcmx::Error);
}
