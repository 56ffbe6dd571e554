// lcmx::test::Emulation: emulated hosts (network namespaces joined by bridges).
// Every test needs root; without it each test is reported "Skipped" (lcmx/test/skip.hpp) with its reason.
#include <arpa/inet.h>
#include <dirent.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <catch2/catch.hpp>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "lcmx/test/catch_netns.hpp"
#include "lcmx/test/netns.hpp"
#include "lcmx/test/watchdog.hpp"

using namespace std::chrono_literals;
using lcmx::test::Child;
using lcmx::test::Emulation;
using lcmx::test::EmulationSpec;
using lcmx::test::LinkSpec;
using lcmx::test::SetupError;
using lcmx::test::Watchdog;
using Clock = std::chrono::steady_clock;

namespace {

Watchdog watchdog(std::chrono::milliseconds t = 25s) {
  return Watchdog(t, Catch::getResultCapture().getCurrentTestName());
}

class Fd {
 public:
  explicit Fd(int fd = -1) : fd_(fd) {}
  Fd(Fd&& o) noexcept : fd_(std::exchange(o.fd_, -1)) {}
  Fd& operator=(Fd&& o) noexcept {
    if (this != &o) {
      reset();
      fd_ = std::exchange(o.fd_, -1);
    }
    return *this;
  }
  ~Fd() { reset(); }
  int get() const { return fd_; }
  void reset() {
    if (fd_ >= 0) ::close(std::exchange(fd_, -1));
  }

 private:
  int fd_;
};

sockaddr_in sa(const std::string& ip, std::uint16_t port) {
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(port);
  REQUIRE(::inet_pton(AF_INET, ip.c_str(), &a.sin_addr) == 1);
  return a;
}

std::uint16_t local_port(int fd) {
  sockaddr_in a{};
  socklen_t len = sizeof a;
  REQUIRE(::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) == 0);
  return ntohs(a.sin_port);
}

// UDP socket bound to bind_ip:port (port 0: any); if group is set, joins it on iface_ip.
Fd udp_socket(const std::string& bind_ip, std::uint16_t port, const std::string& group = {},
              const std::string& iface_ip = {}) {
  Fd fd(::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0));
  REQUIRE(fd.get() >= 0);
  const int one = 1;
  REQUIRE(::setsockopt(fd.get(), SOL_SOCKET, SO_REUSEADDR, &one, sizeof one) == 0);
  const auto a = sa(bind_ip, port);
  REQUIRE(::bind(fd.get(), reinterpret_cast<const sockaddr*>(&a), sizeof a) == 0);
  if (!group.empty()) {
    ip_mreq m{};
    REQUIRE(::inet_pton(AF_INET, group.c_str(), &m.imr_multiaddr) == 1);
    REQUIRE(::inet_pton(AF_INET, iface_ip.c_str(), &m.imr_interface) == 1);
    REQUIRE(::setsockopt(fd.get(), IPPROTO_IP, IP_ADD_MEMBERSHIP, &m, sizeof m) == 0);
  }
  return fd;
}

bool send_to(int fd, const std::string& ip, std::uint16_t port, std::size_t size, char fill = 'x') {
  const std::string payload(size, fill);
  const auto a = sa(ip, port);
  return ::sendto(fd, payload.data(), payload.size(), 0, reinterpret_cast<const sockaddr*>(&a),
                  sizeof a) == static_cast<ssize_t>(size);
}

// Size of the next datagram, or -1 if none arrives before the timeout.
long recv_within(int fd, std::chrono::milliseconds timeout) {
  pollfd p{fd, POLLIN, 0};
  if (::poll(&p, 1, static_cast<int>(timeout.count())) != 1) return -1;
  char buf[65536];
  return static_cast<long>(::recv(fd, buf, sizeof buf, 0));
}

std::set<std::string> netns_names() {
  std::set<std::string> out;
  if (DIR* d = ::opendir("/run/netns")) {
    for (int guard = 0; guard < 100000; ++guard) {
      const dirent* e = ::readdir(d);
      if (e == nullptr) break;
      if (e->d_name[0] != '.') out.insert(e->d_name);
    }
    ::closedir(d);
  }
  return out;
}

