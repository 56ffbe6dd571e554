#include "lcmx/udpm/group.hpp"

#include <arpa/inet.h>
#include <linux/filter.h>
#include <ifaddrs.h>
#include <net/if.h>
#include <netinet/in.h>
#include <poll.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <mutex>
#include <optional>

#include "lcmx/udpm/error.hpp"
#include "lcmx/udpm/wire.hpp"
#include "reassembler.hpp"

#ifndef SO_RXQ_OVFL
#define SO_RXQ_OVFL 40
#endif

namespace lcmx::udpm {
namespace {

constexpr std::size_t kRecvBatch = 16;               // datagrams per recvmmsg
constexpr std::size_t kRecvSlot = 65536;             // > kMaxDatagramSize
constexpr std::size_t kMaxDatagramsPerDrain = 4096;  // bounds one drain() call
constexpr std::size_t kSendBatch = 32;               // fragments per sendmmsg

[[noreturn]] void throw_errno(const std::string& what, int err) {
  throw Error(Error::Code::system, what + ": " + std::strerror(err), err);
}

// Closes a file descriptor on scope exit unless released.
class Fd {
 public:
  Fd() = default;
  explicit Fd(int fd) : fd_(fd) {}
  Fd(Fd&& o) noexcept : fd_(o.fd_) { o.fd_ = -1; }
  Fd& operator=(Fd&& o) noexcept {
    if (this != &o) {
      reset();
      fd_ = o.fd_;
      o.fd_ = -1;
    }
    return *this;
  }
  ~Fd() { reset(); }
  int get() const noexcept { return fd_; }
  void reset() noexcept {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
  }

 private:
  int fd_ = -1;
};

template <typename T>
void set_opt(int fd, int level, int name, const T& value, const char* what) {
  if (::setsockopt(fd, level, name, &value, sizeof value) != 0) throw_errno(what, errno);
}

void store_u32(std::byte* p, std::uint32_t v) {
  p[0] = std::byte(v >> 24);
  p[1] = std::byte(v >> 16);
  p[2] = std::byte(v >> 8);
  p[3] = std::byte(v);
}
void store_u16(std::byte* p, std::uint16_t v) {
  p[0] = std::byte(v >> 8);
  p[1] = std::byte(v);
}

void validate(const GroupConfig& cfg, in_addr& group) {
  auto bad = [](const std::string& why) { throw Error(Error::Code::invalid_config, "udpm group: " + why); };
  if (inet_pton(AF_INET, cfg.address.c_str(), &group) != 1)
    bad("bad address '" + cfg.address + "' (expected a dotted IPv4 address)");
  if (!IN_MULTICAST(ntohl(group.s_addr)))
    bad("address '" + cfg.address + "' is not IPv4 multicast (224.0.0.0/4)");
  if (cfg.port == 0) bad("port 0 (expected 1..65535)");
  if (cfg.ttl < 0 || cfg.ttl > 255) bad("ttl " + std::to_string(cfg.ttl) + " (expected 0..255)");
  if (cfg.recv_buffer_bytes < 0) bad("negative recv_buffer_bytes " + std::to_string(cfg.recv_buffer_bytes));
  if (cfg.interface.empty() || cfg.interface.size() >= IFNAMSIZ)
    bad("bad interface name '" + cfg.interface + "'");
}

// The interface's index and first IPv4 address (network order).
std::pair<int, in_addr> resolve_interface(const std::string& name) {
  const unsigned index = ::if_nametoindex(name.c_str());
  if (index == 0)
    throw Error(Error::Code::no_such_interface, "udpm group: no interface named '" + name + "'", errno);
  ifaddrs* list = nullptr;
  if (::getifaddrs(&list) != 0) throw_errno("udpm group: getifaddrs", errno);
  std::optional<in_addr> found;
  for (ifaddrs* i = list; i != nullptr && !found; i = i->ifa_next)
    if (i->ifa_addr != nullptr && i->ifa_addr->sa_family == AF_INET && name == i->ifa_name)
      found = reinterpret_cast<const sockaddr_in*>(i->ifa_addr)->sin_addr;
  ::freeifaddrs(list);
  if (!found)
    throw Error(Error::Code::no_such_interface, "udpm group: interface '" + name + "' has no IPv4 address");
  return {static_cast<int>(index), *found};
}

// A classic BPF socket filter for the receive socket that drops datagrams from `own` (this
// Group's send socket) and accepts everything else. For UDP the filter runs on the datagram
// with the UDP header at offset 0 (source port) and the IPv4 header at SKF_NET_OFF (source
// address at +12); BPF_ABS loads are big-endian, hence the ntoh*.
void drop_own_datagrams(int fd, const Source& own) {
  sock_filter code[] = {
      BPF_STMT(BPF_LD | BPF_W | BPF_ABS, static_cast<std::uint32_t>(SKF_NET_OFF) + 12),
      BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, ntohl(own.address_be), 0, 3),
      BPF_STMT(BPF_LD | BPF_H | BPF_ABS, 0),
      BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, ntohs(own.port_be), 0, 1),
      BPF_STMT(BPF_RET | BPF_K, 0),           // ours: drop
      BPF_STMT(BPF_RET | BPF_K, 0xffffffffu),  // anyone else's: keep all of it
  };
  sock_fprog prog{static_cast<unsigned short>(std::size(code)), code};
  set_opt(fd, SOL_SOCKET, SO_ATTACH_FILTER, prog, "udpm group: SO_ATTACH_FILTER");
}

}  // namespace

