// The attack suite (issue 34, DESIGN.md "Trust"): a machine on the robot's LAN that is not part
// of the robot — host 2 of the emulation, a network namespace of its own on the same switch —
// attacks an ordinary computer (host 0: default route via its LAN interface, LCM's default
// group, nothing configured), as a laptop plugged into the vehicle switch would. Each attack
// is a test that failed on the code before the defence it checks (see the closing notes of
// issue 34): every one proves the hostile traffic reached the victim (interface counters, or a
// stock socket that hears it, as LCM's design lets it) and that lcmx did not take it.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/ip.h>
#include <netinet/udp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstring>

#include "lcmx/test/catch_netns.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;

namespace {

constexpr const char* kLcmGroup = "239.255.76.67";
constexpr std::uint16_t kLcmPort = 7667;

// An LC02 datagram (LCM's short message) carrying a bench_t whose data[0..7] is `id`, as
// lcmx_test_peer and lcmx_mh_lcm_peer label their senders.
std::vector<std::uint8_t> lc02_bench(const std::string& channel, std::uint32_t seq, const std::string& id) {
  lcmx_examples::bench_t m{};
  m.seq = seq;
  m.send_ns = 0;
  m.size = 64;
  m.data.assign(64, 0);
  for (std::size_t i = 0; i < id.size() && i < 8; ++i) m.data[i] = static_cast<std::uint8_t>(id[i]);
  for (std::size_t i = 8; i < m.data.size(); ++i)
    m.data[i] = static_cast<std::uint8_t>((i * 131u + static_cast<std::uint64_t>(seq) * 7u) & 0xffu);
  std::vector<std::uint8_t> d(8 + channel.size() + 1 + static_cast<std::size_t>(m.getEncodedSize()));
  const std::uint32_t magic = htonl(0x4c433032), s = htonl(seq);
  std::memcpy(d.data(), &magic, 4);
  std::memcpy(d.data() + 4, &s, 4);
  std::memcpy(d.data() + 8, channel.c_str(), channel.size() + 1);
  m.encode(d.data() + 8 + channel.size() + 1, 0, m.getEncodedSize());
  return d;
}

in_addr addr(const std::string& text) {
  in_addr a{};
  REQUIRE(::inet_pton(AF_INET, text.c_str(), &a) == 1);
  return a;
}

// The hostile machine's sockets (made inside its namespace, used from this thread).
class Hostile {
 public:
  Hostile(lcmx::test::Emulation& emu, int host) : emu_(emu), host_(host), own_(addr(emu.address(host, "eth"))) {
    udp_ = emu.run_in(host, [] { return ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0); });
    raw_ = emu.run_in(host, [] { return ::socket(AF_INET, SOCK_RAW | SOCK_CLOEXEC, IPPROTO_RAW); });
    REQUIRE(udp_ >= 0);
    REQUIRE(raw_ >= 0);
    const int ttl = 1;
    REQUIRE(::setsockopt(udp_, IPPROTO_IP, IP_MULTICAST_TTL, &ttl, sizeof ttl) == 0);
    REQUIRE(::setsockopt(udp_, IPPROTO_IP, IP_MULTICAST_IF, &own_, sizeof own_) == 0);
    REQUIRE(::setsockopt(raw_, IPPROTO_IP, IP_MULTICAST_IF, &own_, sizeof own_) == 0);
  }
  Hostile(const Hostile&) = delete;
  Hostile& operator=(const Hostile&) = delete;
  ~Hostile() {
    ::close(udp_);
    ::close(raw_);
  }

  // Sends `d` to `to`:`port` from its own address.
  void send(const std::vector<std::uint8_t>& d, in_addr to, std::uint16_t port) {
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr = to;
    a.sin_port = htons(port);
    REQUIRE(::sendto(udp_, d.data(), d.size(), 0, reinterpret_cast<sockaddr*>(&a), sizeof a) ==
            static_cast<ssize_t>(d.size()));
  }
  // Sends `d` to `to`:`port` claiming `from` as its source (a raw IPv4 packet).
  void send_spoofed(const std::vector<std::uint8_t>& d, in_addr from, in_addr to, std::uint16_t port) {
    std::vector<std::uint8_t> pkt(sizeof(iphdr) + sizeof(udphdr) + d.size());
    auto* ip = reinterpret_cast<iphdr*>(pkt.data());
    ip->version = 4;
    ip->ihl = 5;
    ip->ttl = 1;
    ip->protocol = IPPROTO_UDP;
    ip->saddr = from.s_addr;
    ip->daddr = to.s_addr;
    ip->tot_len = htons(static_cast<std::uint16_t>(pkt.size()));  // the kernel fills id and checksum
    auto* udp = reinterpret_cast<udphdr*>(pkt.data() + sizeof(iphdr));
    udp->source = htons(40000);
    udp->dest = htons(port);
    udp->len = htons(static_cast<std::uint16_t>(sizeof(udphdr) + d.size()));
    udp->check = 0;  // none (IPv4 allows it)
    std::memcpy(pkt.data() + sizeof(iphdr) + sizeof(udphdr), d.data(), d.size());
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr = to;
    REQUIRE(::sendto(raw_, pkt.data(), pkt.size(), 0, reinterpret_cast<sockaddr*>(&a), sizeof a) ==
            static_cast<ssize_t>(pkt.size()));
  }

