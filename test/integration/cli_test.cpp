// The `lcmx` tool (nodes, topics) against running participants.
#include <regex>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/udpm/udpm.hpp"
#include "support.hpp"

using namespace lcmx::it;

#ifdef LCMX_TOOL

namespace {

// Lines of `out` from the one starting with `head` up to the next unindented line.
std::string block(const std::string& out, const std::string& head) {
  std::istringstream in(out);
  std::string line, b;
  bool on = false;
  while (std::getline(in, line)) {
    if (!line.empty() && line[0] != ' ') on = line.rfind(head, 0) == 0;
    if (on) b += line + "\n";
  }
  return b;
}

// Listens to a discovery group's beacons in the test process (to know what an observer saw).
class BeaconWatch {
 public:
  explicit BeaconWatch(const std::string& url) : group_(lcmx::udpm::Group::open(lcmx::udpm::parse_url(url))) {}
  // Handles beacons until `done` returns true or the deadline passes.
  bool until(const std::function<bool(const lcmx_msgs::beacon_t&)>& done, ms timeout) {
    const auto deadline = Clock::now() + timeout;
    bool hit = false;
    while (!hit && Clock::now() < deadline) {
      group_.poll(20ms, [&](const lcmx::udpm::Message& m) {
        if (hit || m.channel != lcmx::discovery::kBeaconChannel) return;
        if (auto records = lcmx::discovery::decode_any_records(m.data))  // alone or a speaker's batch
          for (const auto& b : *records)
            if (!hit) hit = done(b);
      });
    }
    return hit;
  }

 private:
  lcmx::udpm::Group group_;
};

}  // namespace

TEST_CASE("lcmx nodes and topics: nodes + topics + types and the path of each pair (intra and shm)", "[integration][cli]") {
  Session s(40);
  const auto ch = unique_channel("CLI", 40);
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "50", "--node", "camera",
                      "--local-sub", "--subscribers", "1"});
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose", "--node", "viewer", "--publishers", "1"});
  REQUIRE(pub.expect("MATCHED"));
  REQUIRE(sub.expect("MATCHED"));

  const auto nodes = s.run({LCMX_TOOL, "--url", s.url, "nodes"});
  INFO("lcmx nodes:\n" << nodes.out);
  CHECK(nodes.rc == 0);
  CHECK(contains(nodes.out, "participant lcmx_test_peer pid " + std::to_string(pub.pid())));
  CHECK(contains(nodes.out, "participant lcmx_test_peer pid " + std::to_string(sub.pid())));
  CHECK(contains(nodes.out, "  node camera\n"));
  CHECK(contains(nodes.out, "  node camera_local\n"));
  CHECK(contains(nodes.out, "  node viewer\n"));
  CHECK(contains(nodes.out, "pub " + ch + "  [pose_t]"));
  CHECK(contains(nodes.out, "sub " + ch + "  [pose_t]"));
  CHECK_FALSE(contains(nodes.out, "lcmx-observer"));

  const auto topics = s.run({LCMX_TOOL, "--url", s.url, "topics"});
  INFO("lcmx topics:\n" << topics.out);
  CHECK(topics.rc == 0);
  const auto b = block(topics.out, ch);
  CHECK(contains(b, ch + "  [pose_t]  1 publisher(s), 2 subscriber(s)"));
  CHECK_FALSE(contains(b, "CONFLICT"));
  const std::string from = "<- lcmx_test_peer[" + std::to_string(pub.pid()) + "]/camera  path ";
  CHECK(contains(b, "sub lcmx_test_peer[" + std::to_string(pub.pid()) + "]/camera_local"));
  CHECK(contains(b, "sub lcmx_test_peer[" + std::to_string(sub.pid()) + "]/viewer"));
  CHECK(contains(b, from + "intra"));
  CHECK(contains(b, from + "shm"));
}