// `ip netns list`, names only.
std::set<std::string> ip_netns_list() {
  Child c = lcmx::test::spawn({LCMX_TEST_IP, "netns", "list"});
  std::set<std::string> out;
  for (int guard = 0; guard < 10000; ++guard) {
    auto line = c.read_line(5s);
    if (!line) break;
    out.insert(line->substr(0, line->find(' ')));
  }
  REQUIRE(c.wait(5s) == 0);
  return out;
}

// True once pid no longer runs (gone, or a zombie waiting for whoever adopted it).
bool dead(pid_t pid) {
  FILE* f = std::fopen(("/proc/" + std::to_string(pid) + "/stat").c_str(), "r");
  if (f == nullptr) return true;
  char buf[512] = {};
  const std::size_t n = std::fread(buf, 1, sizeof buf - 1, f);
  std::fclose(f);
  const char* close = std::strrchr(buf, ')');
  if (n == 0 || close == nullptr || close[1] == '\0') return true;
  return close[2] == 'Z' || close[2] == 'X';
}

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

std::string prefix_of(const Emulation& e) { return e.ns(0).substr(0, e.ns(0).rfind('_') + 1); }

}  // namespace

TEST_CASE("two hosts x one link: names and addresses and unicast UDP across the bridge", "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  const auto t0 = Clock::now();
  auto emu = Emulation::create({});
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - t0).count();
  WARN("create 2 hosts x 1 link: " << ms << " ms");

  REQUIRE(emu.hosts() == 2);
  const std::string pfx = "lx" + std::to_string(::getpid()) + "_";
  CHECK(emu.ns(0).rfind(pfx, 0) == 0);
  CHECK(emu.ns(0).substr(emu.ns(0).size() - 3) == "_h0");
  CHECK(emu.ns(1).substr(emu.ns(1).size() - 3) == "_h1");
  CHECK(emu.switch_ns() == prefix_of(emu) + "sw");
  const auto listed = ip_netns_list();
  CHECK(listed.count(emu.ns(0)) == 1);
  CHECK(listed.count(emu.ns(1)) == 1);
  CHECK(listed.count(emu.switch_ns()) == 1);
  CHECK(emu.interface(0, "eth") == "eth");
  CHECK(emu.address(0, "eth") != emu.address(1, "eth"));
  CHECK_THROWS_AS(emu.address(2, "eth"), std::out_of_range);
  CHECK_THROWS_AS(emu.address(0, "pcie"), std::out_of_range);

  const auto a1 = emu.address(1, "eth");
  Fd rx = emu.run_in(1, [&] { return udp_socket(a1, 0); });
  const auto port = local_port(rx.get());
  Fd tx = emu.run_in(0, [&] { return udp_socket("0.0.0.0", 0); });
  REQUIRE(send_to(tx.get(), a1, port, 100));
  CHECK(recv_within(rx.get(), 3s) == 100);

  // The hosts' addresses are not reachable from the root namespace's sockets.
  Fd root_tx(::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0));
  send_to(root_tx.get(), a1, port, 10);
  CHECK(recv_within(rx.get(), 200ms) == -1);
}

