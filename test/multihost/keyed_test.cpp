// Keyed vehicle groups (docs/keyed-groups.md) between emulated hosts: hosts 0 and 1 hold the
// vehicle key (written by `lcmx keygen --group`); host 2 is a machine on the same switch
// without it (or with another key), as a laptop plugged into the robot would be. Every packet
// stays inside the test's own network namespaces.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <filesystem>

#include "lcmx/test/catch_netns.hpp"
#include "lcmx/test/tmp_dir.hpp"
#include "group_listener.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;

namespace {

// Writes a new group key file with `lcmx keygen --group` (or steps it: --next, --promote,
// --retire) and checks that the tool said so.
void keygen(Hosts& h, const std::string& file, std::vector<std::string> extra = {}) {
  std::vector<std::string> argv = {LCMX_TOOL, "keygen", "--group", file};
  argv.insert(argv.end(), extra.begin(), extra.end());
  const auto r = h.run(0, argv);
  INFO(r.out);
  REQUIRE(r.rc == 0);
  REQUIRE(contains(r.out, "wrote " + file + " (mode 0600)"));
}

// Reads `c`'s output until a line contains `needle` (true) or the deadline passes.
bool wait_contains(Child& c, const std::string& needle, ms timeout) {
  if (contains(c.text(), needle)) return true;
  const auto deadline = Clock::now() + timeout;
  while (Clock::now() < deadline) {
    auto line = c.read_line(std::chrono::duration_cast<ms>(deadline - Clock::now()));
    if (!line) return false;
    if (contains(*line, needle)) return true;
  }
  return false;
}

// A socket of host `host` that hears the vehicle group as any machine on the switch can, and
// sends what it heard back, unchanged, from its own address (a replay attack).
class Recorder {
 public:
  Recorder(lcmx::test::Emulation& emu, int host, const std::string& vehicle_url) {
    const auto g = group_of_url(vehicle_url);
    group_ = g.group;
    port_ = g.port;
    const std::string own = emu.address(host, "eth");
    fd_ = open_group_socket(emu, host, g);
    // Sent from the machine's own address (the receive socket is bound to the group address).
    out_ = emu.run_in(host, [&] {
      const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
      in_addr a{};
      ::inet_pton(AF_INET, own.c_str(), &a);
      if (::setsockopt(fd, IPPROTO_IP, IP_MULTICAST_IF, &a, sizeof a) != 0) return -1;
      const unsigned char ttl = 1, loop = 0;
      ::setsockopt(fd, IPPROTO_IP, IP_MULTICAST_TTL, &ttl, sizeof ttl);
      ::setsockopt(fd, IPPROTO_IP, IP_MULTICAST_LOOP, &loop, sizeof loop);
      return fd;
    });
    REQUIRE(fd_ >= 0);
    REQUIRE(out_ >= 0);
    own_ = own;
  }
  Recorder(const Recorder&) = delete;
  Recorder& operator=(const Recorder&) = delete;
  ~Recorder() {
    ::close(fd_);
    ::close(out_);
  }

  // Keeps what arrived until now from other machines (at most `max` datagrams in all).
  void record(std::size_t max = 4000) {
    for (std::size_t guard = 0; guard < 100000 && captured_.size() < max; ++guard) {
      std::vector<std::uint8_t> d(65536);
      sockaddr_in from{};
      socklen_t len = sizeof from;
      const auto n = ::recvfrom(fd_, d.data(), d.size(), 0, reinterpret_cast<sockaddr*>(&from), &len);
      if (n <= 0) return;
      char a[INET_ADDRSTRLEN] = {};
      ::inet_ntop(AF_INET, &from.sin_addr, a, sizeof a);
      if (own_ == a) continue;  // this machine's own (the hostile peer's)
      d.resize(static_cast<std::size_t>(n));
      captured_.push_back(std::move(d));
    }
  }
  std::size_t size() const { return captured_.size(); }
  // Sends every recorded datagram again to the group.
  void replay() {
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_port = htons(port_);
    ::inet_pton(AF_INET, group_.c_str(), &to.sin_addr);
    for (const auto& d : captured_) {
      for (int attempt = 0; attempt < 100; ++attempt) {  // bounded: a full send buffer waits a little
        if (::sendto(out_, d.data(), d.size(), 0, reinterpret_cast<sockaddr*>(&to), sizeof to) >= 0) break;
        pollfd p{out_, POLLOUT, 0};
        ::poll(&p, 1, 10);
      }
    }
  }