TEST_CASE("lcmx --help and lcmx topics --help exit 0 - a bad flag exits non-zero with a message", "[integration][cli]") {
  Session s(41);
  auto help = s.run({LCMX_TOOL, "--help"});
  CHECK(help.rc == 0);
  CHECK(contains(help.out, "nodes"));
  CHECK(contains(help.out, "topics"));
  auto topics_help = s.run({LCMX_TOOL, "topics", "--help"});
  CHECK(topics_help.rc == 0);
  CHECK(contains(topics_help.out, "topics"));
  auto bad = s.run({LCMX_TOOL, "topics", "--no-such-flag"});
  INFO(bad.out);
  CHECK(bad.rc != 0);
  CHECK(contains(bad.out, "no-such-flag"));
  auto bad_verb = s.run({LCMX_TOOL, "frobnicate"});
  INFO(bad_verb.out);
  CHECK(bad_verb.rc != 0);
  CHECK(contains(bad_verb.out, "lcmx: unknown command 'frobnicate'"));
  // A bad group URL is a bad argument (exit 2, named), on the command line or in the environment.
  auto bad_url = s.run({LCMX_TOOL, "--url", "udpm://not-an-address:1", "nodes"});
  INFO(bad_url.out);
  CHECK(bad_url.rc == 2);
  CHECK(contains(bad_url.out, "--url: 'udpm://not-an-address:1'"));
  auto bad_env = s.run({LCMX_TOOL, "echo", "X"}, {"LCMX_DISCOVERY_URL=garbage"});
  INFO(bad_env.out);
  CHECK(bad_env.rc == 2);
  CHECK(contains(bad_env.out, "lcmx: LCMX_DISCOVERY_URL 'garbage'"));
  // So are a bad LCMX_HOST_ID and a lease not longer than the beacon period: every runtime
  // refuses them, and the observers (topics, nodes), which make none, refuse them too.
  auto bad_host = s.run({LCMX_TOOL, "topics"}, {"LCMX_HOST_ID=chip-a"});
  INFO(bad_host.out);
  CHECK(bad_host.rc == 2);
  CHECK(contains(bad_host.out, "lcmx: LCMX_HOST_ID='chip-a'"));
  auto bad_lease = s.run({LCMX_TOOL, "nodes"}, {"LCMX_LEASE_MS=100", "LCMX_BEACON_PERIOD_MS=400"});
  INFO(bad_lease.out);
  CHECK(bad_lease.rc == 2);
  CHECK(contains(bad_lease.out, "lease 100 ms (LCMX_LEASE_MS) must be longer than beacon_period 400 ms"));
  auto no_iface = s.run({LCMX_TOOL, "--vehicle-url", "udpm://239.255.76.68:7668?ttl=1", "topics"});
  INFO(no_iface.out);
  CHECK(no_iface.rc == 2);
  CHECK(contains(no_iface.out, "names no interface"));
}

// Issue 9 item 5: an unknown verb is named, whatever follows it (--help too: it used to print
// the top-level help and exit 0), and `lcmx <verb> --help` is that verb's help.
TEST_CASE("lcmx: an unknown command is named and fails (also before --help) - each verb has its own --help",
          "[integration][cli]") {
  Session s(48);
  for (const std::vector<std::string>& argv :
       {std::vector<std::string>{LCMX_TOOL, "bogus"}, {LCMX_TOOL, "bogus", "--help"},
        {LCMX_TOOL, "--wait", "100", "bogus"}, {LCMX_TOOL, "--url=udpm://239.1.2.3:4", "bogus", "nodes"}}) {
    auto r = s.run(argv);
    INFO(r.out);
    CHECK(r.rc != 0);
    CHECK(contains(r.out, "lcmx: unknown command 'bogus'"));
    CHECK(contains(r.out, "lcmx --help"));
    CHECK_FALSE(contains(r.out, "Subcommands:"));  // not the top-level help
  }
  auto top = s.run({LCMX_TOOL, "--help"});
  CHECK(top.rc == 0);
  for (const char* verb : {"nodes", "topics", "bridge"}) CHECK(contains(top.out, verb));
  auto nodes = s.run({LCMX_TOOL, "nodes", "--help"});
  CHECK(nodes.rc == 0);
  CHECK(contains(nodes.out, "list participants"));
  CHECK_FALSE(contains(nodes.out, "list topics"));
  auto bridge = s.run({LCMX_TOOL, "bridge", "--help"});
  CHECK(bridge.rc == 0);
  CHECK(contains(bridge.out, "--config"));
  auto status = s.run({LCMX_TOOL, "--wait", "100", "bridge", "status", "--help"});
  CHECK(status.rc == 0);
  CHECK(contains(status.out, "per bridge on this host"));
  CHECK_FALSE(contains(status.out, "--config"));
}

TEST_CASE("lcmx topics: a steady 10 Hz publisher reads about 10 Hz, on queries in quick succession too",
          "[integration][cli]") {
  // Each query makes every participant beacon at once; a rate taken over the gap since the
  // previous beacon read one message over 70 ms as 14 Hz.
  Session s(146);
  const auto ch = unique_channel("RATE", 146);
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose", "--publishers", "1"});
  REQUIRE(sub.expect("READY"));
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "10", "--subscribers", "1"});
  REQUIRE(pub.expect("MATCHED"));
  // Three seconds of traffic: more than one whole rate window (2 s).
  REQUIRE(poll_sub(sub, ch, [](const Summary& x) { return x.num("received") >= 30; }, 10000ms));
  const std::regex pub_line("\n  pub [^\n]* msgs  ([0-9.]+) Hz");
  for (int query = 0; query < 5; ++query) {
    const auto r = s.run({LCMX_TOOL, "--url", s.url, "--wait", "100", "topics"});
    INFO(r.out);
    REQUIRE(r.rc == 0);
    std::smatch m;
    REQUIRE(std::regex_search(r.out, m, pub_line));
    const double hz = std::stod(m[1].str());
    CHECK(hz > 8.5);
    CHECK(hz < 11.5);
  }
  pub.send("quit");
  CHECK(pub.wait() == 0);
  sub.send("quit");
  CHECK(sub.wait() == 0);
}