TEST_CASE("each host has its own network namespace inode hence its own lcmx host id",
          "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  auto emu = Emulation::create({.hosts = 2});
  auto inode_of = [&](int host) {
    Child c = emu.spawn(host, {"readlink", "/proc/self/ns/net"});
    auto line = c.read_line(5s);
    REQUIRE(line);
    REQUIRE(c.wait(5s) == 0);
    return *line;
  };
  char root[64] = {};
  REQUIRE(::readlink("/proc/self/ns/net", root, sizeof root - 1) > 0);
  const auto h0 = inode_of(0);
  const auto h1 = inode_of(1);
  CHECK(h0.rfind("net:[", 0) == 0);
  CHECK(h0 != h1);
  CHECK(h0 != root);
  CHECK(h1 != root);
  // In-process: a run_in thread sees the host's namespace through /proc/thread-self, while
  // /proc/self still names the process's (main thread's) namespace.
  auto thread_ns = [&](int host) {
    return emu.run_in(host, [] {
      char b[64] = {};
      REQUIRE(::readlink("/proc/thread-self/ns/net", b, sizeof b - 1) > 0);
      return std::string(b);
    });
  };
  CHECK(thread_ns(0) == h0);
  CHECK(thread_ns(1) == h1);
  // Programs in a host see its sysfs, like under `ip netns exec`.
  Child ls = emu.spawn(0, {"ls", "/sys/class/net"});
  std::set<std::string> ifs;
  for (int i = 0; i < 100; ++i) {
    auto l = ls.read_line(5s);
    if (!l) break;
    ifs.insert(*l);
  }
  CHECK(ifs == std::set<std::string>{"eth", "lo"});
}

TEST_CASE("four hosts x two links: unicast on both and multicast floods the first link once",
          "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  const auto t0 = Clock::now();
  auto emu = Emulation::create({.hosts = 4, .links = {{.name = "eth"}, {.name = "pcie"}}});
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - t0).count();
  WARN("create 4 hosts x 2 links: " << ms << " ms");
  CHECK(ms < 1000);
  REQUIRE(emu.hosts() == 4);
  CHECK(emu.links()[0].subnet != emu.links()[1].subnet);
  CHECK(emu.address(2, "pcie") != emu.address(2, "eth"));

  // Unicast on the second link.
  const auto p3 = emu.address(3, "pcie");
  Fd rx = emu.run_in(3, [&] { return udp_socket(p3, 0); });
  Fd tx = emu.run_in(2, [&] { return udp_socket("0.0.0.0", 0); });
  REQUIRE(send_to(tx.get(), p3, local_port(rx.get()), 200));
  CHECK(recv_within(rx.get(), 3s) == 200);

  // Multicast: hosts 1..3 join on their first-link address; host 0 sends through the
  // 224.0.0.0/4 route (no IP_MULTICAST_IF), TTL 1.
  const std::string group = "239.255.91." + std::to_string(::getpid() % 250 + 1);
  const std::uint16_t port = static_cast<std::uint16_t>(20000 + ::getpid() % 20000);
  std::vector<Fd> members;
  for (int h = 1; h < 4; ++h)
    members.push_back(emu.run_in(h, [&] { return udp_socket("0.0.0.0", port, group, emu.address(h, "eth")); }));
  Fd mtx = emu.run_in(0, [&] {
    Fd s = udp_socket("0.0.0.0", 0);
    const unsigned char ttl = 1;
    REQUIRE(::setsockopt(s.get(), IPPROTO_IP, IP_MULTICAST_TTL, &ttl, sizeof ttl) == 0);
    return s;
  });
  const auto eth_before = emu.tx_bytes(0, "eth");
  const auto pcie_before = emu.tx_bytes(0, "pcie");
  const auto rx1_before = emu.rx_bytes(1, "eth");
  constexpr int kCount = 10;
  constexpr std::size_t kSize = 1000;
  for (int i = 0; i < kCount; ++i) REQUIRE(send_to(mtx.get(), group, port, kSize));
  for (auto& m : members)
    for (int i = 0; i < kCount; ++i) CHECK(recv_within(m.get(), 3s) == static_cast<long>(kSize));
  // One transmission per datagram for three receivers: payload + UDP 8 + IPv4 20 + Ethernet 14.
  const auto frame = kSize + 42;
  const auto sent = emu.tx_bytes(0, "eth") - eth_before;
  CHECK(sent >= kCount * frame);
  CHECK(sent < kCount * frame + 200);
  CHECK(emu.tx_bytes(0, "pcie") - pcie_before < 200);
  CHECK(emu.rx_bytes(1, "eth") - rx1_before >= kCount * frame);
}