 private:
  std::string group_;
  std::uint16_t port_ = 0;
  std::string own_;
  int fd_ = -1, out_ = -1;
  std::vector<std::vector<std::uint8_t>> captured_;
};

}  // namespace

TEST_CASE("keyed vehicle: two keyed hosts talk on every path - small, fragments, keep last N, lcmx nodes",
          "[multihost][keyed]") {
  LCMX_REQUIRE_NETNS();
  const bool encrypt = GENERATE(false, true);
  INFO((encrypt ? "encrypted" : "authenticated"));
  Hosts h(2, encrypt ? 91 : 90);
  lcmx::test::TmpDir dir("lcmx_mh_keyed");
  const auto key = dir.file("vehicle.key");
  keygen(h, key);
  const std::vector<std::string> env = {"LCMX_VEHICLE_KEY=" + key, encrypt ? "LCMX_VEHICLE_CRYPT=1" : "LCMX_VEHICLE_CRYPT=0"};

  // Small messages over UDP, exactly once and in order.
  const auto ch = h.channel("KEYED_SMALL");
  auto& sub = h.peer(1, {"sub", "--channel", ch, "--type", "pose", "--publishers", "1", "--expect", "300",
                         "--queue-depth", "4096"}, env);
  REQUIRE(sub.expect("READY"));
  auto& pub = h.peer(0, {"pub", "--channel", ch, "--type", "pose", "--count", "300", "--rate", "500",
                         "--subscribers", "1", "--hold", "--id", "A"}, env);
  REQUIRE(pub.expect("MATCHED 1"));
  REQUIRE(pub.expect("PUBLISHED"));
  {
    INFO("subscriber:\n" << sub.output());
    const auto st = of(sub.read_summaries(15000ms), ch);
    check_exact(st, 300);
    CHECK(st.str("paths") == "udp");
    CHECK(sub.wait() == 0);
  }
  pub.send("quit");
  CHECK(pub.wait() == 0);

  // 100 KB messages: LC03 fragments, each sealed.
  const auto big = h.channel("KEYED_BIG");
  auto& bsub = h.peer(1, {"sub", "--channel", big, "--type", "bench", "--publishers", "1", "--expect", "20",
                          "--queue-depth", "64"}, env);
  REQUIRE(bsub.expect("READY"));
  auto& bpub = h.peer(0, {"pub", "--channel", big, "--type", "bench", "--size", "100000", "--count", "20",
                          "--rate", "30", "--subscribers", "1", "--hold", "--id", "A"},
                      {env[0], env[1], "LCMX_SMALL_TOPICS=" + big});
  REQUIRE(bpub.expect("MATCHED 1"));
  REQUIRE(bpub.expect("PUBLISHED"));
  {
    INFO("subscriber:\n" << bsub.output());
    const auto st = of(bsub.read_summaries(15000ms), big);
    check_exact(st, 20);
    CHECK(st.str("paths") == "udp");
    CHECK(bsub.wait() == 0);
  }
  bpub.send("quit");
  CHECK(bpub.wait() == 0);

  // Keep last N: the replay (history) goes to a late subscriber on the other host.
  const auto kch = h.channel("KEYED_KEEP");
  auto& kpub = h.peer(0, {"pub", "--channel", kch, "--type", "pose", "--count", "10", "--rate", "0", "--history", "4",
                          "--hold", "--id", "A"}, env);
  REQUIRE(kpub.expect("PUBLISHED 10"));
  auto& late = h.peer(1, {"sub", "--channel", kch, "--type", "pose", "--publishers", "1", "--expect", "4"}, env);
  {
    INFO("late subscriber:\n" << late.output());
    const auto st = of(late.read_summaries(15000ms), kch);
    CHECK(st.num("received") == 4);
    CHECK(st.num("min") == 6);
    CHECK(st.str("paths") == "udp");
    CHECK(late.wait() == 0);
  }

  // lcmx nodes on host 1 with the key sees host 0's participant and says the group is keyed.
  const auto nodes = h.run(1, {LCMX_TOOL, "nodes", "--wait", "600"}, h.lcmx_env(env));
  INFO("lcmx nodes:\n" << nodes.out);
  CHECK(nodes.rc == 0);
  CHECK(contains(nodes.out, " pid "));
  CHECK(contains(nodes.out, std::string("group vehicle ") + h.vehicle_url + ": keyed (" +
                                (encrypt ? "encrypted" : "authenticated")));
  CHECK(contains(nodes.out, "group host-local " + h.discovery_url + ": unkeyed"));
  CHECK_FALSE(contains(nodes.out, "unauthenticated traffic"));
  kpub.send("quit");
  CHECK(kpub.wait() == 0);
}