TEST_CASE("lcmx nodes: a clean exit and a kill -9 disappear at once - a stopped process after its lease", "[integration][cli]") {
  // Discovery v6 (docs/discovery.md): the tool reads the host registry. alpha exits cleanly,
  // bravo (lease 8 s) is killed -9: both gone at once (goodbye; the speaker sees the death).
  // charlie (lease 8 s) and delta (lease 600 ms) are stopped: only delta's lease runs out
  // while the tool watches (1.5 s).
  Session s(42);
  const auto long_lease = s.env(100ms, 8000ms);
  auto& alpha = s.peer({"idle", "--node", "alpha"}, long_lease);
  auto& bravo = s.peer({"idle", "--node", "bravo"}, long_lease);
  auto& charlie = s.peer({"idle", "--node", "charlie"}, long_lease);
  auto& delta = s.peer({"idle", "--node", "delta"});
  for (auto* p : {&alpha, &bravo, &charlie, &delta}) REQUIRE(p->expect("READY"));
  {
    auto& first = s.spawn({LCMX_TOOL, "--url", s.url, "--wait", "300", "nodes"}, {}, true);
    CHECK(first.wait(10000ms) == 0);
    const auto out = first.text();
    INFO("lcmx nodes:\n" << out);
    for (const char* n : {"node alpha", "node bravo", "node charlie", "node delta"}) REQUIRE(contains(out, n));
  }
  alpha.send("quit");
  CHECK(alpha.wait() == 0);
  bravo.kill9();
  charlie.signal(SIGSTOP);
  delta.signal(SIGSTOP);
  auto& observer = s.spawn({LCMX_TOOL, "--url", s.url, "--wait", "1500", "nodes"}, {}, true);
  CHECK(observer.wait(10000ms) == 0);
  charlie.signal(SIGCONT);
  delta.signal(SIGCONT);
  const auto out = observer.text();
  INFO("lcmx nodes:\n" << out);
  CHECK_FALSE(contains(out, "node alpha"));  // goodbye: gone at once
  CHECK_FALSE(contains(out, "node bravo"));  // killed: gone at once, whatever its lease
  CHECK(contains(out, "node charlie"));      // stopped, lease (8 s) not over
  CHECK_FALSE(contains(out, "node delta"));  // stopped past its lease (600 ms)
}


// Issue 34 item 6: a name from the network is whatever its sender chose. An escape sequence in
// a channel or node name (here: retitle the terminal, clear the screen, ring the bell) must not
// reach the terminal from any verb's text output; JSON output escapes it by JSON's rules.
TEST_CASE("lcmx nodes, topics, echo and hz print names from the network with their control characters escaped",
          "[integration][cli][trust]") {
  Session s(160);
  const std::string evil = "\x1b]0;owned\x07\x1b[2J";
  const auto ch = unique_channel("ESC", 160) + evil;
  const std::string node = "cam\x1b[31mera\x9b";  // and a stray byte that is not UTF-8
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "50", "--node", node});
  REQUIRE(pub.expect("READY"));
  auto clean = [](const std::string& out) {
    return out.find('\x1b') == std::string::npos && out.find('\x07') == std::string::npos &&
           out.find('\x9b') == std::string::npos;
  };
  const std::string ch_shown = unique_channel("ESC", 160) + "\\x1b]0;owned\\x07\\x1b[2J";
  for (const char* verb : {"nodes", "topics"}) {
    const auto r = s.run({LCMX_TOOL, "--url", s.url, verb});
    INFO("lcmx " << verb << ":\n" << r.out);
    CHECK(r.rc == 0);
    CHECK(clean(r.out));
    CHECK(contains(r.out, ch_shown));
    if (std::string(verb) == "nodes") CHECK(contains(r.out, "  node cam\\x1b[31mera\\x9b\n"));
    const auto j = s.run({LCMX_TOOL, "--url", s.url, verb, "--json"});
    INFO("lcmx " << verb << " --json:\n" << j.out);
    CHECK(j.rc == 0);
    CHECK(clean(j.out));
    CHECK(contains(j.out, "\\u001b]0;owned\\u0007\\u001b[2J"));
  }
  const auto echo = s.run({LCMX_TOOL, "--url", s.url, "echo", ch, "-n", "1"});
  INFO("lcmx echo:\n" << echo.out);
  CHECK(echo.rc == 0);
  CHECK(clean(echo.out));
  CHECK(contains(echo.out, "--- " + ch_shown + "  "));
  const auto hz = s.run({LCMX_TOOL, "--url", s.url, "hz", ch, "-n", "1"});
  INFO("lcmx hz:\n" << hz.out);
  CHECK(hz.rc == 0);
  CHECK(clean(hz.out));
  CHECK(contains(hz.out, ch_shown + ": "));
  pub.send("quit");
}

#else
TEST_CASE("lcmx tool tests", "[integration][cli]") { LCMX_SKIP("lcmx tool not built (LCMX_BUILD_APPS=OFF)"); }
#endif
