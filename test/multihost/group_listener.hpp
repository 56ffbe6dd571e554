// A stock socket on an emulated host (test/multihost): what the group carries, seen as any LCM
// program on that host would see it. For tests that count or inspect datagrams on a group.
#pragma once

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "multihost.hpp"

namespace lcmx::mh {

inline in_addr addr(const std::string& text) {
  in_addr a{};
  REQUIRE(::inet_pton(AF_INET, text.c_str(), &a) == 1);
  return a;
}

// A group's address and port, from its URL ("udpm://G:P?...").
struct GroupAddress {
  std::string group;
  std::uint16_t port = 0;
};
inline GroupAddress group_of_url(const std::string& url) {
  const auto a = url.find("://") + 3, c = url.find(':', a), q = url.find('?', c);
  return {url.substr(a, c - a), static_cast<std::uint16_t>(std::stoi(url.substr(c + 1, q - c - 1)))};
}

// A receive socket of `host` (non-blocking, 8 MiB buffer: a test may read it late) bound to
// the group's address and port and joined on the host's "eth" address: what any machine on
// the switch hears of that group. -1 if it cannot be made.
inline int open_group_socket(lcmx::test::Emulation& emu, int host, const GroupAddress& g) {
  const auto own = addr(emu.address(host, "eth"));
  return emu.run_in(host, [&] {
    const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    const int one = 1, buf = 8 << 20;
    ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    ::setsockopt(fd, SOL_SOCKET, SO_RCVBUFFORCE, &buf, sizeof buf);
    sockaddr_in sa{};
    sa.sin_family = AF_INET;
    sa.sin_port = htons(g.port);
    ::inet_pton(AF_INET, g.group.c_str(), &sa.sin_addr);
    if (::bind(fd, reinterpret_cast<sockaddr*>(&sa), sizeof sa) != 0) return -1;
    ip_mreq m{};
    m.imr_multiaddr = sa.sin_addr;
    m.imr_interface = own;
    if (::setsockopt(fd, IPPROTO_IP, IP_ADD_MEMBERSHIP, &m, sizeof m) != 0) return -1;
    return fd;
  });
}

// A stock socket on a host that joined a group ("udpm://G:P?..."): keeps the LC02 datagrams it
// hears (channel, sender address, bytes, arrival time; at most kKeep).
class GroupListener {
 public:
  struct Heard {
    std::string channel;
    in_addr from;
    std::vector<std::uint8_t> payload;  // after the channel's NUL
    Clock::time_point at;
    std::uint32_t seq = 0;  // the LC02 header's sequence number
  };
  static constexpr std::size_t kKeep = 200000;

  GroupListener(lcmx::test::Emulation& emu, int host, const std::string& url) {
    const auto g = group_of_url(url);
    group_ = g.group;
    port_ = g.port;
    fd_ = open_group_socket(emu, host, g);
    REQUIRE(fd_ >= 0);
  }
  GroupListener(const GroupListener&) = delete;
  GroupListener& operator=(const GroupListener&) = delete;
  ~GroupListener() { ::close(fd_); }

  in_addr group() const { return addr(group_); }
  std::uint16_t port() const { return port_; }

  // Reads what arrives for `wait`.
  void read(ms wait) { until([] { return false; }, wait); }
  // Reads until done() (asked after each batch of reads) or `timeout`; returns done().
  bool until(const std::function<bool()>& done, ms timeout) {
    const auto deadline = Clock::now() + timeout;
    for (;;) {
      if (done()) return true;
      if (Clock::now() >= deadline) return false;
      pollfd p{fd_, POLLIN, 0};
      ::poll(&p, 1, 10);
      char buf[65536];
      for (;;) {
        sockaddr_in from{};
        socklen_t len = sizeof from;
        const ssize_t r = ::recvfrom(fd_, buf, sizeof buf, 0, reinterpret_cast<sockaddr*>(&from), &len);
        if (r < 8) break;
        if (std::memcmp(buf, "LC02", 4) != 0 || heard_.size() >= kKeep) continue;
        const std::size_t n = ::strnlen(buf + 8, static_cast<std::size_t>(r) - 8);
        if (8 + n >= static_cast<std::size_t>(r)) continue;  // no NUL: not a message
        std::uint32_t seq_be;
        std::memcpy(&seq_be, buf + 4, sizeof seq_be);
        heard_.push_back({std::string(buf + 8, n), from.sin_addr,
                          std::vector<std::uint8_t>(buf + 8 + n + 1, buf + r), Clock::now(), ntohl(seq_be)});
      }
    }
  }
  const std::vector<Heard>& heard() const { return heard_; }
  // Datagrams of `channel` heard (from `from` only, if given).
  std::size_t count(const std::string& channel, std::optional<in_addr> from = std::nullopt) const {
    return static_cast<std::size_t>(std::count_if(heard_.begin(), heard_.end(), [&](const Heard& h) {
      return h.channel == channel && (!from || h.from.s_addr == from->s_addr);
    }));
  }
  // The most datagrams of `channel` heard within any window of `width`.
  std::size_t densest(const std::string& channel, ms width) const {
    std::vector<Clock::time_point> times;
    for (const auto& h : heard_)
      if (h.channel == channel) times.push_back(h.at);
    std::size_t best = 0;
    for (std::size_t i = 0, j = 0; i < times.size(); ++i) {
      while (times[i] - times[j] > width) ++j;
      best = std::max(best, i - j + 1);
    }
    return best;
  }

 private:
  std::string group_;
  std::uint16_t port_ = 0;
  int fd_ = -1;
  std::vector<Heard> heard_;
};

}  // namespace lcmx::mh
