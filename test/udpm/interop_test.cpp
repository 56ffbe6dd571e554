// Interop with stock liblcm 1.3.1 (lcmx_udpm_peer, lcm-logger) inside a network namespace the
// test creates: liblcm joins with INADDR_ANY, so it must not see the host's interfaces.
// The test thread enters the namespace (setns), so the Group it opens and the processes it starts
// live there; the namespace is deleted by RAII on every exit path.
#include <catch2/catch.hpp>
#include <cstdio>
#include <sstream>

#include "support.hpp"

using namespace lcmx::udpm;
using namespace lcmx::udpm::test;

namespace {

std::string lcm_url(const GroupConfig& cfg) {
  // liblcm's own options only (it ignores and warns about ours).
  return "udpm://" + cfg.address + ":" + std::to_string(cfg.port) + "?ttl=0&recv_buf_size=4194304";
}

void liblcm_to_lcmx(std::size_t size, std::uint32_t count) {
  Netns ns;
  EnterNetns in(ns);
  const auto cfg = unique_config();
  auto rx = Group::open(cfg);  // joined before the publisher starts
  const std::string channel = "LIBLCM_TO_LCMX";
  Child pub({LCMX_UDPM_PEER, "pub", lcm_url(cfg), channel, std::to_string(count), std::to_string(size)});

  std::vector<std::uint32_t> indices;
  bool all_ok = true;
  const bool done = poll_until(
      rx,
      [&](const Message& m) {
        CHECK(m.channel == channel);
        CHECK(m.data.size() == size);
        all_ok = all_ok && payload_ok(m.data);
        indices.push_back(payload_index(m.data));
      },
      [&] { return indices.size() >= count; }, 10000ms);
  CHECK(pub.wait() == 0);
  REQUIRE(done);
  CHECK(all_ok);
  std::vector<std::uint32_t> expected(count);
  for (std::uint32_t i = 0; i < count; ++i) expected[i] = i;
  CHECK(indices == expected);  // all of them, in order
  CHECK(rx.counters().malformed_dropped == 0);
  CHECK(rx.counters().incomplete_dropped == 0);
}

// group_first: open the Group (which binds the port) before liblcm binds it, else after.
void lcmx_to_liblcm(std::size_t size, std::uint32_t count, bool group_first = false) {
  Netns ns;
  EnterNetns in(ns);
  const auto cfg = unique_config();
  const std::string channel = "LCMX_TO_LIBLCM";
  std::optional<Group> early;
  if (group_first) early.emplace(Group::open(cfg));
  Child sub({LCMX_UDPM_PEER, "sub", lcm_url(cfg), channel, std::to_string(count), "15000"});
  REQUIRE(sub.read_line() == std::optional<std::string>("ready"));
  // Same port as liblcm's receive socket: both bind with SO_REUSEADDR.
  auto tx = group_first ? std::move(*early) : Group::open(cfg);
  std::vector<std::string> lines;
  for (std::uint32_t i = 0; i < count; ++i) {
    tx.publish(channel, make_payload(i, size));
    if (size > 65536) {  // lock-step for large messages: wait for liblcm to take each one
      auto line = sub.read_line();
      REQUIRE(line);
      lines.push_back(*line);
    }
  }
  for (std::uint32_t guard = 0; guard <= count + 1; ++guard) {
    auto line = sub.read_line();
    if (!line) break;
    lines.push_back(*line);
  }
  CHECK(sub.wait() == 0);
  REQUIRE(lines.size() == count + 1);
  for (std::uint32_t i = 0; i < count; ++i)
    CHECK(lines[i] == "msg " + channel + " " + std::to_string(i) + " " + std::to_string(size) + " ok");
  CHECK(lines.back() == "done " + std::to_string(count));
}

}  // namespace

TEST_CASE("interop: liblcm publishes short messages, lcmx receives", "[integration][interop]") {
  liblcm_to_lcmx(1000, 20);
}

TEST_CASE("interop: liblcm publishes fragmented messages, lcmx receives", "[integration][interop]") {
  liblcm_to_lcmx(200000, 5);
}

TEST_CASE("interop: lcmx publishes short messages, liblcm receives", "[integration][interop]") {
  lcmx_to_liblcm(1000, 20);
}

TEST_CASE("interop: lcmx publishes fragmented messages, liblcm receives", "[integration][interop]") {
  lcmx_to_liblcm(200000, 5);
}

TEST_CASE("interop: sizes at the LC02/LC03 boundary, both ways", "[integration][interop]") {
  // channel + NUL + payload == 65499 is the largest LC02; one byte more is two LC03 fragments.
  const std::size_t to_lcmx = kShortMessageMaxSize - std::string_view("LIBLCM_TO_LCMX").size() - 1;
  const std::size_t to_liblcm = kShortMessageMaxSize - std::string_view("LCMX_TO_LIBLCM").size() - 1;
  SECTION("liblcm -> lcmx, largest LC02") { liblcm_to_lcmx(to_lcmx, 3); }
  SECTION("liblcm -> lcmx, smallest LC03") { liblcm_to_lcmx(to_lcmx + 1, 3); }
  SECTION("lcmx -> liblcm, largest LC02, Group bound first") { lcmx_to_liblcm(to_liblcm, 3, true); }
  SECTION("lcmx -> liblcm, smallest LC03, Group bound first") { lcmx_to_liblcm(to_liblcm + 1, 3, true); }
}