TEST_CASE("keyed vehicle: a LAN machine without the key injects nothing - messages, beacons, goodbyes, history, "
          "replays",
          "[multihost][keyed][attack]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(3, 92);
  lcmx::test::TmpDir dir("lcmx_mh_keyed");
  const auto key = dir.file("vehicle.key");
  keygen(h, key);
  const std::vector<std::string> env = {"LCMX_VEHICLE_KEY=" + key};
  const auto ch = h.channel("KEYED_ATTACK");
  Recorder recorder(h.emu(), 2, h.vehicle_url);

  // The victim: a keyed subscriber on host 1, reporting its events.
  auto& sub = h.peer(1, {"sub", "--channel", ch, "--type", "pose", "--queue-depth", "4096"}, env);
  REQUIRE(sub.expect("READY"));
  // The LAN machine runs lcmx without the key: beacons, messages (always, like stock LCM), a
  // keep-last-N history, then a goodbye.
  auto& hostile = h.peer(2, {"pub", "--channel", ch, "--type", "pose", "--count", "200", "--rate", "400",
                             "--history", "4", "--hold", "--id", "H"},
                         {"LCMX_VEHICLE_PUBLISH=always"});
  REQUIRE(hostile.expect("PUBLISHED"));
  // The keyed publisher on host 0, keeping its last 4.
  auto& pub = h.peer(0, {"pub", "--channel", ch, "--type", "pose", "--count", "200", "--rate", "400",
                         "--subscribers", "1", "--hold", "--history", "4", "--id", "A"}, env);
  REQUIRE(pub.expect("MATCHED 1"));
  REQUIRE(pub.expect("PUBLISHED"));
  recorder.record();
  const auto host2 = h.emu().address(2, "eth");
  REQUIRE(wait_contains(sub, "EVENT error - vehicle group: unauthenticated traffic from " + host2 +
                                 ": wrong key or not lcmx", 5000ms));
  hostile.send("quit");  // its goodbye, refused too
  CHECK(hostile.wait() == 0);
  // A late keyed subscriber gets host 0's history (recorded on host 2 as it goes by).
  auto& late = h.peer(1, {"sub", "--channel", ch, "--type", "pose", "--publishers", "1"}, env);
  REQUIRE(late.expect("READY"));
  REQUIRE(late.wait_seen("MATCHED", 10000ms));
  for (int guard = 0; guard < 100; ++guard) {  // wait (bounded) for the 4 kept messages
    const auto st = of(late.summaries("status", 5000ms), ch);
    if (st.num("received") >= 4) break;
    recorder.record();  // (each status round trip paces the loop)
  }

  // host 0's datagrams (messages, beacons, its history), recorded on host 2; host 0 says
  // goodbye; then the recording is replayed.
  recorder.record();
  REQUIRE(recorder.size() > 0);
  pub.send("quit");
  CHECK(pub.wait() == 0);
  recorder.record();
  recorder.replay();
  REQUIRE(wait_contains(sub, "EVENT error - vehicle group: replayed datagrams from " + host2, 5000ms));
  {
    const auto st = of(late.summaries("quit", 15000ms), ch);
    INFO("late subscriber:\n" << late.output());
    CHECK(st.num("received") == 4);  // the history once, not again from the replay
    CHECK(st.num("duplicates") == 0);
    CHECK(late.wait() == 0);
  }

  const auto nodes = h.run(1, {LCMX_TOOL, "nodes", "--wait", "600"}, h.lcmx_env(env));
  INFO("lcmx nodes on host 1:\n" << nodes.out);
  CHECK(nodes.rc == 0);
  // Neither host 0 (gone, its old beacons replayed) nor host 2 (no key) is a participant there.
  CHECK(count_lines(nodes.out, "participant ") == 1);  // the subscriber
  CHECK(contains(nodes.out, "group vehicle " + h.vehicle_url + ": keyed (authenticated"));

  const auto st = of(sub.summaries("quit", 15000ms), ch);
  INFO("subscriber:\n" << sub.output());
  CHECK(st.str("sources") == "A:200");  // nothing of H, no replayed message of A
  CHECK(st.num("received") == 200);
  CHECK(st.num("duplicates") == 0);
  CHECK(st.num("publishers") <= 1);
  CHECK(sub.wait() == 0);
}