TEST_CASE("host-local multicast on lo stays inside its host", "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  auto emu = Emulation::create({.hosts = 2});
  const std::string group = "239.255.92." + std::to_string(::getpid() % 250 + 1);
  const std::uint16_t port = static_cast<std::uint16_t>(20000 + ::getpid() % 20000);
  Fd r0 = emu.run_in(0, [&] { return udp_socket("0.0.0.0", port, group, "127.0.0.1"); });
  Fd r1 = emu.run_in(1, [&] { return udp_socket("0.0.0.0", port, group, "127.0.0.1"); });
  Fd tx = emu.run_in(0, [&] {
    Fd s = udp_socket("0.0.0.0", 0);
    in_addr lo{};
    ::inet_pton(AF_INET, "127.0.0.1", &lo);
    REQUIRE(::setsockopt(s.get(), IPPROTO_IP, IP_MULTICAST_IF, &lo, sizeof lo) == 0);
    return s;
  });
  const auto eth_before = emu.tx_bytes(0, "eth");
  REQUIRE(send_to(tx.get(), group, port, 300));
  CHECK(recv_within(r0.get(), 3s) == 300);
  CHECK(recv_within(r1.get(), 200ms) == -1);
  CHECK(emu.tx_bytes(0, "eth") == eth_before);
}

TEST_CASE("link down stops traffic and link up resumes it", "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  auto emu = Emulation::create({.hosts = 2});
  const auto a1 = emu.address(1, "eth");
  Fd rx = emu.run_in(1, [&] { return udp_socket(a1, 0); });
  const auto port = local_port(rx.get());
  Fd tx = emu.run_in(0, [&] { return udp_socket("0.0.0.0", 0); });
  REQUIRE(send_to(tx.get(), a1, port, 64));
  REQUIRE(recv_within(rx.get(), 3s) == 64);

  auto t0 = Clock::now();
  emu.set_link_up(0, "eth", false);
  const auto down_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  for (int i = 0; i < 5; ++i) send_to(tx.get(), a1, port, 64);  // errors allowed: no carrier
  CHECK(recv_within(rx.get(), 300ms) == -1);

  t0 = Clock::now();
  emu.set_link_up(0, "eth", true);
  const auto up_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  bool resumed = false;
  for (int i = 0; i < 50 && !resumed; ++i) {
    send_to(tx.get(), a1, port, 64);
    resumed = recv_within(rx.get(), 100ms) == 64;
  }
  CHECK(resumed);
  WARN("set_link_up: down " << down_ms << " ms, up " << up_ms << " ms, traffic resumed "
                            << ms_since(t0) << " ms after up");

  // The multicast route survived (the host's interface never went administratively down).
  const std::string group = "239.255.93." + std::to_string(::getpid() % 250 + 1);
  const std::uint16_t mport = static_cast<std::uint16_t>(20000 + ::getpid() % 20000);
  Fd m = emu.run_in(1, [&] { return udp_socket("0.0.0.0", mport, group, a1); });
  bool got = false;
  for (int i = 0; i < 50 && !got; ++i) {
    REQUIRE(send_to(tx.get(), group, mport, 32));
    got = recv_within(m.get(), 100ms) == 32;
  }
  CHECK(got);
}

