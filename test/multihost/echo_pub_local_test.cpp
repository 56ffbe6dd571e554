// `lcmx echo`, `lcmx hz`, `lcmx pub` across emulated hosts (UDP on the vehicle group) and on a
// host that looks like an ordinary computer (default route via a LAN, no multicast route, LCM's
// default URL) beside stock liblcm. The shm and lo-routed cases: test/integration/echo_pub_test.cpp.
#include <cmath>
#include <functional>
#include <optional>

#include "lcmx/test/catch_netns.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;

namespace {

const std::string kTypes = LCMX_LCMTYPES_DIR;

std::vector<std::string> json_lines(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);)
    if (!l.empty() && l[0] == '{') out.push_back(l);
  return out;
}

}  // namespace

TEST_CASE("lcmx echo, hz and pub across hosts over UDP (vehicle group)", "[multihost][tools]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 60);
  const auto ch = h.channel("ECHO_UDP");
  auto& pub = h.peer(0, {"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "100", "--subscribers",
                         "1", "--id", "A0"});
  REQUIRE(pub.expect("READY"));
  const auto e = h.run(1, {LCMX_TOOL, "echo", ch, "--types", kTypes, "--json", "-n", "3"}, h.lcmx_env(), 20000ms);
  INFO(e.out);
  CHECK(e.rc == 0);
  const auto objs = json_lines(e.out);
  REQUIRE(objs.size() == 3);
  for (const auto& o : objs) {
    CHECK(contains(o, "\"type\":\"lcmx_examples.pose_t\""));
    CHECK(contains(o, "\"frame_id\":\"A0\""));
  }
  auto& hz = h.spawn(1, {LCMX_TOOL, "hz", ch, "--json", "-w", "20", "--period", "0.25"}, h.lcmx_env());
  const auto r = json_until(hz, [](const std::string& j) { return json_num(j, "window") == 20; }, 15000ms);
  INFO(hz.text());
  REQUIRE(r);
  CHECK(std::abs(json_num(*r, "rate_hz") - 100) < 100 * 0.25);
  hz.signal(SIGINT);
  CHECK(hz.wait(5000ms) == 0);
  pub.send("quit");

  // lcmx pub on host 0 -> a typed subscriber on host 1, over UDP.
  const auto ch2 = h.channel("PUB_UDP");
  const int n = 10;
  auto& sub = h.peer(1, {"sub", "--channel", ch2, "--type", "pose", "--expect", std::to_string(n)});
  REQUIRE(sub.expect("READY"));
  auto& lp = h.spawn(0, {LCMX_TOOL, "pub", ch2, "lcmx_examples.pose_t", "-", "--types", kTypes, "-n", std::to_string(n),
                         "--rate", "100"},
                     h.lcmx_env(), true);
  for (int i = 0; i < n; ++i)
    lp.send(R"({"header": {"seq": )" + std::to_string(i) + R"(, "frame_id": "LP"}, "position": [)" + std::to_string(i) +
            R"(, 0, 0], "orientation": [0, 0, 0, 1]})");
  CHECK(lp.wait(15000ms) == 0);
  INFO(lp.text());
  const auto st = of(sub.read_summaries(15000ms), ch2);
  check_exact(st, n);
}

TEST_CASE("ordinary computer: lcmx echo decodes a stock liblcm publisher, lcmx pub --udp reaches a stock subscriber",
          "[multihost][local][tools]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(1, 61, Ordinary{});
  const auto ch = h.channel("ECHO_STOCK");
  auto& stock = h.lcm_peer(0, {"pub", kLcmDefaultUrl, ch, "2000", "100", "64", "ST"});
  REQUIRE(stock.expect("ready"));
  const auto e = h.run(0, {LCMX_TOOL, "echo", ch, "--types", kTypes, "--json", "-n", "3"}, h.lcmx_env(), 20000ms);
  INFO(e.out);
  CHECK(e.rc == 0);
  const auto objs = json_lines(e.out);
  REQUIRE(objs.size() == 3);
  for (const auto& o : objs) {
    CHECK(contains(o, "\"type\":\"lcmx_examples.bench_t\""));
    CHECK(json_num(o, "size") == 8 + 8 + 8 + 4 + 64);
  }
  // Each message once (the host-local group is joined on lo and on the LAN): seq increases by 1.
  CHECK(json_num(objs[1], "seq") == json_num(objs[0], "seq") + 1);
  CHECK(json_num(objs[2], "seq") == json_num(objs[1], "seq") + 1);
  stock.send("quit");

  const auto ch2 = h.channel("TO_STOCK");
  auto& stock_sub = h.lcm_peer(0, {"sub", kLcmDefaultUrl, ch2, "3", "20000"});
  REQUIRE(stock_sub.expect("ready"));
  auto& pub = h.spawn(0, {LCMX_TOOL, "pub", ch2, "lcmx_examples.bench_t", "-", "--types", kTypes, "--udp",
                          "--no-wait", "--rate", "100", "-n", "3"},
                      h.lcmx_env(), true);
  for (int i = 0; i < 3; ++i) pub.send(R"({"seq": )" + std::to_string(i) + "}");
  CHECK(pub.wait(10000ms) == 0);
  INFO(pub.text());
  const auto sum = stock_sub.read_summaries(15000ms);
  REQUIRE(sum.size() == 1);
  CHECK(sum[0].num("received") == 3);
  CHECK(sum[0].num("duplicates") == 0);
}
