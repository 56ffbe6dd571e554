// `lcmx monitor` (--once --json, the same model as on a terminal) and `lcmx graph` on emulated
// hosts: an ordinary computer (default route via a LAN, no multicast route to lo, default
// options) with stock liblcm and lcmx shm publishers, and two hosts on a vehicle group (UDP).
// The terminal itself is driven in test/integration/monitor_graph_test.cpp.
#include <regex>

#include "lcmx/test/catch_netns.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;

TEST_CASE("ordinary computer: lcmx monitor and lcmx graph see stock liblcm and lcmx shm publishers",
          "[multihost][local][tools]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(1, 45, Ordinary{});
  const auto stock = h.channel("MON_STOCK"), shm = h.channel("MON_SHM");
  auto& lcm = h.lcm_peer(0, {"pub", kLcmDefaultUrl, stock, "100000", "20", "64", "ST"});
  REQUIRE(lcm.expect("ready"));
  auto& pub = h.peer(0, {"pub", "--channel", shm, "--type", "bench", "--count", "0", "--rate", "50", "--size", "32"});
  REQUIRE(pub.expect("READY"));
  const auto mon = h.run(0, {LCMX_TOOL, "monitor", "--once", "--json", "--duration", "2"}, h.lcmx_env(), 20000ms);
  INFO(mon.out);
  CHECK(mon.rc == 0);
  CHECK(std::regex_search(mon.out, std::regex("\\{\"channel\":\"" + stock +
                                              "\",\"type\":\"0x[0-9a-f]{16}\",\"publishers\":\"LCM sender\","
                                              "\"paths\":\"udp\",\"hz\":[1-9]")));
  CHECK(std::regex_search(mon.out, std::regex("\\{\"channel\":\"" + shm +
                                              "\",\"type\":\"bench_t\",\"publishers\":\"lcmx_test_peer\\[[0-9]+\\]@[0-9a-f]{4}\","
                                              "\"paths\":\"shm\",\"hz\":[1-9]")));
  auto& sub = h.peer(0, {"sub", "--channel", shm, "--type", "bench", "--publishers", "1"});
  REQUIRE(sub.expect("MATCHED", 10000ms));
  const auto graph = h.run(0, {LCMX_TOOL, "graph", "--json"}, h.lcmx_env(), 15000ms);
  INFO(graph.out);
  CHECK(graph.rc == 0);
  CHECK(graph.out.find("{\"topic\":\"" + shm + "\",\"type\":\"bench_t\",\"pairs\":[{\"publisher\":\"lcmx_test_peer[") !=
        std::string::npos);
  CHECK(graph.out.find("\"path\":\"shm\"") != std::string::npos);
}

TEST_CASE("two hosts on a vehicle group: lcmx monitor and graph on one host see the other's publisher over UDP",
          "[multihost][tools]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 46);
  const auto ch = h.channel("MON_REMOTE");
  auto& pub = h.peer(1, {"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "30"});
  REQUIRE(pub.expect("READY"));
  auto& sub = h.peer(0, {"sub", "--channel", ch, "--type", "pose", "--publishers", "1"});
  REQUIRE(sub.expect("MATCHED", 10000ms));
  const auto mon = h.run(0, {LCMX_TOOL, "monitor", "--once", "--json", "--duration", "2"}, h.lcmx_env(), 20000ms);
  INFO(mon.out);
  CHECK(mon.rc == 0);
  CHECK(std::regex_search(mon.out, std::regex("\\{\"channel\":\"" + ch +
                                              "\",\"type\":\"pose_t\",\"publishers\":\"lcmx_test_peer\\[[0-9]+\\]@[0-9a-f]{4}\","
                                              "\"paths\":\"udp\",\"hz\":[1-9]")));
  const auto graph = h.run(0, {LCMX_TOOL, "graph"}, h.lcmx_env(), 15000ms);
  INFO(graph.out);
  CHECK(graph.rc == 0);
  std::size_t hosts = 0;
  for (auto at = graph.out.find("subgraph \"cluster_host_"); at != std::string::npos;
       at = graph.out.find("subgraph \"cluster_host_", at + 1))
    ++hosts;
  CHECK(hosts == 2);
  CHECK(graph.out.find("[label=\"udp from lcmx_test_peer[") != std::string::npos);
}