std::string to_string(const Source& source) {
  char buf[INET_ADDRSTRLEN] = {};
  in_addr a{};
  a.s_addr = source.address_be;
  ::inet_ntop(AF_INET, &a, buf, sizeof buf);
  return std::string(buf) + ":" + std::to_string(ntohs(source.port_be));
}

struct Group::Impl {
  GroupConfig cfg;
  Fd recv_fd;
  Fd send_fd;
  sockaddr_in dest{};
  Source local{};
  int effective_rcvbuf = 0;

  // --- send side (any thread) ---
  std::mutex send_mutex;  // guards sequence and keeps one message's fragments together
  std::uint32_t sequence = 0;
  std::atomic<std::uint64_t> packets_sent{0}, messages_sent{0}, bytes_sent{0};

  // --- receive side (the receive thread) ---
  detail::Reassembler reassembler;
  std::unique_ptr<std::byte[]> slots;  // kRecvBatch * kRecvSlot
  mmsghdr msgs[kRecvBatch]{};
  iovec iovs[kRecvBatch]{};
  sockaddr_in names[kRecvBatch]{};
  alignas(cmsghdr) char controls[kRecvBatch][CMSG_SPACE(sizeof(std::uint32_t)) + 16]{};
  std::size_t batch_size = 0;  // datagrams in the current batch
  std::size_t batch_next = 0;  // next one to handle (resumes after a throwing callback)
  Counters recv_counters;
  mutable Counters snapshot;

  explicit Impl(const GroupConfig& c)
      : cfg(c),
        reassembler({c.max_reassembly_bytes, c.max_partial_messages,
                     std::chrono::duration_cast<detail::Reassembler::Clock::duration>(c.reassembly_timeout)}),
        slots(std::make_unique_for_overwrite<std::byte[]>(kRecvBatch * kRecvSlot)) {}

