#pragma once
// Helpers for lcmx::udpm tests: unique groups, test payloads, hand-made datagrams, a raw UDP
// sender, child processes read line by line with deadlines, and RAII network namespaces.
#include <arpa/inet.h>
#include <dirent.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <net/if.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <catch2/catch.hpp>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <functional>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <vector>

#include "lcmx/udpm/udpm.hpp"

extern char** environ;

namespace lcmx::udpm::test {

using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

// ---- unique group and port per (process, test) ----
inline std::uint64_t fnv1a(std::string_view s, std::uint64_t h = 1469598103934665603ull) {
  for (char c : s) h = (h ^ static_cast<unsigned char>(c)) * 1099511628211ull;
  return h;
}

// A group 239.255.x.y and a port in 20000..59999 derived from the pid and the running test's
// name (plus `salt` for several groups in one test), never LCM's default 239.255.76.67:7667.
inline GroupConfig unique_config(std::string_view salt = {}) {
  const std::string name = Catch::getResultCapture().getCurrentTestName();
  std::uint64_t h = fnv1a(name + "/" + std::string(salt), fnv1a(std::to_string(::getpid())));
  h ^= h >> 29;
  GroupConfig cfg;
  const unsigned x = static_cast<unsigned>((h >> 8) & 0xff), y = static_cast<unsigned>(h & 0xff);
  cfg.address = "239.255." + std::to_string(x == 76 ? 77 : x) + "." + std::to_string(y == 0 ? 1 : y);
  cfg.port = static_cast<std::uint16_t>(20000 + (h >> 16) % 40000);
  cfg.interface = "lo";
  cfg.ttl = 0;
  return cfg;
}

// ---- the test payload (same as peer/lcmx_udpm_peer.cpp) ----
inline std::vector<std::byte> make_payload(std::uint32_t index, std::size_t size) {
  std::vector<std::byte> p(size);
  for (std::size_t j = 0; j < size; ++j) p[j] = static_cast<std::byte>(j * 131 + index * 17 + 7);
  for (std::size_t j = 0; j < 4 && j < size; ++j) p[j] = static_cast<std::byte>(index >> (8 * j));
  return p;
}
inline std::uint32_t payload_index(std::span<const std::byte> p) {
  std::uint32_t index = 0;
  for (std::size_t j = 0; j < 4 && j < p.size(); ++j) index |= std::uint32_t(p[j]) << (8 * j);
  return index;
}
inline bool payload_ok(std::span<const std::byte> p) {
  const auto expect = make_payload(payload_index(p), p.size());
  return p.empty() || std::memcmp(p.data(), expect.data(), p.size()) == 0;
}

// ---- hand-made datagrams (written from the format description, independent of the library) ----
inline void put32(std::vector<std::byte>& v, std::uint32_t x) {
  for (int s = 24; s >= 0; s -= 8) v.push_back(static_cast<std::byte>(x >> s));
}
inline void put16(std::vector<std::byte>& v, std::uint16_t x) {
  v.push_back(static_cast<std::byte>(x >> 8));
  v.push_back(static_cast<std::byte>(x));
}
inline void put_str(std::vector<std::byte>& v, std::string_view s, bool nul = true) {
  for (char c : s) v.push_back(static_cast<std::byte>(c));
  if (nul) v.push_back(std::byte{0});
}
inline std::vector<std::byte> lc02(std::uint32_t seq, std::string_view channel, std::span<const std::byte> data) {
  std::vector<std::byte> v;
  put32(v, 0x4c433032);
  put32(v, seq);
  put_str(v, channel);
  v.insert(v.end(), data.begin(), data.end());
  return v;
}
// One LC03 fragment; `channel` is written (with its NUL) only when given.
inline std::vector<std::byte> lc03(std::uint32_t seq, std::uint32_t total, std::uint32_t offset, std::uint16_t no,
                                   std::uint16_t count, std::optional<std::string_view> channel,
                                   std::span<const std::byte> data) {
  std::vector<std::byte> v;
  put32(v, 0x4c433033);
  put32(v, seq);
  put32(v, total);
  put32(v, offset);
  put16(v, no);
  put16(v, count);
  if (channel) put_str(v, *channel);
  v.insert(v.end(), data.begin(), data.end());
  return v;
}
// Cuts a message exactly as liblcm 1.3.1 does on Linux (fragment payload 65487).
inline std::vector<std::vector<std::byte>> lc03_message(std::uint32_t seq, std::string_view channel,
                                                        std::span<const std::byte> data) {
  const std::size_t frag = 65487;
  const std::size_t whole = channel.size() + 1 + data.size();
  const std::size_t count = (whole + frag - 1) / frag;
  std::vector<std::vector<std::byte>> out;
  std::size_t offset = 0;
  for (std::size_t no = 0; no < count; ++no) {
    const std::size_t len = no == 0 ? frag - channel.size() - 1 : std::min(frag, data.size() - offset);
    out.push_back(lc03(seq, static_cast<std::uint32_t>(data.size()), static_cast<std::uint32_t>(offset),
                       static_cast<std::uint16_t>(no), static_cast<std::uint16_t>(count),
                       no == 0 ? std::optional<std::string_view>(channel) : std::nullopt,
                       data.subspan(offset, len)));
    offset += len;
  }
  return out;
}

// ---- a raw UDP sender to a group on lo ----
class RawSender {
 public:
  explicit RawSender(const GroupConfig& cfg) {
    fd_ = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    REQUIRE(fd_ >= 0);
    ip_mreqn m{};
    m.imr_ifindex = static_cast<int>(::if_nametoindex("lo"));
    REQUIRE(::setsockopt(fd_, IPPROTO_IP, IP_MULTICAST_IF, &m, sizeof m) == 0);
    const unsigned char ttl = 0;
    REQUIRE(::setsockopt(fd_, IPPROTO_IP, IP_MULTICAST_TTL, &ttl, sizeof ttl) == 0);
    sockaddr_in src{};
    src.sin_family = AF_INET;
    src.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    REQUIRE(::bind(fd_, reinterpret_cast<sockaddr*>(&src), sizeof src) == 0);
    socklen_t len = sizeof src;
    REQUIRE(::getsockname(fd_, reinterpret_cast<sockaddr*>(&src), &len) == 0);
    source_ = Source{src.sin_addr.s_addr, src.sin_port};
    dest_.sin_family = AF_INET;
    REQUIRE(::inet_pton(AF_INET, cfg.address.c_str(), &dest_.sin_addr) == 1);
    dest_.sin_port = htons(cfg.port);
  }
  RawSender(const RawSender&) = delete;
  RawSender& operator=(const RawSender&) = delete;
  ~RawSender() { ::close(fd_); }
  void send(std::span<const std::byte> d) {
    const auto n = ::sendto(fd_, d.data(), d.size(), 0, reinterpret_cast<const sockaddr*>(&dest_), sizeof dest_);
    REQUIRE(n == static_cast<ssize_t>(d.size()));
  }
  Source source() const { return source_; }

