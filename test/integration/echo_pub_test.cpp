// `lcmx echo`, `lcmx hz`, `lcmx bw`, `lcmx pub` against live publishers in other processes:
// lcmx peers over shared memory, this process's own raw publisher of damaged messages, and
// stock liblcm in a network namespace on LCM's default URL. (UDP across emulated hosts and
// ordinary computers: test/multihost/echo_pub_local_test.cpp; the bridge: test/bridge/bridge_test.cpp.)
#include <sys/stat.h>

#include <cmath>
#include <fstream>

#include "lcmx/core.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "support.hpp"

using namespace lcmx::it;

namespace {

const std::string kTypes = LCMX_LCMTYPES_DIR;

std::vector<std::string> lines_of(const std::string& text, const std::string& prefix = "") {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);)
    if (l.rfind(prefix, 0) == 0) out.push_back(l);
  return out;
}


}  // namespace

TEST_CASE("lcmx echo decodes a shm publisher's messages: text, --json, --field, -n", "[integration][tools]") {
  Session s(120);
  const std::string ch = unique_channel("ECHO", 120);
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "200", "--subscribers",
                      "1", "--id", "E1"});
  REQUIRE(pub.expect("READY"));

  // --json, by a glob, exits after -n messages.
  const auto j = s.run({LCMX_TOOL, "echo", "IT_ECHO_*", "--types", kTypes, "--json", "-n", "3"});
  INFO(j.out);
  CHECK(j.rc == 0);
  const auto objs = lines_of(j.out, "{");
  REQUIRE(objs.size() == 3);
  for (const auto& o : objs) {
    CHECK(contains(o, "\"channel\":\"" + ch + "\""));
    CHECK(contains(o, "\"type\":\"lcmx_examples.pose_t\""));
    CHECK(contains(o, "\"frame_id\":\"E1\""));
    CHECK(contains(o, "\"orientation\":[0,0,0,1]"));
    CHECK(json_num(o, "size") == lcmx_examples::pose_t().getEncodedSize() + 2);  // frame_id "E1"
  }
  // Messages of one publisher arrive in order.
  CHECK(json_num(objs[1], "seq") > json_num(objs[0], "seq"));

  // Text (default) and --field.
  const auto t = s.run({LCMX_TOOL, "echo", ch, "--types", kTypes, "-n", "2"});
  INFO(t.out);
  CHECK(t.rc == 0);
  CHECK(lines_of(t.out, "--- " + ch).size() == 2);
  CHECK(contains(t.out, "  frame_id: \"E1\""));
  CHECK(contains(t.out, "lcmx_examples.pose_t"));
  const auto f = s.run({LCMX_TOOL, "echo", ch, "--types", kTypes, "-n", "2", "--field", "orientation[3]", "--no-header"});
  INFO(f.out);
  CHECK(lines_of(f.out, "orientation[3]: 1").size() == 2);
  // --raw needs no types: the fingerprint's bytes come first.
  const auto r = s.run({LCMX_TOOL, "echo", ch, "--raw", "-n", "1"}, {"LCMX_TYPES_PATH"});
  INFO(r.out);
  char fp[64];
  const auto h = static_cast<unsigned long long>(lcmx_examples::pose_t::getHash());
  std::snprintf(fp, sizeof fp, "  000000  %02llx %02llx", h >> 56, (h >> 48) & 0xff);
  CHECK(contains(r.out, fp));
  // Until SIGINT: a clean exit.
  auto& live = s.spawn({LCMX_TOOL, "echo", ch, "--types", kTypes, "--max-array", "2"});
  REQUIRE(live.expect("orientation: [0, 0, ... (2 more)]"));
  live.signal(SIGINT);
  CHECK(live.wait(5000ms) == 0);
  // LCMX_TYPES_PATH instead of --types; a field that does not exist is shown per message.
  const auto e = s.run({LCMX_TOOL, "echo", ch, "-n", "1", "--field", "header.nope"}, {"LCMX_TYPES_PATH=" + kTypes});
  INFO(e.out);
  CHECK(e.rc == 0);
  CHECK(contains(e.out, "no field 'nope' in header"));
  pub.send("quit");
}