  void send_all(mmsghdr* m, std::size_t n) {
    std::size_t done = 0;
    while (done < n) {
      const int r = ::sendmmsg(send_fd.get(), m + done, static_cast<unsigned>(n - done), 0);
      if (r < 0) {
        if (errno == EINTR) continue;
        throw_errno("udpm publish on " + to_url(cfg), errno);
      }
      for (int i = 0; i < r; ++i) {
        const std::size_t expected = [&] {
          std::size_t s = 0;
          for (std::size_t k = 0; k < m[done + i].msg_hdr.msg_iovlen; ++k) s += m[done + i].msg_hdr.msg_iov[k].iov_len;
          return s;
        }();
        if (m[done + i].msg_len != expected)
          throw Error(Error::Code::system, "udpm publish: short send (" + std::to_string(m[done + i].msg_len) +
                                               " of " + std::to_string(expected) + " bytes)");
        bytes_sent.fetch_add(expected, std::memory_order_relaxed);
      }
      packets_sent.fetch_add(static_cast<std::uint64_t>(r), std::memory_order_relaxed);
      done += static_cast<std::size_t>(r);
    }
  }

  void publish(std::string_view channel, std::span<const std::byte> payload) {
    if (channel.size() > kMaxChannelLength)
      throw Error(Error::Code::channel_too_long, "udpm publish: channel '" + std::string(channel) + "' is " +
                                                     std::to_string(channel.size()) + " bytes (max 63)");
    if (channel.find('\0') != std::string_view::npos)
      throw Error(Error::Code::invalid_channel, "udpm publish: channel name contains a NUL byte");
    if (payload.size() > kMaxMessageSize)
      throw Error(Error::Code::message_too_large, "udpm publish on '" + std::string(channel) + "': " +
                                                      std::to_string(payload.size()) + " bytes exceed " +
                                                      std::to_string(kMaxMessageSize));
    static constexpr char kNul = '\0';
    auto* chan = const_cast<char*>(channel.data());
    auto* data = const_cast<std::byte*>(payload.data());
    const std::size_t nframes = datagram_count(channel.size(), payload.size());

    std::lock_guard lock(send_mutex);
    const std::uint32_t seq = sequence++;
    mmsghdr m[kSendBatch]{};
    if (nframes == 1) {
      std::byte hdr[kShortHeaderSize];
      store_u32(hdr, kMagicShort);
      store_u32(hdr + 4, seq);
      iovec all[4] = {{hdr, sizeof hdr}, {chan, channel.size()}, {const_cast<char*>(&kNul), 1},
                      {data, payload.size()}};
      m[0].msg_hdr.msg_name = &dest;
      m[0].msg_hdr.msg_namelen = sizeof dest;
      m[0].msg_hdr.msg_iov = all;
      m[0].msg_hdr.msg_iovlen = payload.empty() ? 3 : 4;
      send_all(m, 1);
    } else {
      // LC03, exactly as liblcm 1.3.1 cuts it (see wire.hpp).
      std::byte hdrs[kSendBatch][kLongHeaderSize];
      iovec iov[kSendBatch][4];
      const std::size_t first = kFragmentMaxPayload - (channel.size() + 1);
      std::size_t offset = 0;
      for (std::size_t base = 0; base < nframes; base += kSendBatch) {
        const std::size_t n = std::min(kSendBatch, nframes - base);
        for (std::size_t i = 0; i < n; ++i) {
          const std::size_t no = base + i;
          std::byte* h = hdrs[i];
          store_u32(h, kMagicLong);
          store_u32(h + 4, seq);
          store_u32(h + 8, static_cast<std::uint32_t>(payload.size()));
          store_u32(h + 12, static_cast<std::uint32_t>(offset));
          store_u16(h + 16, static_cast<std::uint16_t>(no));
          store_u16(h + 18, static_cast<std::uint16_t>(nframes));
          mmsghdr& mm = m[i];
          mm = mmsghdr{};
          mm.msg_hdr.msg_name = &dest;
          mm.msg_hdr.msg_namelen = sizeof dest;
          mm.msg_hdr.msg_iov = iov[i];
          iov[i][0] = {h, kLongHeaderSize};
          std::size_t len;
          if (no == 0) {
            len = first;
            iov[i][1] = {chan, channel.size()};
            iov[i][2] = {const_cast<char*>(&kNul), 1};
            iov[i][3] = {data, len};
            mm.msg_hdr.msg_iovlen = 4;
          } else {
            len = std::min(kFragmentMaxPayload, payload.size() - offset);
            iov[i][1] = {data + offset, len};
            mm.msg_hdr.msg_iovlen = 2;
          }
          offset += len;
        }
        send_all(m, n);
      }
    }
    messages_sent.fetch_add(1, std::memory_order_relaxed);
  }

