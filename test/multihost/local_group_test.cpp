// The host-local group beside stock LCM on hosts that look like ordinary computers (issue 9,
// item 1): a default route via a LAN interface and no multicast route to lo (the laptop, Jetson
// or CI runner), a second LAN interface, and hosts with no route at all. Stock liblcm (and
// Java's lcm-spy) join and send where the kernel routes LCM's default group, here the LAN
// interface; lcmx must hear them by default, reach them with the mirror, never deliver a
// message twice, and never let anything leave the host (ttl=0). The lo-routed variants are in
// multihost_test.cpp ("host-local group: ...").
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>

#include <map>
#include <string_view>

#include "lcmx/test/catch_netns.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;
using lcmx::test::MulticastRoute;

namespace {

// A receiver of LCM's default group on a host, made like Java's MulticastSocket (lcm-spy,
// lcm-logplayer-gui): joined with INADDR_ANY (where the kernel routes the group, as liblcm) and
// IP_MULTICAST_ALL = 0 (OpenJDK sets it on Linux), so unlike liblcm's own socket it hears only
// datagrams arriving on the interface it joined. Counts LC02 messages per channel and
// (source, sequence) repeats.
class JavaLikeReceiver {
 public:
  JavaLikeReceiver(lcmx::test::Emulation& emu, int host) {
    fd_ = emu.run_in(host, [] {
      const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
      const int one = 1, zero = 0;
      ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
      ::setsockopt(fd, IPPROTO_IP, IP_MULTICAST_ALL, &zero, sizeof zero);
      const int buf = 8 << 20;  // the test reads it late: room for everything it will get
      if (::setsockopt(fd, SOL_SOCKET, SO_RCVBUFFORCE, &buf, sizeof buf) != 0)
        ::setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &buf, sizeof buf);
      sockaddr_in a{};
      a.sin_family = AF_INET;
      a.sin_port = htons(7667);
      if (::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) return -1;
      ip_mreq m{};
      ::inet_pton(AF_INET, "239.255.76.67", &m.imr_multiaddr);
      m.imr_interface.s_addr = htonl(INADDR_ANY);
      if (::setsockopt(fd, IPPROTO_IP, IP_ADD_MEMBERSHIP, &m, sizeof m) != 0) return -1;
      return fd;
    });
    REQUIRE(fd_ >= 0);
  }
  JavaLikeReceiver(const JavaLikeReceiver&) = delete;
  JavaLikeReceiver& operator=(const JavaLikeReceiver&) = delete;
  ~JavaLikeReceiver() { ::close(fd_); }

  // Reads until `channel` has `n` messages or the deadline passes; returns the count.
  long until(const std::string& channel, long n, ms timeout) {
    const auto deadline = Clock::now() + timeout;
    while (count(channel) < n && Clock::now() < deadline) {
      pollfd p{fd_, POLLIN, 0};
      ::poll(&p, 1, 50);
      char buf[65536];
      for (;;) {
        sockaddr_in from{};
        socklen_t len = sizeof from;
        const ssize_t r = ::recvfrom(fd_, buf, sizeof buf, 0, reinterpret_cast<sockaddr*>(&from), &len);
        if (r < 8) break;
        if (std::string(buf, 4) != "LC02") continue;
        const std::uint32_t seq = ntohl(*reinterpret_cast<const std::uint32_t*>(buf + 4));
        const std::string ch(buf + 8, ::strnlen(buf + 8, static_cast<std::size_t>(r - 8)));
        const auto key = std::to_string(from.sin_addr.s_addr) + ":" + std::to_string(from.sin_port) + "/" +
                         std::to_string(seq);
        if (!seen_.insert(ch + " " + key).second) ++duplicates_;
        ++counts_[ch];
      }
    }
    return count(channel);
  }
  long count(const std::string& channel) const {
    auto it = counts_.find(channel);
    return it == counts_.end() ? 0 : it->second;
  }
  long duplicates() const { return duplicates_; }