TEST_CASE("lcmx echo shows unknown, truncated and garbage messages and never crashes", "[integration][tools]") {
  Session s(121);
  const std::string ch = unique_channel("BAD", 121);
  auto& echo = s.spawn({LCMX_TOOL, "echo", ch, "--types", kTypes, "--json", "-n", "5"}, {}, false);
  // This process publishes raw bytes: whatever it likes.
  auto rt = lcmx::Runtime::create(lcmx::RuntimeOptions::from_env());
  auto node = rt.create_node("bad");
  auto pub = node.advertise_raw(ch);
  REQUIRE(pub.wait_for_subscribers(1, 10000ms));
  lcmx_examples::pose_t pose;
  pose.header.frame_id = "ok";
  std::vector<std::byte> good(static_cast<std::size_t>(pose.getEncodedSize()));
  pose.encode(good.data(), 0, static_cast<int>(good.size()));
  std::vector<std::vector<std::byte>> msgs;
  msgs.emplace_back(good.begin(), good.begin() + 30);        // truncated
  msgs.emplace_back(good.begin(), good.begin() + 5);         // shorter than a fingerprint
  msgs.emplace_back(good);                                  // ... then garbage after it:
  msgs.back().insert(msgs.back().end(), 13, std::byte{0xab});
  msgs.push_back(std::vector<std::byte>(40, std::byte{0x5a}));  // unknown fingerprint
  msgs.emplace_back(good);                                  // and a good one at last
  for (const auto& m : msgs) pub.publish(m);
  const int rc = echo.wait(10000ms);
  INFO(echo.text());
  CHECK(rc == 0);
  const auto out = lines_of(echo.text(), "{");
  REQUIRE(out.size() == 5);
  CHECK(contains(out[0], "\"size\":30"));
  CHECK(contains(out[0], "\"type\":\"lcmx_examples.pose_t\""));
  CHECK(contains(out[0], "\"error\":\"decode: header.frame_id: message truncated"));
  CHECK(contains(out[1], "\"size\":5,\"error\":\"too short for an LCM message"));
  CHECK(contains(out[2], "13 trailing bytes after a lcmx_examples.pose_t"));
  CHECK(contains(out[3], "\"fingerprint\":\"0x5a5a5a5a5a5a5a5a\""));
  CHECK(contains(out[3], "unknown type: no type in the type path has this fingerprint"));
  CHECK(contains(out[4], "\"frame_id\":\"ok\""));
}

TEST_CASE("lcmx echo and pub: bad .lcm files and bad arguments are errors that say why", "[integration][tools]") {
  Session s(122);
  TmpDir d;
  const auto bad = d.write("bad.lcm", "package p;\nstruct s_t {\n  int32_t x\n}\n");
  const auto e = s.run({LCMX_TOOL, "echo", "X", "--types", bad});
  CHECK(e.rc == 1);
  CHECK(contains(e.out, bad + ":4:1:"));
  const auto missing = s.run({LCMX_TOOL, "echo", "X", "--types", d.path + "/nothing"});
  CHECK(missing.rc == 1);
  CHECK(contains(missing.out, "nothing"));
  const auto rx = s.run({LCMX_TOOL, "hz", "(", "--regex"});
  CHECK(rx.rc == 2);
  CHECK(contains(rx.out, "bad channel expression"));
  const std::string ch = unique_channel("PUBERR", 122);
  auto p = s.run({LCMX_TOOL, "pub", ch, "lcmx_examples.pose_t", R"({"position": [1, 2, 3], "orientaton": []})",
                  "--types", kTypes, "--once"});
  CHECK(p.rc == 1);
  CHECK(contains(p.out, "from_json: orientaton: no such field in lcmx_examples.pose_t"));
  p = s.run({LCMX_TOOL, "pub", ch, "pose_t", "{}", "--types", kTypes, "--once"});
  CHECK(p.rc == 1);
  CHECK(contains(p.out, "unknown type 'pose_t'"));
  CHECK(contains(p.out, "did you mean lcmx_examples.pose_t?"));
  p = s.run({LCMX_TOOL, "pub", ch, "lcmx_examples.pose_t", R"({"header": {"seq": "x"}})", "--types", kTypes, "--once"});
  CHECK(p.rc == 1);
  CHECK(contains(p.out, "header.seq: expected an integer (int64_t), got a string"));
  for (const char* verb : {"echo", "hz", "bw", "pub"}) {
    const auto h = s.run({LCMX_TOOL, verb, "--help"});
    CHECK(h.rc == 0);
    CHECK(contains(h.out, "Usage"));
  }
}