  void arm_batch() {
    for (std::size_t i = 0; i < kRecvBatch; ++i) {
      iovs[i] = {slots.get() + i * kRecvSlot, kRecvSlot};
      msgs[i].msg_hdr = msghdr{};
      msgs[i].msg_hdr.msg_name = &names[i];
      msgs[i].msg_hdr.msg_namelen = sizeof names[i];
      msgs[i].msg_hdr.msg_iov = &iovs[i];
      msgs[i].msg_hdr.msg_iovlen = 1;
      msgs[i].msg_hdr.msg_control = controls[i];
      msgs[i].msg_hdr.msg_controllen = sizeof controls[i];
      msgs[i].msg_len = 0;
    }
  }

  // Handles datagram i of the current batch; returns 1 if it delivered a message.
  std::size_t handle(std::size_t i, const Handler& on_message) {
    mmsghdr& mm = msgs[i];
    for (cmsghdr* c = CMSG_FIRSTHDR(&mm.msg_hdr); c != nullptr; c = CMSG_NXTHDR(&mm.msg_hdr, c)) {
      if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SO_RXQ_OVFL) {
        std::uint32_t dropped = 0;
        std::memcpy(&dropped, CMSG_DATA(c), sizeof dropped);
        recv_counters.kernel_dropped = dropped;
      }
    }
    ++recv_counters.packets_received;
    recv_counters.bytes_received += mm.msg_len;
    if ((mm.msg_hdr.msg_flags & MSG_TRUNC) != 0 || mm.msg_hdr.msg_namelen < sizeof(sockaddr_in) ||
        names[i].sin_family != AF_INET) {
      ++recv_counters.malformed_dropped;
      return 0;
    }
    const std::span<const std::byte> datagram(slots.get() + i * kRecvSlot, mm.msg_len);
    const auto parsed = parse_datagram(datagram);
    if (!parsed) {
      ++recv_counters.malformed_dropped;
      return 0;
    }
    const Source source{names[i].sin_addr.s_addr, names[i].sin_port};
    if (!parsed->fragment) {
      ++recv_counters.messages_received;
      on_message(Message{parsed->channel, parsed->payload, source, parsed->sequence});
      return 1;
    }
    ++recv_counters.fragments_received;
    auto complete = reassembler.add(*parsed, source, detail::Reassembler::Clock::now());
    if (!complete) return 0;
    ++recv_counters.messages_received;
    on_message(Message{complete->channel, std::span<const std::byte>(complete->data.get(), complete->size),
                       complete->source, complete->sequence});
    return 1;
  }

  std::size_t drain(const Handler& on_message) {
    std::size_t delivered = 0;
    std::size_t read = 0;
    for (;;) {
      while (batch_next < batch_size) {
        const std::size_t i = batch_next++;  // advance first: a throwing callback does not replay it
        delivered += handle(i, on_message);
      }
      if (read >= kMaxDatagramsPerDrain) break;
      arm_batch();
      batch_size = batch_next = 0;
      const int r = ::recvmmsg(recv_fd.get(), msgs, kRecvBatch, MSG_DONTWAIT, nullptr);
      if (r < 0) {
        if (errno == EINTR) continue;
        if (errno == EAGAIN || errno == EWOULDBLOCK) break;
        throw_errno("udpm receive on " + to_url(cfg), errno);
      }
      if (r == 0) break;
      batch_size = static_cast<std::size_t>(r);
      read += batch_size;
    }
    reassembler.expire(detail::Reassembler::Clock::now());
    return delivered;
  }
};