 private:
  int fd_ = -1;
  std::map<std::string, long> counts_;
  std::set<std::string> seen_;
  long duplicates_ = 0;
};

}  // namespace

TEST_CASE("ordinary computer (default route via the LAN): stock liblcm on LCM's default URL -> lcmx "
          "exactly once - nothing leaves the host",
          "[multihost][interop][local]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 30, Ordinary{});
  const auto ch = h.channel("STOCK_TO_LCMX");
  auto& sub = h.peer(0, {"sub", "--channel", ch, "--type", "bench", "--expect", "200", "--queue-depth", "4096"});
  auto& neighbour = h.peer(1, {"sub", "--channel", ch, "--type", "bench"});
  REQUIRE(sub.expect("READY"));
  REQUIRE(neighbour.expect("READY"));
  const auto eth0 = h.emu().tx_bytes(0, "eth"), wlan0 = h.emu().tx_bytes(0, "wlan");
  auto& lcm = h.lcm_peer(0, {"pub", kLcmDefaultUrl, ch, "200", "500", "500", "L"});
  REQUIRE(lcm.expect("done 200", 15000ms));
  INFO(sub.output());
  const auto st = of(sub.read_summaries(10000ms), ch);
  check_exact(st, 200);
  CHECK(st.str("paths") == "udp");
  CHECK(st.str("sources") == "L:200");
  CHECK(sub.wait() == 0);
  // ttl=0: 200 x 500 bytes went nowhere but this host (a few IGMP reports of the joins do).
  CHECK(h.emu().tx_bytes(0, "eth") - eth0 < 5000);
  CHECK(h.emu().tx_bytes(0, "wlan") - wlan0 < 5000);
  CHECK(of(neighbour.summaries("quit"), ch).num("received") == 0);
  CHECK(neighbour.wait() == 0);
}

TEST_CASE("ordinary computer: lcmx with LCMX_MIRROR=1 -> stock liblcm and a Java-like receiver exactly once - "
          "lcmx on the host still gets it once over shm",
          "[multihost][interop][local]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(2, 31, Ordinary{});
  const auto ch = h.channel("MIRROR_ALL");
  auto& lcm = h.lcm_peer(0, {"sub", kLcmDefaultUrl, ch, "150", "20000"});
  auto& far = h.lcm_peer(1, {"sub", kLcmDefaultUrl, ch, "150", "20000"});
  REQUIRE(lcm.expect("ready"));
  REQUIRE(far.expect("ready"));
  JavaLikeReceiver java(h.emu(), 0);
  auto& sub = h.peer(0, {"sub", "--channel", ch, "--type", "bench", "--expect", "150", "--queue-depth", "4096",
                         "--publishers", "1"});
  REQUIRE(sub.expect("READY"));
  const auto eth0 = h.emu().tx_bytes(0, "eth");
  auto& pub = h.peer(0, {"pub", "--channel", ch, "--type", "bench", "--size", "2000", "--count", "150",
                         "--rate", "500", "--subscribers", "1", "--hold", "--id", "M"},
                     {"LCMX_MIRROR=1"});
  REQUIRE(pub.expect("PUBLISHED"));
  INFO(lcm.output());
  const auto st = lcm.read_summaries(15000ms);
  REQUIRE(st.size() == 1);
  check_exact(st[0], 150);
  CHECK(lcm.wait() == 0);
  CHECK(java.until(ch, 150, 10000ms) == 150);
  CHECK(java.duplicates() == 0);
  const auto s = of(sub.read_summaries(10000ms), ch);
  check_exact(s, 150);
  CHECK(s.str("paths") == "shm");  // the mirrored copies (another address of this host) dropped
  CHECK(sub.wait() == 0);
  pub.send("quit");
  CHECK(pub.wait() == 0);
  CHECK(h.emu().tx_bytes(0, "eth") - eth0 < 5000);  // 150 x 2 KB mirrored, none of it on the LAN
  const auto f = far.summaries("quit", 5000ms);
  REQUIRE(f.size() == 1);
  CHECK(f[0].num("received") == 0);
}