TEST_CASE("lcmx pub: typed shm subscribers receive JSON lines in order - --once without subscribers",
          "[integration][tools]") {
  Session s(123);
  const std::string ch = unique_channel("PUB", 123);
  const int n = 20;
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose", "--expect", std::to_string(n)});
  REQUIRE(sub.expect("READY"));
  auto& pub = s.spawn({LCMX_TOOL, "pub", ch, "lcmx_examples.pose_t", "--types", kTypes, "--rate", "200", "-n",
                       std::to_string(n)},
                      {}, true);
  for (int i = 0; i < n; ++i)
    pub.send(R"({"header": {"seq": )" + std::to_string(i) + R"(, "frame_id": "P1"}, "position": [)" +
             std::to_string(i) + R"(, 0, 0], "orientation": [0, 0, 0, 1]})");
  CHECK(pub.wait(15000ms) == 0);
  INFO(pub.text());
  const auto sum = sub.read_summaries(10000ms);
  REQUIRE(sum.size() == 1);
  CHECK(sum[0].num("received") == n);
  CHECK(sum[0].num("first") == 0);
  CHECK(sum[0].num("last") == n - 1);
  CHECK(sum[0].num("bad_content") == 0);
  CHECK(sum[0].num("out_of_order") == 0);
  CHECK(sum[0].num("duplicates") == 0);
  CHECK(contains(pub.text(), "published 20 messages"));

  // Nobody subscribed: it says so after --wait-timeout, publishes anyway, exits.
  const auto lonely = s.run({LCMX_TOOL, "pub", ch + "_NOBODY", "lcmx_examples.pose_t", "{}", "--types", kTypes,
                             "--once", "--wait-timeout", "0.3", "--json"});
  CHECK(lonely.rc == 0);
  CHECK(contains(lonely.out, "0 of 1 subscribers after 0.3 s; publishing anyway"));
  CHECK(contains(lonely.out, "published 1 message"));
  CHECK_FALSE(contains(lonely.out, "published 1 messages"));
  // --json: the summary line for scripts.
  const auto j = json_line(lonely.out);
  CHECK(contains(j, "\"channel\":\"" + ch + "_NOBODY\""));
  CHECK(contains(j, "\"type\":\"lcmx_examples.pose_t\""));
  CHECK(json_num(j, "published") == 1);
  CHECK(json_num(j, "subscribers") == 0);
  CHECK(contains(j, "\"ok\":true"));
  // A bad stdin line stops it, naming the line.
  auto& bad = s.spawn({LCMX_TOOL, "pub", ch + "_BAD", "lcmx_examples.pose_t", "-", "--types", kTypes, "--no-wait"},
                      {}, true);
  bad.send("{}");
  bad.send(R"({"header": {"frame": "x"}})");
  CHECK(bad.wait(10000ms) == 1);
  CHECK(contains(bad.text(), "stdin line 2: from_json: header.frame: no such field in lcmx_examples.header_t"));
}

TEST_CASE("lcmx hz and bw: a 30 Hz camera of 6 MB images reads 30 Hz over shm, several channels, SIGINT",
          "[integration][tools]") {
  Session s(124, 40000ms);
  const std::string fast = unique_channel("HZ_FAST", 124), slow = unique_channel("HZ_SLOW", 124);
  // lcmx pub keeps absolute deadlines: 30 Hz of 6 MB images (zero-filled to "size") and 10 Hz
  // of small ones.
  auto& p1 = s.spawn({LCMX_TOOL, "pub", fast, "lcmx_examples.image_t", R"({"size": 6000000})", "--types", kTypes,
                      "--rate", "30", "--wait-subscribers", "2"},
                     {}, true);
  auto& p2 = s.spawn({LCMX_TOOL, "pub", slow, "lcmx_examples.image_t", R"({"size": 1000})", "--types", kTypes,
                      "--rate", "10", "--wait-subscribers", "1"},
                     {}, true);
  auto& hz = s.spawn({LCMX_TOOL, "hz", "IT_HZ_*_" + std::to_string(::getpid()) + "_124", "--json", "-w", "20",
                      "--period", "0.25"});
  auto& bw = s.spawn({LCMX_TOOL, "bw", fast, "--json", "-w", "20", "--period", "0.25"});
  // A full window of each channel.
  auto full = [](const std::string& channel) {
    return [channel](const std::string& j) { return contains(j, "\"" + channel + "\"") && json_num(j, "window") == 20; };
  };
  const auto hf = json_until(hz, full(fast), 20000ms);
  INFO(hz.text() << p1.text());
  REQUIRE(hf);
  CHECK(std::abs(json_num(*hf, "rate_hz") - 30) < 30 * 0.15);
  CHECK(json_num(*hf, "period_min_s") <= 1.0 / 30);
  CHECK(json_num(*hf, "period_max_s") >= 1.0 / 30);
  const auto hs = json_until(hz, [&](const std::string& j) { return contains(j, "\"" + slow + "\"") && json_num(j, "window") >= 8; },
                             20000ms);
  REQUIRE(hs);
  CHECK(std::abs(json_num(*hs, "rate_hz") - 10) < 10 * 0.2);
  const auto b = json_until(bw, full(fast), 20000ms);
  INFO(bw.text());
  REQUIRE(b);
  const double size = json_num(*b, "size_max");
  CHECK(size > 6000000);
  CHECK(size < 6000100);
  CHECK(json_num(*b, "size_min") == size);
  CHECK(std::abs(json_num(*b, "bytes_per_s") - 30 * size) < 30 * size * 0.15);
  // SIGINT and SIGTERM end them cleanly.
  hz.signal(SIGINT);
  bw.signal(SIGTERM);
  p1.signal(SIGINT);
  CHECK(hz.wait(5000ms) == 0);
  CHECK(bw.wait(5000ms) == 0);
  CHECK(p1.wait(5000ms) == 0);
  CHECK(contains(p1.text(), "lcmx pub: published"));
  p2.signal(SIGTERM);
  CHECK(p2.wait(5000ms) == 0);
}