Group::Group(std::unique_ptr<Impl> impl) noexcept : impl_(std::move(impl)) {}
Group::Group(Group&&) noexcept = default;
Group& Group::operator=(Group&&) noexcept = default;
Group::~Group() = default;

Group Group::open(const GroupConfig& cfg) {
  in_addr group{};
  validate(cfg, group);
  const auto [ifindex, if_addr] = resolve_interface(cfg.interface);
  auto impl = std::make_unique<Impl>(cfg);
  const std::string where = " (" + to_url(cfg) + ")";

  // ---- receive socket ----
  Fd r(::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0));
  if (r.get() < 0) throw_errno("udpm group: socket" + where, errno);
  const int one = 1, zero = 0;
  // liblcm 1.3.1 sets only SO_REUSEADDR on Linux; both having it is what lets them share the
  // port. SO_REUSEPORT too lets programs that set only that one share it as well.
  set_opt(r.get(), SOL_SOCKET, SO_REUSEADDR, one, "udpm group: SO_REUSEADDR");
  set_opt(r.get(), SOL_SOCKET, SO_REUSEPORT, one, "udpm group: SO_REUSEPORT");
  // Only the groups this socket joined, not every group joined on this host with our port.
  set_opt(r.get(), IPPROTO_IP, IP_MULTICAST_ALL, zero, "udpm group: IP_MULTICAST_ALL");
  (void)::setsockopt(r.get(), SOL_SOCKET, SO_RXQ_OVFL, &one, sizeof one);  // best effort
  if (cfg.recv_buffer_bytes > 0) {
    if (::setsockopt(r.get(), SOL_SOCKET, SO_RCVBUFFORCE, &cfg.recv_buffer_bytes, sizeof(int)) != 0)
      set_opt(r.get(), SOL_SOCKET, SO_RCVBUF, cfg.recv_buffer_bytes, "udpm group: SO_RCVBUF");
  }
  socklen_t len = sizeof impl->effective_rcvbuf;
  if (::getsockopt(r.get(), SOL_SOCKET, SO_RCVBUF, &impl->effective_rcvbuf, &len) != 0)
    throw_errno("udpm group: getsockopt SO_RCVBUF", errno);
  if (cfg.recv_buffer_bytes > 0 && impl->effective_rcvbuf / 2 < cfg.recv_buffer_bytes)
    spdlog::warn("lcmx::udpm {}: receive buffer is {} bytes, asked for {} (raise net.core.rmem_max)",
                 to_url(cfg), impl->effective_rcvbuf / 2, cfg.recv_buffer_bytes);

  sockaddr_in bind_addr{};
  bind_addr.sin_family = AF_INET;
  bind_addr.sin_addr.s_addr = htonl(INADDR_ANY);
  bind_addr.sin_port = htons(cfg.port);
  if (::bind(r.get(), reinterpret_cast<const sockaddr*>(&bind_addr), sizeof bind_addr) != 0)
    throw_errno("udpm group: bind 0.0.0.0:" + std::to_string(cfg.port) + where, errno);
  ip_mreqn mreq{};
  mreq.imr_multiaddr = group;
  mreq.imr_ifindex = ifindex;
  if (::setsockopt(r.get(), IPPROTO_IP, IP_ADD_MEMBERSHIP, &mreq, sizeof mreq) != 0)
    throw_errno("udpm group: join " + cfg.address + " on " + cfg.interface + where, errno);

  // ---- send socket ----
  Fd s(::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0));
  if (s.get() < 0) throw_errno("udpm group: socket" + where, errno);
  set_opt(s.get(), IPPROTO_IP, IP_MULTICAST_ALL, zero, "udpm group: IP_MULTICAST_ALL");
  ip_mreqn ifreq{};
  ifreq.imr_ifindex = ifindex;
  set_opt(s.get(), IPPROTO_IP, IP_MULTICAST_IF, ifreq, "udpm group: IP_MULTICAST_IF");
  const unsigned char ttl = static_cast<unsigned char>(cfg.ttl);
  const unsigned char loop = cfg.multicast_loop ? 1 : 0;
  set_opt(s.get(), IPPROTO_IP, IP_MULTICAST_TTL, ttl, "udpm group: IP_MULTICAST_TTL");
  set_opt(s.get(), IPPROTO_IP, IP_MULTICAST_LOOP, loop, "udpm group: IP_MULTICAST_LOOP");
  sockaddr_in src{};
  src.sin_family = AF_INET;
  src.sin_addr = if_addr;
  src.sin_port = 0;
  if (::bind(s.get(), reinterpret_cast<const sockaddr*>(&src), sizeof src) != 0)
    throw_errno("udpm group: bind send socket to " + cfg.interface + where, errno);
  socklen_t slen = sizeof src;
  if (::getsockname(s.get(), reinterpret_cast<sockaddr*>(&src), &slen) != 0)
    throw_errno("udpm group: getsockname", errno);
  impl->local = Source{src.sin_addr.s_addr, src.sin_port};
  // Nothing has been sent from `s` yet, so no own datagram can be queued before the filter.
  if (!cfg.receive_own) drop_own_datagrams(r.get(), impl->local);

  impl->dest.sin_family = AF_INET;
  impl->dest.sin_addr = group;
  impl->dest.sin_port = htons(cfg.port);
  impl->recv_fd = std::move(r);
  impl->send_fd = std::move(s);
  spdlog::debug("lcmx::udpm opened {} (ifindex {}, from {}, SO_RCVBUF {})", to_url(cfg), ifindex,
                to_string(impl->local), impl->effective_rcvbuf);
  return Group(std::move(impl));
}