TEST_CASE("ordinary computer: LCMX_MIRROR=<channel patterns> mirrors just the matching channels",
          "[multihost][interop][local]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(1, 32, Ordinary{});
  const auto cam = h.channel("CAM_FRONT"), pose = h.channel("POSE"), odom = h.channel("ODOM");
  const std::string patterns = "MH_CAM_*," + pose;
  Child* stock[3];
  const std::string chans[3] = {cam, pose, odom};
  for (int i = 0; i < 3; ++i) {
    stock[i] = &h.lcm_peer(0, {"sub", kLcmDefaultUrl, chans[i], "100", "20000"});
    REQUIRE(stock[i]->expect("ready"));
  }
  JavaLikeReceiver java(h.emu(), 0);
  Child* pubs[3];
  for (int i = 0; i < 3; ++i)
    pubs[i] = &h.peer(0, {"pub", "--channel", chans[i], "--type", "bench", "--size", "300", "--count", "100",
                          "--rate", "500", "--hold", "--id", "P" + std::to_string(i)},
                      {"LCMX_MIRROR=" + patterns});
  for (auto* p : pubs) REQUIRE(p->expect("PUBLISHED"));
  for (int i = 0; i < 2; ++i) {
    INFO("stock subscriber of " << chans[i] << ":\n" << stock[i]->output());
    const auto st = stock[i]->read_summaries(15000ms);
    REQUIRE(st.size() == 1);
    check_exact(st[0], 100);
    CHECK(java.until(chans[i], 100, 10000ms) == 100);
  }
  // Everything mirrored has arrived by now (same publisher pacing, same host); ODOM never was.
  const auto other = stock[2]->summaries("quit", 5000ms);
  REQUIRE(other.size() == 1);
  CHECK(other[0].num("received") == 0);
  CHECK(java.count(odom) == 0);
  CHECK(java.duplicates() == 0);
  for (auto* p : pubs) {
    p->send("quit");
    CHECK(p->wait() == 0);
  }
}

TEST_CASE("ordinary computer: a bad LCMX_MIRROR is an error naming the variable", "[multihost][local]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(1, 33, Ordinary{});
  for (const std::string bad : {"CAM_*,,POSE", "CAM_*,", ","}) {
    const auto r = h.run(0, {LCMX_TEST_PEER, "pub", "--channel", h.channel("X"), "--type", "bench", "--count", "1",
                             "--timeout-ms", "5000"},
                         h.lcmx_env({"LCMX_MIRROR=" + bad}));
    INFO(r.out);
    CHECK(r.rc != 0);
    CHECK(contains(r.out, "LCMX_MIRROR"));
  }
}