namespace {
// Seconds to move `bytes` over TCP from host 0 to host 1's address on `link`.
double tcp_transfer_seconds(Emulation& emu, const std::string& link, std::size_t bytes) {
  const auto a1 = emu.address(1, link);
  Fd listener = emu.run_in(1, [&] {
    Fd s(::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0));
    const auto a = sa(a1, 0);
    REQUIRE(::bind(s.get(), reinterpret_cast<const sockaddr*>(&a), sizeof a) == 0);
    REQUIRE(::listen(s.get(), 1) == 0);
    return s;
  });
  const auto port = local_port(listener.get());
  Fd client = emu.run_in(0, [&] {
    Fd s(::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0));
    const auto a = sa(a1, port);
    REQUIRE(::connect(s.get(), reinterpret_cast<const sockaddr*>(&a), sizeof a) == 0);
    return s;
  });
  Fd server(::accept4(listener.get(), nullptr, nullptr, SOCK_CLOEXEC));
  REQUIRE(server.get() >= 0);
  const auto t0 = Clock::now();
  std::thread writer([&] {
    const std::string chunk(65536, 'b');
    std::size_t sent = 0;
    for (int guard = 0; guard < 1000000 && sent < bytes; ++guard) {
      const ssize_t n = ::send(client.get(), chunk.data(), std::min(chunk.size(), bytes - sent), MSG_NOSIGNAL);
      if (n <= 0) break;
      sent += static_cast<std::size_t>(n);
    }
  });
  std::size_t got = 0;
  char buf[65536];
  for (int guard = 0; guard < 1000000 && got < bytes; ++guard) {
    pollfd p{server.get(), POLLIN, 0};
    if (::poll(&p, 1, 10000) != 1) break;
    const ssize_t n = ::recv(server.get(), buf, sizeof buf, 0);
    if (n <= 0) break;
    got += static_cast<std::size_t>(n);
  }
  const double s = std::chrono::duration<double>(Clock::now() - t0).count();
  writer.join();
  REQUIRE(got == bytes);
  return s;
}
}  // namespace

TEST_CASE("a rate-limited link measurably slows a bulk transfer", "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  auto emu = Emulation::create({.hosts = 2, .links = {{.name = "eth"}, {.name = "slow", .rate = "40mbit"}}});
  constexpr std::size_t kBytes = 2 << 20;
  const double fast = tcp_transfer_seconds(emu, "eth", kBytes);
  const double slow = tcp_transfer_seconds(emu, "slow", kBytes);
  const double theory = kBytes * 8.0 / 40e6;  // 0.42 s
  WARN("2 MiB over TCP: unlimited " << fast * 1e3 << " ms, 40mbit " << slow * 1e3
                                    << " ms (line rate " << theory * 1e3 << " ms)");
  CHECK(slow > 0.5 * theory);  // cannot beat the rate by more than the burst
  CHECK(slow < 5 * theory);    // and it still flows
  CHECK(slow > 3 * fast);
}

TEST_CASE("link delay: netem when the kernel has it or a clear error otherwise", "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  std::string why;
  const EmulationSpec spec{.hosts = 2, .links = {{.name = "eth", .delay = "2ms"}}};
  if (!lcmx::test::delay_available(&why)) {
    WARN("netem unavailable: " << why);
    CHECK_THROWS_WITH(Emulation::create(spec), Catch::Contains("netem"));
    CHECK(netns_names().count("lx" + std::to_string(::getpid()) + "_") == 0);
    return;
  }
  auto emu = Emulation::create(spec);
  const auto a1 = emu.address(1, "eth");
  Fd echo = emu.run_in(1, [&] { return udp_socket(a1, 0); });
  Fd tx = emu.run_in(0, [&] { return udp_socket(emu.address(0, "eth"), 0); });
  double best = 1e9;
  for (int i = 0; i < 5; ++i) {
    const auto t0 = Clock::now();
    REQUIRE(send_to(tx.get(), a1, local_port(echo.get()), 10));
    REQUIRE(recv_within(echo.get(), 3s) == 10);
    best = std::min(best, std::chrono::duration<double>(Clock::now() - t0).count());
  }
  CHECK(best >= 0.0019);  // one way, one delay
}