TEST_CASE("keyed vehicle: a host with the wrong key is refused and reported", "[multihost][keyed][attack]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(3, 93);
  lcmx::test::TmpDir dir("lcmx_mh_keyed");
  const auto key = dir.file("vehicle.key"), wrong = dir.file("other.key");
  keygen(h, key);
  keygen(h, wrong);
  const auto ch = h.channel("KEYED_WRONG");
  auto& sub = h.peer(1, {"sub", "--channel", ch, "--type", "pose", "--queue-depth", "4096"}, {"LCMX_VEHICLE_KEY=" + key});
  REQUIRE(sub.expect("READY"));
  auto& other = h.peer(2, {"pub", "--channel", ch, "--type", "pose", "--count", "50", "--rate", "200", "--hold",
                           "--id", "W"},
                       {"LCMX_VEHICLE_KEY=" + wrong, "LCMX_VEHICLE_PUBLISH=always"});
  REQUIRE(other.expect("PUBLISHED"));
  const auto host2 = h.emu().address(2, "eth");
  REQUIRE(wait_contains(sub, "EVENT error - vehicle group: unauthenticated traffic from " + host2 +
                                 ": wrong key or not lcmx", 5000ms));
  // Reported once, then counted.
  INFO("subscriber:\n" << sub.output());
  CHECK(count_lines(sub.text(), "EVENT error - vehicle group: unauthenticated traffic from " + host2) == 1);
  const auto nodes = h.run(1, {LCMX_TOOL, "nodes", "--wait", "600"}, h.lcmx_env({"LCMX_VEHICLE_KEY=" + key}));
  INFO("lcmx nodes:\n" << nodes.out);
  CHECK(contains(nodes.out, "  unauthenticated traffic from " + host2 + ": wrong key or not lcmx"));
  CHECK_FALSE(contains(nodes.out, "\"W\""));
  const auto st = of(sub.summaries("quit", 15000ms), ch);
  CHECK(st.num("received") == 0);
  CHECK(sub.wait() == 0);
  other.send("quit");
  CHECK(other.wait() == 0);
}