TEST_CASE("no route at all: liblcm refuses to start and lcmx still works on lo - once LCM's lo route is added "
          "stock and the running lcmx hear each other",
          "[multihost][interop][local]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(1, 34, Ordinary{MulticastRoute::none});
  const auto ch = h.channel("NOROUTE");
  // lcmx to lcmx on this host: discovery on lo, shared memory.
  auto& sub = h.peer(0, {"sub", "--channel", ch, "--type", "bench", "--queue-depth", "4096"});
  REQUIRE(sub.expect("READY"));
  auto& pub = h.peer(0, {"pub", "--channel", ch, "--type", "bench", "--count", "50", "--rate", "500",
                         "--subscribers", "1", "--hold", "--id", "X"},
                     {"LCMX_MIRROR=1"});
  REQUIRE(pub.expect("PUBLISHED"));
  REQUIRE(poll_sub(sub, ch, [](const Summary& s) { return s.num("received") >= 50; }, 10000ms));
  // Stock liblcm: "LCM requires a valid multicast route".
  auto& refused = h.lcm_peer(0, {"pub", kLcmDefaultUrl, ch, "1", "0", "100", "L"});
  CHECK(refused.wait(10000ms) != 0);
  // What LCM's message tells users to do; lcmx (started before) needs no restart.
  REQUIRE(lcmx::it::run_quiet({LCMX_IP, "-n", h.emu().ns(0), "route", "add", "224.0.0.0/4", "dev", "lo"}) == 0);
  auto& lcm = h.lcm_peer(0, {"pub", kLcmDefaultUrl, ch, "100", "500", "500", "L"});
  REQUIRE(lcm.expect("done 100", 15000ms));
  REQUIRE(poll_sub(sub, ch, [](const Summary& s) { return s.str("sources").find("L:100") != std::string::npos; },
                   10000ms));
  auto& stock_sub = h.lcm_peer(0, {"sub", kLcmDefaultUrl, ch, "100", "20000"});
  REQUIRE(stock_sub.expect("ready"));
  auto& pub2 = h.peer(0, {"pub", "--channel", ch, "--type", "bench", "--count", "100", "--rate", "500",
                          "--subscribers", "1", "--hold", "--id", "Y"},
                      {"LCMX_MIRROR=1"});
  REQUIRE(pub2.expect("PUBLISHED"));
  const auto st = stock_sub.read_summaries(15000ms);
  REQUIRE(st.size() == 1);
  check_exact(st[0], 100);
  const auto s = of(sub.summaries("quit"), ch);
  CHECK(s.num("duplicates") == 0);
  CHECK(s.str("sources") == "L:100,X:50,Y:100");
  for (auto* p : {&pub, &pub2}) {
    p->send("quit");
    CHECK(p->wait() == 0);
  }
}

TEST_CASE("a LAN route that comes after lcmx started: lcmx follows it - stock programs started since are heard",
          "[multihost][interop][local]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(1, 35, Ordinary{MulticastRoute::none});
  const auto ch = h.channel("LATE_ROUTE");
  auto& sub = h.peer(0, {"sub", "--channel", ch, "--type", "bench", "--queue-depth", "4096"}, {"SPDLOG_LEVEL=debug"},
                     true);
  // lcmx's first look at the routes (a second after its start), before the network comes up:
  // from then on only the kernel's notice of a change makes it look again.
  constexpr std::string_view kLooked = "lcmx: routes and addresses re-read";
  auto looked = [&] {  // the next debug line saying so, within 5 s
    const auto deadline = Clock::now() + 5000ms;
    while (const auto line = sub.read_line(std::chrono::duration_cast<ms>(deadline - Clock::now())))
      if (line->find(kLooked) != std::string::npos) return true;
    return false;
  };
  // On a loaded machine the first look may come before READY (a start slower than a second).
  bool ready = false, looked_first = false;
  const auto ready_by = Clock::now() + 10000ms;
  while (const auto line = sub.read_line(std::chrono::duration_cast<ms>(ready_by - Clock::now()))) {
    looked_first = looked_first || line->find(kLooked) != std::string::npos;
    if (line->rfind("READY", 0) == 0) {
      ready = true;
      break;
    }
  }
  REQUIRE(ready);
  REQUIRE((looked_first || looked()));
  // The network comes up (DHCP after boot): a default route via eth.
  REQUIRE(lcmx::it::run_quiet({LCMX_IP, "-n", h.emu().ns(0), "route", "add", "default", "dev", "eth"}) == 0);
  REQUIRE(looked());
  // A stock publisher started now sends on eth.
  auto& lcm = h.lcm_peer(0, {"pub", kLcmDefaultUrl, ch, "2000", "500", "200", "L"});
  REQUIRE(lcm.expect("ready"));
  REQUIRE(poll_sub(sub, ch, [](const Summary& s) { return s.num("received") >= 100; }, 10000ms));
  lcm.send("quit");
  CHECK(lcm.wait(5000ms) == 0);
  const auto s = of(sub.summaries("quit"), ch);
  CHECK(s.num("duplicates") == 0);
  CHECK(s.num("out_of_order") == 0);
  CHECK(s.num("bad_content") == 0);
}