 private:
  lcmx::test::Emulation& emu_;
  int host_;
  in_addr own_;
  int udp_ = -1, raw_ = -1;
};

// A stock receiver of LCM's default group on the victim, made like liblcm's (INADDR_ANY:7667,
// joined where the group routes, hearing every group joined on the host): counts the LC02
// datagrams of `channel` whose label is `id`.
class StockListener {
 public:
  StockListener(lcmx::test::Emulation& emu, int host) {
    fd_ = emu.run_in(host, [] {
      const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
      const int one = 1;
      ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
      sockaddr_in a{};
      a.sin_family = AF_INET;
      a.sin_port = htons(kLcmPort);
      if (::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) return -1;
      ip_mreq m{};
      ::inet_pton(AF_INET, kLcmGroup, &m.imr_multiaddr);
      m.imr_interface.s_addr = htonl(INADDR_ANY);
      if (::setsockopt(fd, IPPROTO_IP, IP_ADD_MEMBERSHIP, &m, sizeof m) != 0) return -1;
      return fd;
    });
    REQUIRE(fd_ >= 0);
  }
  StockListener(const StockListener&) = delete;
  StockListener& operator=(const StockListener&) = delete;
  ~StockListener() { ::close(fd_); }

  // Reads until `n` datagrams of `channel` were seen or `timeout` passed; returns the count.
  long until(const std::string& channel, long n, ms timeout) {
    const auto deadline = Clock::now() + timeout;
    while (count_ < n && Clock::now() < deadline) {
      pollfd p{fd_, POLLIN, 0};
      ::poll(&p, 1, 20);
      char buf[2048];
      for (;;) {
        const ssize_t r = ::recv(fd_, buf, sizeof buf, 0);
        if (r < 8) break;
        if (std::memcmp(buf, "LC02", 4) == 0 && channel == std::string(buf + 8, ::strnlen(buf + 8, r - 8))) ++count_;
      }
    }
    return count_;
  }

 private:
  int fd_ = -1;
  long count_ = 0;
};

}  // namespace

TEST_CASE("attack: messages injected from the LAN into the host-local group - by multicast (ttl 1), by unicast to "
          "port 7667, with a spoofed local source - never reach an lcmx subscriber",
          "[multihost][attack]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(3, 80, Ordinary{});
  const auto ch = h.channel("ATTACK_INJECT");
  auto& sub = h.peer(0, {"sub", "--channel", ch, "--type", "bench", "--queue-depth", "4096", "--expect", "50"});
  REQUIRE(sub.expect("READY"));
  StockListener stock(h.emu(), 0);
  Hostile lan(h.emu(), 2);
  const auto victim = addr(h.emu().address(0, "eth"));
  const auto group = addr(kLcmGroup);
  const auto rx0 = h.emu().rx_bytes(0, "eth");
  std::size_t bytes = 0;
  for (std::uint32_t i = 0; i < 100; ++i) {
    const auto d = lc02_bench(ch, i, "H");
    lan.send(d, group, kLcmPort);     // to the group, as a stock program on the LAN would (ttl 1)
    lan.send(d, victim, kLcmPort);    // to the victim's address and LCM's port
    lan.send_spoofed(d, victim, group, kLcmPort);  // claiming to be the victim itself
    bytes += 3 * d.size();
  }
  // They reached the victim: its LAN interface took them in, and a stock liblcm-like socket
  // (bound to INADDR_ANY:7667) hears the 100 multicast and 100 unicast ones; the kernel drops
  // the spoofed ones (a local source arriving from the LAN: accept_local is off).
  CHECK(h.emu().rx_bytes(0, "eth") - rx0 >= bytes);
  CHECK(stock.until(ch, 200, 5000ms) == 200);
  // Then a stock program on the victim itself: lcmx takes exactly these, none of the hostile.
  auto& lcm = h.lcm_peer(0, {"pub", kLcmDefaultUrl, ch, "50", "500", "64", "L"});
  REQUIRE(lcm.expect("done 50", 15000ms));
  const auto st = of(sub.read_summaries(10000ms), ch);
  INFO(sub.output());
  CHECK(st.num("received") == 50);
  CHECK(st.str("sources") == "L:50");
  CHECK(sub.wait() == 0);
}