TEST_CASE("every host uses cubic TCP congestion control unless told otherwise, whatever the machine uses",
          "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  auto cc_of = [](const Emulation& emu, int host) {
    Child c = emu.spawn(host, {"cat", "/proc/sys/net/ipv4/tcp_congestion_control"});
    auto line = c.read_line(5s);
    CHECK(c.wait(5s) == 0);
    return line.value_or("");
  };
  std::string machine;
  std::ifstream("/proc/sys/net/ipv4/tcp_congestion_control") >> machine;
  {
    auto emu = Emulation::create({.hosts = 2});
    CHECK(cc_of(emu, 0) == "cubic");
    CHECK(cc_of(emu, 1) == "cubic");
  }
  {
    // The machine's own default is left as it was, even where cubic had to be allowed first.
    std::string after;
    std::ifstream("/proc/sys/net/ipv4/tcp_congestion_control") >> after;
    CHECK(after == machine);
  }
  {
    // Empty: what a new namespace inherits from the machine.
    auto emu = Emulation::create({.hosts = 1, .tcp_congestion = ""});
    CHECK(cc_of(emu, 0) == machine);
  }
  {
    auto emu = Emulation::create({.hosts = 1, .tcp_congestion = "reno"});  // built into every kernel
    CHECK(cc_of(emu, 0) == "reno");
  }
  CHECK_THROWS_WITH(Emulation::create({.hosts = 1, .tcp_congestion = "nosuchcc"}),
                    Catch::Contains("nosuchcc") && Catch::Contains("this kernel offers"));
  const std::string mine = "lx" + std::to_string(::getpid()) + "_";
  for (const auto& n : netns_names()) CHECK(n.rfind(mine, 0) != 0);
}

TEST_CASE("destruction removes namespaces and kills processes left inside", "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  std::vector<std::string> names;
  std::optional<Child> survivor;
  {
    auto emu = Emulation::create({.hosts = 2, .links = {{.name = "eth"}, {.name = "pcie"}}});
    names = {emu.ns(0), emu.ns(1), emu.switch_ns()};
    survivor.emplace(emu.spawn(1, {"sleep", "600"}));  // outlives the emulation
    for (const auto& n : names) CHECK(netns_names().count(n) == 1);
  }
  const auto listed = ip_netns_list();
  for (const auto& n : names) CHECK(listed.count(n) == 0);
  for (const auto& n : names) CHECK(netns_names().count(n) == 0);
  CHECK(survivor->wait(5s) == 128 + SIGKILL);  // the destructor killed it
}

TEST_CASE("a child killed by a watchdog and a creator killed outright still get cleaned up",
          "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  // 1. The test's own watchdog kills a hung child: the emulation still tears down normally.
  std::string name;
  {
    auto emu = Emulation::create({.hosts = 2});
    name = emu.ns(0);
    Child hung = emu.spawn(0, {"sleep", "600"});
    CHECK_FALSE(hung.wait(50ms).has_value());
    hung.kill(SIGKILL);
    CHECK(hung.wait(5s) == 128 + SIGKILL);
  }
  CHECK(netns_names().count(name) == 0);

  // 2. The creating process is SIGKILLed (no destructor runs): its namespaces stay until the
  //    next create() (or remove_stale()) sees the creator pid is dead.
  Child holder = lcmx::test::spawn({LCMX_NETNS_HOLDER, "2"});
  auto ready = holder.expect("ready ", 10s);
  REQUIRE(ready);
  char h0[64] = {}, sw[64] = {};
  int sleeper = 0;
  REQUIRE(std::sscanf(ready->c_str(), "ready %63s %63s %d", h0, sw, &sleeper) == 3);
  CHECK(netns_names().count(h0) == 1);
  holder.kill(SIGKILL);
  REQUIRE(holder.wait(5s) == 128 + SIGKILL);
  // Left behind (unless another test process's create() already removed them: ctest -j).
  INFO("left behind after SIGKILL: " << netns_names().count(h0));
  Emulation::remove_stale();
  CHECK(netns_names().count(h0) == 0);
  CHECK(netns_names().count(sw) == 0);
  // The sleeper was killed (its parent died: PR_SET_PDEATHSIG; or remove_stale found it inside).
  bool gone = false;
  for (int i = 0; i < 500 && !gone; ++i) {
    gone = dead(sleeper);
    if (!gone) std::this_thread::sleep_for(2ms);  // not our child: poll its state
  }
  CHECK(gone);

  // 3. A Watchdog that fires in a process removes that process's namespaces before aborting.
  Child fired = lcmx::test::spawn({LCMX_NETNS_HOLDER, "2", "watchdog"});
  auto r2 = fired.expect("ready ", 10s);
  REQUIRE(r2);
  REQUIRE(std::sscanf(r2->c_str(), "ready %63s %63s %d", h0, sw, &sleeper) == 3);
  CHECK(fired.wait(10s) == 128 + SIGABRT);
  CHECK(netns_names().count(h0) == 0);
  CHECK(netns_names().count(sw) == 0);
}