 private:
  int fd_ = -1;
  sockaddr_in dest_{};
  Source source_{};
};

// Polls `group` until `done()` or the deadline; returns done().
template <typename Done>
bool poll_until(Group& group, const Group::Handler& on_message, Done done,
                std::chrono::milliseconds timeout = 5000ms) {
  const auto deadline = Clock::now() + timeout;
  while (!done()) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    if (left.count() <= 0) break;
    group.poll(std::min(left, std::chrono::milliseconds(100)), on_message);
  }
  return done();
}

// ---- child processes ----
// Runs argv with stdout on a pipe (stderr inherited). The destructor kills and reaps it.
class Child {
 public:
  explicit Child(const std::vector<std::string>& argv) {
    int fds[2];
    if (::pipe2(fds, O_CLOEXEC) != 0) throw std::runtime_error("pipe2 failed");
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_adddup2(&fa, fds[1], STDOUT_FILENO);
    std::vector<char*> args;
    for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    const int rc = ::posix_spawnp(&pid_, args[0], &fa, nullptr, args.data(), environ);
    posix_spawn_file_actions_destroy(&fa);
    ::close(fds[1]);
    if (rc != 0) {
      ::close(fds[0]);
      pid_ = -1;
      throw std::runtime_error("cannot start " + argv[0] + ": " + std::strerror(rc));
    }
    out_ = fds[0];
  }
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;
  ~Child() {
    if (pid_ > 0) {
      ::kill(pid_, SIGKILL);
      int st = 0;
      ::waitpid(pid_, &st, 0);
    }
    if (out_ >= 0) ::close(out_);
  }

  // Next stdout line, or nullopt on EOF or when the deadline passes.
  std::optional<std::string> read_line(std::chrono::milliseconds timeout = 10000ms) {
    const auto deadline = Clock::now() + timeout;
    for (;;) {
      if (const auto nl = buf_.find('\n'); nl != std::string::npos) {
        std::string line = buf_.substr(0, nl);
        buf_.erase(0, nl + 1);
        return line;
      }
      if (eof_) return std::nullopt;
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
      if (left.count() <= 0) return std::nullopt;
      pollfd p{out_, POLLIN, 0};
      if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) continue;
      char chunk[4096];
      const ssize_t n = ::read(out_, chunk, sizeof chunk);
      if (n <= 0) eof_ = true;
      else buf_.append(chunk, static_cast<std::size_t>(n));
    }
  }

  // Waits for exit up to the deadline (then SIGKILL); returns the exit code, or -signal.
  int wait(std::chrono::milliseconds timeout = 10000ms) {
    const auto deadline = Clock::now() + timeout;
    while (read_line(std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()))) {
    }
    int st = 0;
    for (;;) {
      const pid_t r = ::waitpid(pid_, &st, WNOHANG);
      if (r == pid_) break;
      if (Clock::now() >= deadline) {
        ::kill(pid_, SIGKILL);
        ::waitpid(pid_, &st, 0);
        break;
      }
      pollfd p{out_, POLLIN, 0};  // stdout is at EOF: poll returns at once; bounded by the deadline
      ::poll(&p, 1, 10);
    }
    pid_ = -1;
    return WIFEXITED(st) ? WEXITSTATUS(st) : -WTERMSIG(st);
  }

  void signal(int sig) {
    if (pid_ > 0) ::kill(pid_, sig);
  }
  pid_t pid() const { return pid_; }

 private:
  pid_t pid_ = -1;
  int out_ = -1;
  std::string buf_;
  bool eof_ = false;
};