TEST_CASE("lcmx echo, hz and pub --udp with stock liblcm on LCM's default URL", "[integration][tools]") {
  Session s(125, 40000ms);
  Netns ns;
  REQUIRE_NETNS_OR_SKIP(ns);
  const std::string ch = unique_channel("STOCK", 125);
  auto in_ns = [&](std::vector<std::string> argv) {
    argv.insert(argv.begin(), {LCMX_IP, "netns", "exec", ns.name()});
    return argv;
  };
  const std::vector<std::string> env = {"LCMX_DISCOVERY_URL", "LCM_DEFAULT_URL"};  // the defaults
  // A stock publisher of bench_t at 50 Hz (lcmx_mh_lcm_peer: liblcm).
  auto& stock = s.spawn(in_ns({LCMX_LCM_PEER, "pub", kLcmDefaultUrl, ch, "2000", "50", "100", "ST"}));
  REQUIRE(stock.expect("ready"));
  auto& echo = s.spawn(in_ns({LCMX_TOOL, "echo", ch, "--types", kTypes, "--json", "-n", "3"}), env);
  CHECK(echo.wait(15000ms) == 0);
  const auto out = lines_of(echo.text(), "{");
  INFO(echo.text());
  REQUIRE(out.size() == 3);
  for (const auto& o : out) {
    CHECK(contains(o, "\"type\":\"lcmx_examples.bench_t\""));
    CHECK(json_num(o, "size") == 8 + 8 + 8 + 4 + 100);
  }
  auto& hz = s.spawn(in_ns({LCMX_TOOL, "hz", ch, "--json", "-w", "10", "--period", "0.25"}), env);
  const auto r = json_until(hz, [](const std::string& j) { return json_num(j, "window") == 10; }, 15000ms);
  INFO(hz.text());
  REQUIRE(r);
  CHECK(std::abs(json_num(*r, "rate_hz") - 50) < 50 * 0.25);
  hz.signal(SIGINT);
  CHECK(hz.wait(5000ms) == 0);
  stock.send("quit");

  // lcmx pub --udp reaches a stock subscriber (who is not in discovery: --no-wait).
  const std::string ch2 = unique_channel("TO_STOCK", 125);
  auto& stock_sub = s.spawn(in_ns({LCMX_LCM_PEER, "sub", kLcmDefaultUrl, ch2, "3", "20000"}));
  REQUIRE(stock_sub.expect("ready"));
  auto& pub = s.spawn(in_ns({LCMX_TOOL, "pub", ch2, "lcmx_examples.bench_t", "-", "--types", kTypes, "--udp",
                             "--no-wait", "--rate", "100", "-n", "3"}),
                      env, true);
  for (int i = 0; i < 3; ++i) pub.send(R"({"seq": )" + std::to_string(i) + R"(, "data": [83, 84, 0, 0, 0, 0, 0, 0]})");
  CHECK(pub.wait(10000ms) == 0);
  INFO(pub.text());
  const auto sum = stock_sub.read_summaries(15000ms);
  REQUIRE(sum.size() == 1);
  CHECK(sum[0].num("received") == 3);
  CHECK(sum[0].num("decode_errors") == 0);
  CHECK(sum[0].num("out_of_order") == 0);
}