TEST_CASE("interop: lcm-logger records what lcmx publishes on LCM's default URL", "[integration][interop]") {
  Netns ns;
  EnterNetns in(ns);
  char dir_template[] = "/tmp/lcmx_udpm_log_XXXXXX";
  REQUIRE(::mkdtemp(dir_template) != nullptr);
  const std::string dir = dir_template;
  const std::string log = dir + "/recording.lcmlog";
  struct RemoveDir {
    std::string dir, log;
    ~RemoveDir() {
      std::remove(log.c_str());
      ::rmdir(dir.c_str());
    }
  } remove_dir{dir, log};

  // The namespace isolates LCM's default group, so using it here is fine.
  const auto cfg = parse_url("udpm://239.255.76.67:7667?ttl=0");
  Child logger({LCMX_LCM_LOGGER, "-q", "-f", "--flush-interval=10",
                // (liblcm 1.3.1's lcm-logger lists -l but does not accept it)
                "--lcm-url=udpm://239.255.76.67:7667?ttl=0", log});
  auto g = Group::open(cfg);
  const std::string channel = "LCMX_LOGGED";
  const auto payload = make_payload(77, 3000);

  // lcm-logger prints no ready line: publish, then look in the log, until it shows up (deadline).
  bool found = false;
  std::string answer;
  const auto deadline = Clock::now() + 10s;
  for (int attempt = 0; attempt < 200 && !found && Clock::now() < deadline; ++attempt) {
    g.publish(channel, payload);
    g.poll(50ms, [](const Message&) {});  // the retry interval; also drains our own loopback
    Child check({LCMX_UDPM_PEER, "logcheck", log, channel});
    answer = check.read_line().value_or("");
    found = check.wait() == 0;
  }
  logger.signal(SIGINT);
  CHECK(logger.wait(5000ms) == 0);
  INFO("logcheck said: " << answer);
  REQUIRE(found);
  std::istringstream in_answer(answer);
  std::string word;
  long n = 0, first_size = 0;
  in_answer >> word >> n >> first_size;
  CHECK(word == "found");
  CHECK(n >= 1);
  CHECK(first_size == 3000);
}

// Host-local mode (no iface=) on a host whose group routes to its LAN interface, like an
// ordinary computer's: joined on lo and lan0, publish() on lo, publish_routed() on lan0 from the
// same port, both recognised as its own, neither received by itself with receive_own = false;
// liblcm's ttl=0 datagrams (sent on lan0) are heard, and liblcm hears publish_routed().
TEST_CASE("interop: host-local mode on a LAN-routed host - lo and the routed interface both ways",
          "[integration][interop]") {
  Netns ns(NetnsRoute::lan);
  EnterNetns in(ns);
  auto cfg = unique_config();
  cfg.interface = "";  // what a URL without iface= gives
  auto rx = Group::open(cfg);
  auto self_cfg = cfg;
  self_cfg.receive_own = false;
  auto tx = Group::open(self_cfg);
  CHECK(rx.routed_interface() == "lan0");
  CHECK(tx.routed_interface() == "lan0");
  CHECK_FALSE(rx.refresh());  // the route did not change

  // stock -> lcmx: liblcm sends where the group routes (lan0).
  {
    Child pub({LCMX_UDPM_PEER, "pub", lcm_url(cfg), "FROM_LIBLCM", "20", "300"});
    std::vector<std::uint32_t> got;
    REQUIRE(poll_until(rx, [&](const Message& m) { if (m.channel == "FROM_LIBLCM") got.push_back(payload_index(m.data)); },
                       [&] { return got.size() >= 20; }));
    CHECK(pub.wait() == 0);
    CHECK(got.size() == 20);
    CHECK(rx.counters().duplicates_dropped == 0);
  }

  // publish() from 127.0.0.1, publish_routed() from lan0's address, one port.
  tx.drain([](const Message&) {});  // liblcm's, above
  const auto before = tx.counters().packets_received;
  tx.publish("ON_LO", make_payload(1, 100));
  tx.publish_routed("ON_LAN", make_payload(2, 100));
  std::vector<std::string> channels;
  std::vector<Source> sources;
  REQUIRE(poll_until(rx, [&](const Message& m) { channels.emplace_back(m.channel); sources.push_back(m.source); },
                     [&] { return channels.size() >= 2; }));
  REQUIRE(channels == std::vector<std::string>{"ON_LO", "ON_LAN"});
  CHECK(to_string(sources[0]) == "127.0.0.1:" + std::to_string(ntohs(tx.local_source().port_be)));
  CHECK(to_string(sources[1]) == std::string(kLanAddress) + ":" + std::to_string(ntohs(tx.local_source().port_be)));
  CHECK(tx.is_own(sources[0]));
  CHECK(tx.is_own(sources[1]));
  CHECK_FALSE(rx.is_own(sources[1]));
  tx.poll(50ms, [](const Message&) {});
  CHECK(tx.counters().packets_received == before);  // its own, dropped in the kernel

  // lcmx -> stock: liblcm joined where the group routes and hears publish_routed().
  Child sub({LCMX_UDPM_PEER, "sub", lcm_url(cfg), "TO_LIBLCM", "10", "10000"});
  REQUIRE(sub.read_line() == std::optional<std::string>("ready"));
  for (std::uint32_t i = 0; i < 10; ++i) tx.publish_routed("TO_LIBLCM", make_payload(i, 500));
  std::vector<std::string> lines;
  for (int guard = 0; guard < 12; ++guard) {
    auto line = sub.read_line();
    if (!line) break;
    lines.push_back(*line);
  }
  CHECK(sub.wait() == 0);
  REQUIRE(lines.size() == 11);
  CHECK(lines.back() == "done 10");
}