namespace {

// Counts the LC02 datagrams of `channel` multicast to the vehicle group `url` ("udpm://G:P?...")
// as heard on a host, with their arrival times.
class GroupListener {
 public:
  GroupListener(lcmx::test::Emulation& emu, int host, const std::string& url) {
    const auto a = url.find("://") + 3, c = url.find(':', a), q = url.find('?', c);
    const std::string group = url.substr(a, c - a);
    const int port = std::stoi(url.substr(c + 1, q - c - 1));
    const auto own = addr(emu.address(host, "eth"));
    fd_ = emu.run_in(host, [&] {
      const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
      const int one = 1, buf = 8 << 20;
      ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
      ::setsockopt(fd, SOL_SOCKET, SO_RCVBUFFORCE, &buf, sizeof buf);
      sockaddr_in sa{};
      sa.sin_family = AF_INET;
      sa.sin_port = htons(static_cast<std::uint16_t>(port));
      ::inet_pton(AF_INET, group.c_str(), &sa.sin_addr);
      if (::bind(fd, reinterpret_cast<sockaddr*>(&sa), sizeof sa) != 0) return -1;
      ip_mreq m{};
      ::inet_pton(AF_INET, group.c_str(), &m.imr_multiaddr);
      m.imr_interface = own;
      if (::setsockopt(fd, IPPROTO_IP, IP_ADD_MEMBERSHIP, &m, sizeof m) != 0) return -1;
      return fd;
    });
    REQUIRE(fd_ >= 0);
  }
  GroupListener(const GroupListener&) = delete;
  GroupListener& operator=(const GroupListener&) = delete;
  ~GroupListener() { ::close(fd_); }

  // Reads what arrived (for at most `wait`), keeping the times of `channel`'s datagrams.
  void read(const std::string& channel, ms wait) {
    const auto deadline = Clock::now() + wait;
    while (Clock::now() < deadline) {
      pollfd p{fd_, POLLIN, 0};
      ::poll(&p, 1, 10);
      char buf[65536];
      for (;;) {
        const ssize_t r = ::recv(fd_, buf, sizeof buf, 0);
        if (r < 8) break;
        if (std::memcmp(buf, "LC02", 4) == 0 && channel == std::string(buf + 8, ::strnlen(buf + 8, r - 8)))
          times_.push_back(Clock::now());
      }
    }
  }
  std::size_t count() const { return times_.size(); }
  // The most datagrams seen within any window of `width`.
  std::size_t densest(ms width) const {
    std::size_t best = 0;
    for (std::size_t i = 0, j = 0; i < times_.size(); ++i) {
      while (times_[i] - times_[j] > width) ++j;
      best = std::max(best, i - j + 1);
    }
    return best;
  }

 private:
  int fd_ = -1;
  std::vector<Clock::time_point> times_;
};

}  // namespace

TEST_CASE("attack: a LAN machine with 200 subscribers of a topic that keeps its last messages makes the publisher "
          "replay at most 32 times per lease - the others in later leases, not at once",
          "[multihost][attack]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(3, 83);  // a vehicle group on "eth", lease 800 ms
  const auto ch = h.channel("ATTACK_REPLAY");
  auto& pub = h.peer(0, {"pub", "--channel", ch, "--type", "bench", "--size", "100", "--count", "20", "--rate",
                         "0", "--history", "20", "--hold", "--id", "V"});
  REQUIRE(pub.expect("PUBLISHED", 20000ms));
  GroupListener lan(h.emu(), 2, h.vehicle_url);
  // 200 subscriber endpoints (one per node) on the hostile machine: each asks for the history.
  auto& hostile = h.peer(2, {"sub", "--channel", ch, "--type", "bench", "--nodes", "200", "--publishers", "1",
                             "--queue-depth", "64"});
  REQUIRE(hostile.expect("MATCHED", 30000ms));
  lan.read("LCMX_HISTORY", 3000ms);
  INFO("replays heard: " << lan.count());
  // On a880031 all 200 went at once. Now at most 32 per lease (800 ms), the rest later.
  CHECK(lan.count() > 0);
  CHECK(lan.densest(h.lease_ms) <= 32 + 1);
  hostile.send("quit");
  pub.send("quit");
  CHECK(pub.wait() == 0);
}