TEST_CASE("emulations created in parallel do not collide", "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  std::optional<Emulation> a, b;
  std::thread ta([&] { a.emplace(Emulation::create({.hosts = 2})); });
  std::thread tb([&] { b.emplace(Emulation::create({.hosts = 2})); });
  ta.join();
  tb.join();
  REQUIRE(a);
  REQUIRE(b);
  CHECK(a->ns(0) != b->ns(0));
  CHECK(a->switch_ns() != b->switch_ns());
  CHECK(a->links()[0].subnet != b->links()[0].subnet);
  // Each works; A's host cannot reach B's host (different L2 networks, no route).
  const auto b1 = b->address(1, "eth");
  Fd rb = b->run_in(1, [&] { return udp_socket(b1, 0); });
  Fd ta_sock = a->run_in(0, [&] { return udp_socket("0.0.0.0", 0); });
  send_to(ta_sock.get(), b1, local_port(rb.get()), 50);
  CHECK(recv_within(rb.get(), 200ms) == -1);
  Fd tb_sock = b->run_in(0, [&] { return udp_socket("0.0.0.0", 0); });
  REQUIRE(send_to(tb_sock.get(), b1, local_port(rb.get()), 50));
  CHECK(recv_within(rb.get(), 3s) == 50);
}

TEST_CASE("setup faults throw SetupError naming the problem and run_in rethrows", "[multihost]") {
  LCMX_REQUIRE_NETNS();
  auto wd = watchdog();
  CHECK_THROWS_AS(Emulation::create({.hosts = 0}), SetupError);
  CHECK_THROWS_WITH(Emulation::create({.links = {{.name = "Bad-Name"}}}), Catch::Contains("Bad-Name"));
  CHECK_THROWS_WITH(Emulation::create({.links = {{.name = "eth", .rate = "fast"}}}), Catch::Contains("fast"));
  CHECK_THROWS_WITH(Emulation::create({.links = {{.name = "a"}, {.name = "a"}}}), Catch::Contains("twice"));
  CHECK_THROWS_WITH(Emulation::create({.hosts = 5, .links = {{.subnet = "10.9.9.0/30"}}}),
                    Catch::Contains("too small"));
  // A fault in the middle of creation (tc rejects the rate after the namespaces exist): the
  // message carries the command and its stderr, and nothing is left behind.
  try {
    Emulation::create({.hosts = 2, .links = {{.name = "eth", .rate = "0.5bit"}}});
    FAIL("no exception");
  } catch (const SetupError& e) {
    const std::string what = e.what();
    CHECK_THAT(what, Catch::Contains("tc -n lx") && Catch::Contains("qdisc add dev eth root") &&
                         Catch::Contains("stderr: ") && Catch::Contains("rate"));
  }
  const std::string mine = "lx" + std::to_string(::getpid()) + "_";
  for (const auto& n : netns_names()) CHECK(n.rfind(mine, 0) != 0);  // nothing left by failures

  auto emu = Emulation::create({.hosts = 1, .links = {{.name = "eth", .subnet = "192.168.77.0/24"}}});
  CHECK(emu.address(0, "eth") == "192.168.77.1");
  CHECK_THROWS_WITH(emu.run_in(0, []() -> int { throw std::runtime_error("inside"); }), "inside");
  CHECK_THROWS_AS(emu.spawn(0, {"/nonexistent/program"}), SetupError);
  {
    auto guard = emu.enter(0);
    char b[64] = {};
    REQUIRE(::readlink("/proc/thread-self/ns/net", b, sizeof b - 1) > 0);
    Child c = lcmx::test::spawn({"readlink", "/proc/self/ns/net"});  // inherits the thread's netns
    CHECK(c.read_line(5s) == std::string(b));
  }
}