TEST_CASE("keyed vehicle: rotating the key host by host keeps traffic flowing with no loss", "[multihost][keyed]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 94);
  lcmx::test::TmpDir dir("lcmx_mh_keyed");
  // One key file per host, rolled out one host at a time (docs/keyed-groups.md "Rotation").
  const std::string files[2] = {dir.file("host0.key"), dir.file("host1.key")};
  keygen(h, files[0]);
  REQUIRE(std::filesystem::copy_file(files[0], files[1]));
  const auto ch = h.channel("KEYED_ROTATE");
  auto& sub = h.peer(1, {"sub", "--channel", ch, "--type", "pose", "--publishers", "1", "--queue-depth", "100000"},
                     {"LCMX_VEHICLE_KEY=" + files[1]}, true);
  REQUIRE(sub.expect("READY"));
  auto& pub = h.peer(0, {"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "300",
                         "--subscribers", "1", "--id", "A"},
                     {"LCMX_VEHICLE_KEY=" + files[0]}, true);
  REQUIRE(pub.expect("MATCHED 1"));
  // Each step on host 0, then on host 1, each time waiting until that host's runtime has
  // re-read its file; traffic flows meanwhile.
  for (const char* step : {"--next", "--promote", "--retire"}) {
    for (int host = 0; host < 2; ++host) {
      INFO("step " << step << " on host " << host);
      if (host == 0) {
        keygen(h, files[0], {step});
      } else {  // copied and renamed over it, as a deployment tool would
        std::filesystem::copy_file(files[0], files[1] + ".new", std::filesystem::copy_options::overwrite_existing);
        std::filesystem::rename(files[1] + ".new", files[1]);
      }
      Child& c = host == 0 ? pub : sub;
      REQUIRE(wait_contains(c, "group's key file " + files[host] + " changed", 5000ms));
    }
  }
  REQUIRE(sub.wait_seen("MATCHED", 1000ms));
  // Traffic goes on after the last step (on the new key alone) for at least 300 messages in all.
  REQUIRE(poll_sub(sub, ch, [](const Summary& x) { return x.num("received") > 300; }, 15000ms));
  pub.send("quit");
  CHECK(pub.wait() == 0);
  const auto st = of(sub.summaries("quit", 15000ms), ch);
  INFO("subscriber:\n" << sub.output() << "publisher:\n" << pub.output());
  CHECK(st.num("received") > 300);
  CHECK(st.num("first") == 0);
  CHECK(st.num("received") == st.num("last") + 1);  // contiguous: nothing lost
  CHECK(st.num("gaps") == 0);
  CHECK(st.num("drops") == 0);
  CHECK(st.num("duplicates") == 0);
  CHECK_FALSE(contains(sub.text(), "unauthenticated traffic"));
  CHECK(sub.wait() == 0);
}

TEST_CASE("keyed vehicle: the Message Bridge refuses to start without CURVE", "[multihost][keyed][bridge]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 95);
  lcmx::test::TmpDir dir("lcmx_mh_keyed");
  const auto key = dir.file("vehicle.key");
  keygen(h, key);
  const auto config = dir.write("bridge.toml", "name = \"a\"\nlisten = [\"" + h.emu().address(0, "eth") +
                                                   "\"]\ncontrol_port = 7700\n[[peer]]\nname = \"b\"\n"
                                                   "endpoints = [{ link = \"eth\", address = \"" +
                                                   h.emu().address(1, "eth") + "\" }]\n");
  const auto keyed = h.run(0, {LCMX_TOOL, "bridge", "--config", config}, h.lcmx_env({"LCMX_VEHICLE_KEY=" + key}));
  INFO(keyed.out);
  CHECK(keyed.rc != 0);
  CHECK(contains(keyed.out, "the vehicle group is keyed"));
  CHECK(contains(keyed.out, "runs only with CURVE"));
  CHECK_FALSE(contains(keyed.out, "ready"));
}