void Group::publish(std::string_view channel, std::span<const std::byte> payload) {
  impl_->publish(channel, payload);
}

int Group::fd() const noexcept { return impl_ ? impl_->recv_fd.get() : -1; }

std::size_t Group::drain(const Handler& on_message) { return impl_->drain(on_message); }

std::size_t Group::poll(std::chrono::milliseconds timeout, const Handler& on_message) {
  using Clock = std::chrono::steady_clock;
  const auto deadline = Clock::now() + std::max(timeout, std::chrono::milliseconds(0));
  if (impl_->batch_next < impl_->batch_size) return drain(on_message);  // leftovers first
  for (;;) {
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(deadline - Clock::now());
    pollfd p{impl_->recv_fd.get(), POLLIN, 0};
    const int r = ::poll(&p, 1, static_cast<int>(std::max<std::int64_t>(left.count(), 0)));
    if (r < 0) {
      if (errno == EINTR && Clock::now() < deadline) continue;
      if (errno != EINTR) throw_errno("udpm poll", errno);
    }
    break;
  }
  return drain(on_message);  // also expires stale partial messages on timeout
}

Source Group::local_source() const { return impl_->local; }

const Counters& Group::counters() const noexcept {
  Counters& c = impl_->snapshot;
  c = impl_->recv_counters;
  c.packets_sent = impl_->packets_sent.load(std::memory_order_relaxed);
  c.messages_sent = impl_->messages_sent.load(std::memory_order_relaxed);
  c.bytes_sent = impl_->bytes_sent.load(std::memory_order_relaxed);
  const auto& r = impl_->reassembler.stats();
  c.incomplete_dropped = r.incomplete_dropped;
  c.malformed_dropped += r.malformed_dropped;
  c.duplicate_fragments = r.duplicate_fragments;
  c.oversize_dropped = r.oversize_dropped;
  return c;
}

const GroupConfig& Group::config() const noexcept { return impl_->cfg; }

int Group::effective_recv_buffer() const noexcept { return impl_->effective_rcvbuf; }

}  // namespace lcmx::udpm