inline int run(const std::vector<std::string>& argv) {
  Child c(argv);
  return c.wait(10000ms);
}

// ---- network namespaces ----
// Creates "lcmxt_<pid>_<n>" with lo up and a multicast route on lo; deletes it on destruction.
// NetnsRoute::lan instead looks like an ordinary computer: a veth pair lan0/lan1 inside the
// namespace, lan0 10.77.0.1/24 with the default route (via 10.77.0.254), no multicast route.
// Namespaces left behind by dead test processes (lcmxt_<pid>_* whose pid is gone) are removed.
enum class NetnsRoute { lo, lan };
inline constexpr const char* kLanAddress = "10.77.0.1";

class Netns {
 public:
  explicit Netns(NetnsRoute route = NetnsRoute::lo) {
    remove_stale();
    static int counter = 0;
    name_ = "lcmxt_" + std::to_string(::getpid()) + "_" + std::to_string(++counter);
    if (run({LCMX_IP, "netns", "add", name_}) != 0) throw std::runtime_error("ip netns add " + name_ + " failed");
    created_ = true;
    bool ok = run({LCMX_IP, "-n", name_, "link", "set", "lo", "up"}) == 0;
    if (route == NetnsRoute::lo) {
      ok = ok && run({LCMX_IP, "-n", name_, "route", "add", "224.0.0.0/4", "dev", "lo"}) == 0;
    } else {
      ok = ok && run({LCMX_IP, "-n", name_, "link", "add", "lan0", "type", "veth", "peer", "name", "lan1"}) == 0 &&
           run({LCMX_IP, "-n", name_, "addr", "add", std::string(kLanAddress) + "/24", "dev", "lan0"}) == 0 &&
           run({LCMX_IP, "-n", name_, "link", "set", "lan1", "up"}) == 0 &&
           run({LCMX_IP, "-n", name_, "link", "set", "lan0", "up"}) == 0 &&
           run({LCMX_IP, "-n", name_, "route", "add", "default", "via", "10.77.0.254", "dev", "lan0"}) == 0;
    }
    if (!ok) {
      del();
      throw std::runtime_error("cannot set up the interfaces of " + name_);
    }
  }
  Netns(const Netns&) = delete;
  Netns& operator=(const Netns&) = delete;
  ~Netns() { del(); }
  const std::string& name() const { return name_; }

 private:
  void del() {
    if (created_) run({LCMX_IP, "netns", "del", name_});
    created_ = false;
  }
  static void remove_stale() {
    DIR* d = ::opendir("/run/netns");
    if (d == nullptr) return;
    std::vector<std::string> stale;
    for (int guard = 0; guard < 100000; ++guard) {
      const dirent* e = ::readdir(d);
      if (e == nullptr) break;
      const std::string n = e->d_name;
      if (n.rfind("lcmxt_", 0) != 0) continue;
      const auto us = n.find('_', 6);
      if (us == std::string::npos) continue;
      const pid_t pid = static_cast<pid_t>(std::atol(n.substr(6, us - 6).c_str()));
      if (pid > 0 && ::kill(pid, 0) != 0 && errno == ESRCH) stale.push_back(n);
    }
    ::closedir(d);
    for (const auto& n : stale) run({LCMX_IP, "netns", "del", n});
  }
  std::string name_;
  bool created_ = false;
};

// Moves the calling thread into a namespace (sockets it creates and processes it starts live
// there) and back on destruction.
class EnterNetns {
 public:
  explicit EnterNetns(const Netns& ns) {
    home_ = ::open("/proc/thread-self/ns/net", O_RDONLY | O_CLOEXEC);
    REQUIRE(home_ >= 0);
    const int fd = ::open(("/run/netns/" + ns.name()).c_str(), O_RDONLY | O_CLOEXEC);
    REQUIRE(fd >= 0);
    const int rc = ::setns(fd, CLONE_NEWNET);
    ::close(fd);
    REQUIRE(rc == 0);
  }
  EnterNetns(const EnterNetns&) = delete;
  EnterNetns& operator=(const EnterNetns&) = delete;
  ~EnterNetns() {
    if (::setns(home_, CLONE_NEWNET) != 0) std::abort();  // cannot continue in the wrong namespace
    ::close(home_);
  }

 private:
  int home_ = -1;
};

}  // namespace lcmx::udpm::test
