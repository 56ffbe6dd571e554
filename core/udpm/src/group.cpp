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
#include <ctime>
#include <mutex>
#include <optional>
#include <string_view>
#include <unordered_map>
#include <vector>

#include "lcmx/udpm/error.hpp"
#include "lcmx/udpm/wire.hpp"
#include "envelope.hpp"
#include "reassembler.hpp"
#include "socket_filter.hpp"

#ifndef SO_RXQ_OVFL
#define SO_RXQ_OVFL 40
#endif

namespace lcmx::udpm {
namespace {

constexpr std::size_t kRecvBatch = 16;               // datagrams per recvmmsg
constexpr std::size_t kRecvSlot = 65536;             // > kMaxDatagramSize
constexpr std::size_t kMaxDatagramsPerDrain = 4096;  // bounds one drain() call
constexpr std::size_t kSendBatch = 32;               // fragments per sendmmsg
// Keyed groups: an LCM datagram inside an envelope is at most this large, so the envelope
// still fits one IPv4 UDP datagram; a message is cut with these limits instead of liblcm's.
constexpr std::size_t kSealedInnerMax = kMaxDatagramSize - kEnvelopeOverhead;
constexpr std::size_t kSealedShortMax = kSealedInnerMax - kShortHeaderSize;   // channel + NUL + payload
constexpr std::size_t kSealedFragmentMax = kSealedInnerMax - kLongHeaderSize;  // payload bytes per LC03
constexpr std::size_t kSealSlot = kMaxDatagramSize + 1;

void check_keys(const std::shared_ptr<const GroupKeys>& keys) {
  if (keys && (keys->keys.empty() || keys->keys.size() > 2))
    throw Error(Error::Code::invalid_config, "udpm group: a group key set holds 1 or 2 keys, not " +
                                                 std::to_string(keys->keys.size()));
}

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
  if (cfg.interface.size() >= IFNAMSIZ) bad("bad interface name '" + cfg.interface + "'");
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

// Where the kernel routes the group (where liblcm's INADDR_ANY join and its sends go).
struct Route {
  int index = 0;
  in_addr address{};  // the source address the kernel picks for it
  std::string name;
  bool operator==(const Route& o) const { return index == o.index && address.s_addr == o.address.s_addr; }
};

// Asks the kernel (connect() of a UDP socket does the route lookup and picks the source
// address), then finds the interface holding that address. nullopt: no route (liblcm then fails
// with "LCM requires a valid multicast route"). Throws Error(system) on other faults.
std::optional<Route> route_of(in_addr group, std::uint16_t port) {
  Fd s(::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0));
  if (s.get() < 0) throw_errno("udpm group: socket", errno);
  sockaddr_in to{};
  to.sin_family = AF_INET;
  to.sin_addr = group;
  to.sin_port = htons(port);
  if (::connect(s.get(), reinterpret_cast<const sockaddr*>(&to), sizeof to) != 0) {
    if (errno == ENETUNREACH || errno == EHOSTUNREACH || errno == ENODEV || errno == EADDRNOTAVAIL ||
        errno == EINVAL)
      return std::nullopt;
    throw_errno("udpm group: route lookup (connect)", errno);
  }
  sockaddr_in from{};
  socklen_t len = sizeof from;
  if (::getsockname(s.get(), reinterpret_cast<sockaddr*>(&from), &len) != 0)
    throw_errno("udpm group: getsockname", errno);
  ifaddrs* list = nullptr;
  if (::getifaddrs(&list) != 0) throw_errno("udpm group: getifaddrs", errno);
  std::optional<Route> route;
  for (ifaddrs* i = list; i != nullptr && !route; i = i->ifa_next)
    if (i->ifa_addr != nullptr && i->ifa_addr->sa_family == AF_INET &&
        reinterpret_cast<const sockaddr_in*>(i->ifa_addr)->sin_addr.s_addr == from.sin_addr.s_addr) {
      const unsigned index = ::if_nametoindex(i->ifa_name);
      if (index != 0) route = Route{static_cast<int>(index), from.sin_addr, i->ifa_name};
    }
  ::freeifaddrs(list);
  return route;
}

void join(int fd, in_addr group, int ifindex) {
  ip_mreqn mreq{};
  mreq.imr_multiaddr = group;
  mreq.imr_ifindex = ifindex;
  if (::setsockopt(fd, IPPROTO_IP, IP_ADD_MEMBERSHIP, &mreq, sizeof mreq) != 0 && errno != EADDRINUSE)
    throw_errno("udpm group: join", errno);
}

// A send socket on interface `ifindex`, bound to `address`:`port_be` (0: ephemeral).
Fd open_send_socket(const GroupConfig& cfg, int ifindex, in_addr address, std::uint16_t port_be,
                    const std::string& where) {
  const int zero = 0;
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
  src.sin_addr = address;
  src.sin_port = port_be;
  if (::bind(s.get(), reinterpret_cast<const sockaddr*>(&src), sizeof src) != 0) {
    char buf[INET_ADDRSTRLEN] = {};
    ::inet_ntop(AF_INET, &address, buf, sizeof buf);
    throw_errno("udpm group: bind send socket to " + std::string(buf) + ":" + std::to_string(ntohs(port_be)) + where,
                errno);
  }
  return s;
}

std::uint16_t bound_port(int fd) {
  sockaddr_in a{};
  socklen_t len = sizeof a;
  if (::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) != 0) throw_errno("udpm group: getsockname", errno);
  return a.sin_port;
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
  in_addr group{};
  bool host_local = false;  // GroupConfig::interface empty (see Group)
  int primary_index = 0;    // the interface publish() sends on (lo in host-local mode)

  // --- send side (any thread) ---
  std::mutex send_mutex;  // guards sequence, routed_fd, routed_name; keeps one message's fragments together
  std::uint32_t sequence = 0;
  Fd routed_fd;             // host-local mode, group routed to another interface than lo
  std::string routed_name;  // the interface publish_routed() uses
  std::atomic<std::uint64_t> packets_sent{0}, messages_sent{0}, bytes_sent{0};
  // Keyed groups (send_mutex): the envelope's sender id and counter, and the buffer datagrams
  // are sealed in (grown once to the largest batch sent, then reused: no allocation per
  // datagram).
  std::optional<detail::Sealer> sealer;
  std::atomic<std::uint64_t> own_sender{0};  // sealer's sender id (0: none yet), for the receive thread
  std::unique_ptr<std::byte[]> seal_buffer;
  std::size_t seal_slots = 0;

  // --- counts per channel sent (send_mutex), for publish_counted ---
  struct Sent {
    std::uint64_t messages = 0;
    std::chrono::steady_clock::time_point last{};
  };
  struct NameHash {
    using is_transparent = void;
    std::size_t operator()(std::string_view s) const noexcept { return std::hash<std::string_view>{}(s); }
  };
  // Looked up by string_view (no allocation but the first message of a channel); bounded.
  std::unordered_map<std::string, Sent, NameHash, std::equal_to<>> sent_counts;
  std::vector<ChannelCount> count_view;  // publish_counted's span, reused
  std::atomic<std::uint64_t> uncounted_sent{0};

  // A message on `channel` was sent whole (send_mutex held).
  void count_sent(std::string_view channel) {
    auto it = sent_counts.find(channel);
    if (it == sent_counts.end()) {
      if (sent_counts.size() >= kMaxCountedChannels) {
        uncounted_sent.fetch_add(1, std::memory_order_relaxed);
        return;
      }
      it = sent_counts.emplace(std::string(channel), Sent{}).first;
    }
    ++it->second.messages;
    it->second.last = std::chrono::steady_clock::now();
  }

  // --- the receive filter ---
  // filter_mutex guards filter, own_addresses' changes and the kernel program (attach_locked):
  // set_filter and refresh (the receive thread) change them, set_keys (any thread) re-derives
  // the program. The receive thread reads filter and own_addresses without it (it is their
  // only writer); rule is the receive thread's alone.
  mutable std::mutex filter_mutex;
  ReceiveFilter filter;
  detail::FilterRule rule;
  bool program_attached = false;
  std::atomic<bool> kernel_whole{true};

  // Derives the receive socket's kernel program from the filter, the own-datagram drop and the
  // keys, and attaches it (replacing the previous one atomically). Tries the parts of the
  // filter most first (detail::KernelPart) until one fits and the socket takes it.
  // filter_mutex held. Throws Error(system) if the socket refuses even the own-datagram drop.
  void attach_locked(const ReceiveFilter& f, const std::shared_ptr<const GroupKeys>& k) {
    detail::ProgramSpec spec;
    spec.drop_own = !cfg.receive_own;
    spec.own_port_be = local.port_be;
    spec.own_addresses = own_addresses;
    if (k) {
      spec.key_ids.emplace();
      for (const auto& key : k->keys) spec.key_ids->push_back(key.id);
    }
    std::vector<sock_filter> tried;
    for (const auto part : {detail::KernelPart::whole, detail::KernelPart::without_channels,
                            detail::KernelPart::without_sources, detail::KernelPart::own_only}) {
      auto code = detail::socket_program(spec, f, part);
      if (!code) continue;  // does not fit classic BPF
      if (code->empty()) {  // nothing to drop
        if (!program_attached) {
          set_kernel_whole(f, k, part);
          return;
        }
        code->push_back(BPF_STMT(BPF_RET | BPF_K, 0xffffffffu));
      }
      if (code->size() == tried.size() &&
          std::memcmp(code->data(), tried.data(), code->size() * sizeof(sock_filter)) == 0)
        continue;  // the same program as the part before, refused already
      sock_fprog prog{static_cast<unsigned short>(code->size()), code->data()};
      if (::setsockopt(recv_fd.get(), SOL_SOCKET, SO_ATTACH_FILTER, &prog, sizeof prog) == 0) {
        program_attached = true;
        set_kernel_whole(f, k, part);
        if (part != detail::KernelPart::whole)
          spdlog::debug("lcmx::udpm {}: the kernel holds part of the receive filter ({} instructions)", to_url(cfg),
                        code->size());
        return;
      }
      const int err = errno;
      if (part == detail::KernelPart::own_only) throw_errno("udpm group: SO_ATTACH_FILTER", err);
      // ENOMEM: larger than net.core.optmem_max allows; anything else: try a smaller part.
      spdlog::debug("lcmx::udpm {}: SO_ATTACH_FILTER of {} instructions: {}", to_url(cfg), code->size(),
                    std::strerror(err));
      tried = std::move(*code);
    }
  }
  void set_kernel_whole(const ReceiveFilter& f, const std::shared_ptr<const GroupKeys>& k, detail::KernelPart part) {
    kernel_whole.store(takes_everything(f) || (part == detail::KernelPart::whole && !(k && k->encrypt)));
  }

  // --- the group key (any thread) ---
  mutable std::mutex keys_mutex;  // guards keys
  std::shared_ptr<const GroupKeys> keys;
  std::shared_ptr<Refusals> refusals;
  std::shared_ptr<const GroupKeys> current_keys() const {
    std::lock_guard lock(keys_mutex);
    return keys;
  }

  // --- routing (the receive thread) ---
  std::optional<Route> route_seen;           // the route as last resolved
  std::vector<int> joined;                   // interfaces the receive socket joined
  std::vector<std::uint32_t> own_addresses;  // source addresses of our send sockets, ever

  // --- receive side (the receive thread) ---
  detail::Reassembler reassembler;
  detail::Opener opener;                     // keyed groups: the senders' replay windows
  std::shared_ptr<const GroupKeys> rx_keys;  // the keys of the current drain()
  std::unique_ptr<std::byte[]> slots;  // kRecvBatch * kRecvSlot
  mmsghdr msgs[kRecvBatch]{};
  iovec iovs[kRecvBatch]{};
  sockaddr_in names[kRecvBatch]{};
  alignas(cmsghdr) char controls[kRecvBatch][CMSG_SPACE(sizeof(std::uint32_t)) + 16]{};
  std::size_t batch_size = 0;  // datagrams in the current batch
  std::size_t batch_next = 0;  // next one to handle (resumes after a throwing callback)
  Counters recv_counters;
  mutable Counters snapshot;

  // Duplicate filter: per sender, the newest sequence delivered and a bitmap of the 64 before it
  // (bit i: top - i delivered), as in IPsec's anti-replay window. Bounded: cleared when it
  // holds kMaxSenders senders.
  struct Window {
    std::uint32_t top;
    std::uint64_t bits;
  };
  static constexpr std::size_t kMaxSenders = 4096;
  std::unordered_map<std::uint64_t, Window> windows;

  // A jump ahead this large is a sender that restarted on the same port, not a loss.
  static constexpr std::uint32_t kMaxGap = 1u << 16;

  // True the first time (source, sequence) is seen. *lost: sequence numbers skipped since the
  // source's newest message (Message::lost_before).
  bool fresh(const Source& source, std::uint32_t seq, std::uint32_t* lost) {
    *lost = 0;
    if (windows.size() >= kMaxSenders) windows.clear();
    const std::uint64_t key = (std::uint64_t{source.address_be} << 16) | source.port_be;
    auto [it, inserted] = windows.try_emplace(key, Window{seq, 1});
    if (inserted) return true;
    Window& w = it->second;
    const std::uint32_t ahead = seq - w.top;  // modulo 2^32
    if (ahead != 0 && ahead < 0x80000000u) {  // newer
      if (ahead <= kMaxGap) *lost = ahead - 1;
      w.bits = ahead >= 64 ? 1 : (w.bits << ahead) | 1;
      w.top = seq;
      return true;
    }
    const std::uint32_t behind = w.top - seq;
    if (behind >= 64) {  // far behind: a restarted sender (same port); start over
      w = Window{seq, 1};
      return true;
    }
    const std::uint64_t bit = std::uint64_t{1} << behind;
    if ((w.bits & bit) != 0) return false;
    w.bits |= bit;
    return true;
  }

  explicit Impl(const GroupConfig& c)
      : cfg(c),
        reassembler({c.max_reassembly_bytes, c.max_partial_messages,
                     std::chrono::duration_cast<detail::Reassembler::Clock::duration>(c.reassembly_timeout)}),
        slots(std::make_unique_for_overwrite<std::byte[]>(kRecvBatch * kRecvSlot)) {
    keys = c.keys;
    refusals = c.refusals ? c.refusals : std::make_shared<Refusals>();
    check_keys(keys);
    if (keys) {
      sealer.emplace();
      own_sender.store(sealer->sender_id());
    }
  }

  void send_all(int fd, mmsghdr* m, std::size_t n) {
    std::size_t done = 0;
    while (done < n) {
      const int r = ::sendmmsg(fd, m + done, static_cast<unsigned>(n - done), 0);
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

  static void check_channel(std::string_view channel) {
    if (channel.size() > kMaxChannelLength)
      throw Error(Error::Code::channel_too_long, "udpm publish: channel '" + std::string(channel) + "' is " +
                                                     std::to_string(channel.size()) + " bytes (max 63)");
    if (channel.find('\0') != std::string_view::npos)
      throw Error(Error::Code::invalid_channel, "udpm publish: channel name contains a NUL byte");
  }
  static void check_payload(std::string_view channel, std::span<const std::byte> payload) {
    if (payload.size() > kMaxMessageSize)
      throw Error(Error::Code::message_too_large, "udpm publish on '" + std::string(channel) + "': " +
                                                      std::to_string(payload.size()) + " bytes exceed " +
                                                      std::to_string(kMaxMessageSize));
  }

  std::uint32_t publish(std::string_view channel, std::span<const std::byte> payload, bool routed) {
    check_channel(channel);
    check_payload(channel, payload);
    const auto sealing = current_keys();
    std::lock_guard lock(send_mutex);
    return send_locked(sealing.get(), channel, payload, routed);
  }

  std::uint32_t publish_counted(
      std::string_view channel, const std::function<std::vector<std::byte>(std::span<const ChannelCount>)>& build) {
    check_channel(channel);
    const auto sealing = current_keys();
    std::lock_guard lock(send_mutex);
    count_view.clear();
    for (const auto& [name, sent] : sent_counts)
      if (name != channel) count_view.push_back(ChannelCount{name, sent.messages, sent.last});
    const std::vector<std::byte> payload = build(std::span<const ChannelCount>(count_view));
    check_payload(channel, payload);
    return send_locked(sealing.get(), channel, payload, false);
  }

  // Sends one checked message and counts it once all of it was sent (send_mutex held).
  std::uint32_t send_locked(const GroupKeys* sealing, std::string_view channel, std::span<const std::byte> payload,
                            bool routed) {
    static constexpr char kNul = '\0';
    auto* chan = const_cast<char*>(channel.data());
    auto* data = const_cast<std::byte*>(payload.data());
    const std::size_t nframes = datagram_count(channel.size(), payload.size());
    const int fd = routed && routed_fd.get() >= 0 ? routed_fd.get() : send_fd.get();
    const std::uint32_t seq = sequence++;
    if (sealing) {
      publish_sealed(*sealing, fd, seq, channel, payload);
      messages_sent.fetch_add(1, std::memory_order_relaxed);
      count_sent(channel);
      return seq;
    }
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
      send_all(fd, m, 1);
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
        send_all(fd, m, n);
      }
    }
    messages_sent.fetch_add(1, std::memory_order_relaxed);
    count_sent(channel);
    return seq;
  }

  // Keyed publish (send_mutex held): each LCM datagram is written into a slot of seal_buffer
  // behind room for the envelope header, sealed in place, and sent in sendmmsg batches.
  void publish_sealed(const GroupKeys& k, int fd, std::uint32_t seq, std::string_view channel,
                      std::span<const std::byte> payload) {
    if (!sealer) {  // keyed after open (set_keys)
      sealer.emplace();
      own_sender.store(sealer->sender_id());
    }
    const std::size_t n = channel.size() + 1 + payload.size();
    const std::size_t nframes = n <= kSealedShortMax ? 1 : (n + kSealedFragmentMax - 1) / kSealedFragmentMax;
    const std::size_t slots_needed = std::min(nframes, kSendBatch);
    if (seal_slots < slots_needed) {
      seal_buffer = std::make_unique_for_overwrite<std::byte[]>(slots_needed * kSealSlot);
      seal_slots = slots_needed;
    }
    mmsghdr m[kSendBatch]{};
    iovec iov[kSendBatch];
    if (nframes == 1) {
      std::byte* inner = seal_buffer.get() + kEnvelopeHeaderSize;
      store_u32(inner, kMagicShort);
      store_u32(inner + 4, seq);
      std::memcpy(inner + kShortHeaderSize, channel.data(), channel.size());
      inner[kShortHeaderSize + channel.size()] = std::byte{0};
      if (!payload.empty()) std::memcpy(inner + kShortHeaderSize + channel.size() + 1, payload.data(), payload.size());
      iov[0] = {seal_buffer.get(), sealer->seal(k, seal_buffer.get(), kShortHeaderSize + n)};
      m[0].msg_hdr.msg_name = &dest;
      m[0].msg_hdr.msg_namelen = sizeof dest;
      m[0].msg_hdr.msg_iov = &iov[0];
      m[0].msg_hdr.msg_iovlen = 1;
      send_all(fd, m, 1);
      sealer->prepare(k);  // the next datagram's one-time key, now that this one is out
      return;
    }
    const std::size_t first = kSealedFragmentMax - (channel.size() + 1);
    std::size_t offset = 0;
    for (std::size_t base = 0; base < nframes; base += kSendBatch) {
      const std::size_t count = std::min(kSendBatch, nframes - base);
      for (std::size_t i = 0; i < count; ++i) {
        const std::size_t no = base + i;
        std::byte* slot = seal_buffer.get() + i * kSealSlot;
        std::byte* h = slot + kEnvelopeHeaderSize;
        store_u32(h, kMagicLong);
        store_u32(h + 4, seq);
        store_u32(h + 8, static_cast<std::uint32_t>(payload.size()));
        store_u32(h + 12, static_cast<std::uint32_t>(offset));
        store_u16(h + 16, static_cast<std::uint16_t>(no));
        store_u16(h + 18, static_cast<std::uint16_t>(nframes));
        std::byte* p = h + kLongHeaderSize;
        std::size_t len;
        if (no == 0) {
          std::memcpy(p, channel.data(), channel.size());
          p[channel.size()] = std::byte{0};
          p += channel.size() + 1;
          len = std::min(first, payload.size());
        } else {
          len = std::min(kSealedFragmentMax, payload.size() - offset);
        }
        if (len > 0) std::memcpy(p, payload.data() + offset, len);
        const std::size_t inner = static_cast<std::size_t>(p - h) + len;
        iov[i] = {slot, sealer->seal(k, slot, inner)};
        mmsghdr& mm = m[i];
        mm = mmsghdr{};
        mm.msg_hdr.msg_name = &dest;
        mm.msg_hdr.msg_namelen = sizeof dest;
        mm.msg_hdr.msg_iov = &iov[i];
        mm.msg_hdr.msg_iovlen = 1;
        offset += len;
      }
      send_all(fd, m, count);
    }
    sealer->prepare(k);
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
    const Source source{names[i].sin_addr.s_addr, names[i].sin_port};
    std::span<const std::byte> datagram(slots.get() + i * kRecvSlot, mm.msg_len);
    if (rx_keys) {
      // Keyed: the envelope is checked before anything of the datagram is parsed.
      const bool from_self =
          source.port_be == local.port_be &&
          std::find(own_addresses.begin(), own_addresses.end(), source.address_be) != own_addresses.end();
      const auto opened = opener.open(*rx_keys, std::span<std::byte>(slots.get() + i * kRecvSlot, mm.msg_len),
                                      own_sender.load(std::memory_order_relaxed), from_self,
                                      static_cast<std::uint32_t>(std::time(nullptr)),
                                      static_cast<std::uint32_t>(std::max<std::int64_t>(cfg.keyed_max_skew.count(), 0)));
      if (opened.refused) {
        const bool replay = *opened.refused == Refusal::replayed || *opened.refused == Refusal::stale;
        ++(replay ? recv_counters.replays_dropped : recv_counters.unauthenticated_dropped);
        refusals->record(source.address_be, *opened.refused);
        return 0;
      }
      datagram = opened.inner;
    }
    const auto parsed = parse_datagram(datagram);
    if (!parsed) {
      ++recv_counters.malformed_dropped;
      return 0;
    }
    std::uint32_t lost = 0;
    if (!parsed->fragment) {
      if (!rule.takes(parsed->channel, parsed->payload, source)) {
        ++recv_counters.filtered_dropped;
        return 0;
      }
      if (!fresh(source, parsed->sequence, &lost)) {
        ++recv_counters.duplicates_dropped;
        return 0;
      }
      ++recv_counters.messages_received;
      on_message(Message{parsed->channel, parsed->payload, source, parsed->sequence, lost, nullptr});
      return 1;
    }
    ++recv_counters.fragments_received;
    const auto now = detail::Reassembler::Clock::now();
    // A message is judged at its fragment 0 (the one with the channel); the rest of a refused
    // one is dropped as it comes, never counted incomplete (filter.hpp "LC03").
    if (parsed->fragment_no == 0) {
      if (!rule.takes(parsed->channel, parsed->payload, source)) {
        recv_counters.filtered_dropped += 1 + reassembler.refuse(*parsed, source, now);
        return 0;
      }
    } else if (reassembler.refused(*parsed, source, now)) {
      ++recv_counters.filtered_dropped;
      return 0;
    }
    auto complete = reassembler.add(*parsed, source, now);
    if (!complete) return 0;
    // The filter may have changed since its fragment 0.
    if (!rule.takes(complete->channel, std::span<const std::byte>(complete->data.get(), complete->size),
                    complete->source)) {
      ++recv_counters.filtered_dropped;
      return 0;
    }
    if (!fresh(complete->source, complete->sequence, &lost)) {
      ++recv_counters.duplicates_dropped;
      return 0;
    }
    ++recv_counters.messages_received;
    // The reassembly buffer is handed over with the message (no copy after reassembly).
    std::shared_ptr<const std::byte[]> buffer(std::move(complete->data));
    on_message(Message{complete->channel, std::span<const std::byte>(buffer.get(), complete->size),
                       complete->source, complete->sequence, lost, buffer});
    return 1;
  }

  std::size_t drain(const Handler& on_message) {
    rx_keys = current_keys();
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
    if (rx_keys) opener.prepare();  // the senders' next one-time keys, once theirs were handled
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
  const bool host_local = cfg.interface.empty();
  const std::string primary = host_local ? "lo" : cfg.interface;
  const auto [ifindex, if_addr] = resolve_interface(primary);
  auto impl = std::make_unique<Impl>(cfg);
  impl->group = group;
  impl->host_local = host_local;
  impl->primary_index = ifindex;
  const std::string where = " (" + to_url(cfg) + ")";
  std::optional<Route> route;
  if (host_local) {
    route = route_of(group, cfg.port);
    impl->route_seen = route;
  }

  // ---- receive socket ----
  Fd r(::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0));
  if (r.get() < 0) throw_errno("udpm group: socket" + where, errno);
  const int one = 1, zero = 0;
  // liblcm 1.3.1 sets only SO_REUSEADDR on Linux; both having it is what lets them share the
  // port. SO_REUSEPORT too lets programs that set only that one share it as well.
  set_opt(r.get(), SOL_SOCKET, SO_REUSEADDR, one, "udpm group: SO_REUSEADDR");
  set_opt(r.get(), SOL_SOCKET, SO_REUSEPORT, one, "udpm group: SO_REUSEPORT");
  // Only the groups (and interfaces) this socket joined, not every group joined on this host
  // with our port.
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

  // Bound to the group's address, not INADDR_ANY: only datagrams sent to the group reach this
  // socket, never unicast to the port (a LAN machine sending to this host's address:port). The
  // kernel still delivers the group's datagrams to liblcm's INADDR_ANY sockets on the port too.
  sockaddr_in bind_addr{};
  bind_addr.sin_family = AF_INET;
  bind_addr.sin_addr = group;
  bind_addr.sin_port = htons(cfg.port);
  if (::bind(r.get(), reinterpret_cast<const sockaddr*>(&bind_addr), sizeof bind_addr) != 0)
    throw_errno("udpm group: bind " + cfg.address + ":" + std::to_string(cfg.port) + where, errno);
  try {
    join(r.get(), group, ifindex);
  } catch (const Error& e) {
    throw Error(Error::Code::system, "udpm group: join " + cfg.address + " on " + primary + where + ": " +
                                         std::strerror(e.sys_errno()), e.sys_errno());
  }
  impl->joined.push_back(ifindex);
  if (route && route->index != ifindex) {
    try {
      join(r.get(), group, route->index);
      impl->joined.push_back(route->index);
    } catch (const Error& e) {  // lo still works; stock programs on this host are not heard
      spdlog::warn("lcmx::udpm {}: cannot join on {}, where the group routes to: {}", to_url(cfg), route->name,
                   e.what());
    }
  }

  // ---- send sockets: publish() on the interface (lo in host-local mode), and publish_routed()
  // from the same port where the group routes to ----
  const bool routed_elsewhere = route && route->index != ifindex;
  Fd s, rs;
  for (int attempt = 0;; ++attempt) {
    s = open_send_socket(cfg, ifindex, if_addr, 0, where);
    if (!routed_elsewhere) break;
    try {
      rs = open_send_socket(cfg, route->index, route->address, bound_port(s.get()), where);
      break;
    } catch (const Error& e) {
      if (e.sys_errno() == EADDRINUSE && attempt < 16) continue;  // that port is taken there: another one
      spdlog::warn("lcmx::udpm {}: stock LCM programs on this host will not hear publish_routed(): {}",
                   to_url(cfg), e.what());
      break;
    }
  }
  sockaddr_in src{};
  socklen_t slen = sizeof src;
  if (::getsockname(s.get(), reinterpret_cast<sockaddr*>(&src), &slen) != 0)
    throw_errno("udpm group: getsockname", errno);
  impl->local = Source{src.sin_addr.s_addr, src.sin_port};
  impl->own_addresses.push_back(src.sin_addr.s_addr);
  if (rs.get() >= 0) impl->own_addresses.push_back(route->address.s_addr);
  impl->routed_name = rs.get() >= 0 ? route->name : primary;
  impl->dest.sin_family = AF_INET;
  impl->dest.sin_addr = group;
  impl->dest.sin_port = htons(cfg.port);
  impl->recv_fd = std::move(r);
  {
    // Nothing has been sent yet, so no own datagram can be queued before the filter.
    std::lock_guard lock(impl->filter_mutex);
    impl->attach_locked(impl->filter, impl->current_keys());
  }
  impl->send_fd = std::move(s);
  impl->routed_fd = std::move(rs);
  spdlog::debug("lcmx::udpm opened {} (ifindex {}, from {}, SO_RCVBUF {}{}{})", to_url(cfg), ifindex,
                to_string(impl->local), impl->effective_rcvbuf, host_local ? ", routed to " : "",
                host_local ? (route ? route->name : std::string("nowhere")) : "");
  return Group(std::move(impl));
}

bool Group::refresh() {
  Impl& g = *impl_;
  if (!g.host_local) return false;
  try {
    const auto route = route_of(g.group, g.cfg.port);
    if (route == g.route_seen) return false;
    g.route_seen = route;
    const std::string url = to_url(g.cfg);
    if (route && std::find(g.joined.begin(), g.joined.end(), route->index) == g.joined.end()) {
      try {
        join(g.recv_fd.get(), g.group, route->index);
        g.joined.push_back(route->index);
      } catch (const Error& e) {
        spdlog::warn("lcmx::udpm {}: cannot join on {}, where the group now routes to: {}", url, route->name, e.what());
      }
    }
    Fd rs;
    if (route && route->index != g.primary_index) {
      try {
        rs = open_send_socket(g.cfg, route->index, route->address, g.local.port_be, " (" + url + ")");
      } catch (const Error& e) {
        spdlog::warn("lcmx::udpm {}: stock LCM programs on this host will not hear publish_routed(): {}", url,
                     e.what());
      }
    }
    std::string name = rs.get() >= 0 ? route->name : "lo";
    if (rs.get() >= 0 &&
        std::find(g.own_addresses.begin(), g.own_addresses.end(), route->address.s_addr) == g.own_addresses.end()) {
      std::lock_guard flock(g.filter_mutex);
      g.own_addresses.push_back(route->address.s_addr);
      if (!g.cfg.receive_own) g.attach_locked(g.filter, g.current_keys());
    }
    std::string joined;
    for (int i : g.joined) {
      char n[IF_NAMESIZE] = {};
      if (!joined.empty()) joined += ",";
      joined += ::if_indextoname(static_cast<unsigned>(i), n) != nullptr ? std::string(n) : std::to_string(i);
    }
    spdlog::info("lcmx::udpm {}: the group now routes to {}: listening on {}, sending to stock LCM programs on {}",
                 url, route ? route->name : std::string("nowhere"), joined, name);
    std::lock_guard lock(g.send_mutex);
    g.routed_fd = std::move(rs);
    g.routed_name = std::move(name);
    return true;
  } catch (const std::exception& e) {
    spdlog::warn("lcmx::udpm {}: route lookup failed: {}", to_url(g.cfg), e.what());
    return false;
  }
}

std::string Group::routed_interface() const {
  std::lock_guard lock(impl_->send_mutex);
  return impl_->routed_name;
}

bool Group::is_own(const Source& source) const {
  if (source.port_be != impl_->local.port_be) return false;
  const auto& a = impl_->own_addresses;
  return std::find(a.begin(), a.end(), source.address_be) != a.end();
}

std::uint32_t Group::publish(std::string_view channel, std::span<const std::byte> payload) {
  return impl_->publish(channel, payload, false);
}

std::uint32_t Group::publish_routed(std::string_view channel, std::span<const std::byte> payload) {
  return impl_->publish(channel, payload, true);
}

std::uint32_t Group::next_sequence() const {
  std::lock_guard lock(impl_->send_mutex);
  return impl_->sequence;
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
  c.uncounted_sent = impl_->uncounted_sent.load(std::memory_order_relaxed);
  const auto& r = impl_->reassembler.stats();
  c.incomplete_dropped = r.incomplete_dropped;
  c.malformed_dropped += r.malformed_dropped;
  c.duplicate_fragments = r.duplicate_fragments;
  c.oversize_dropped = r.oversize_dropped;
  return c;
}

const GroupConfig& Group::config() const noexcept { return impl_->cfg; }

std::shared_ptr<const GroupKeys> Group::keys() const { return impl_->current_keys(); }

void Group::set_keys(std::shared_ptr<const GroupKeys> keys) {
  check_keys(keys);
  if (keys) detail::sodium_ready();
  {
    std::lock_guard lock(impl_->keys_mutex);
    impl_->keys = std::move(keys);
  }
  // The program names the keys and where the LCM datagram starts: derived again from the keys
  // now in force (the last set_keys' whichever thread attaches last).
  std::lock_guard lock(impl_->filter_mutex);
  if (takes_everything(impl_->filter)) return;  // the program does not depend on the keys
  try {
    impl_->attach_locked(impl_->filter, impl_->current_keys());
  } catch (const Error& e) {
    spdlog::warn("lcmx::udpm {}: the receive filter's program stays as it was: {}", to_url(impl_->cfg), e.what());
  }
}

bool Group::set_filter(const ReceiveFilter& f) {
  detail::check_filter(f);
  detail::FilterRule rule(f);
  std::lock_guard lock(impl_->filter_mutex);
  impl_->attach_locked(f, impl_->current_keys());  // throws before anything changed
  impl_->filter = f;
  impl_->rule = std::move(rule);
  return impl_->kernel_whole.load();
}

const ReceiveFilter& Group::filter() const noexcept { return impl_->filter; }

bool Group::kernel_filtered() const noexcept { return impl_->kernel_whole.load(); }

std::vector<std::pair<std::string, std::uint64_t>> Group::channel_counts() const {
  std::lock_guard lock(impl_->send_mutex);
  std::vector<std::pair<std::string, std::uint64_t>> out;
  out.reserve(impl_->sent_counts.size());
  for (const auto& [name, sent] : impl_->sent_counts) out.emplace_back(name, sent.messages);
  return out;
}

std::uint32_t Group::publish_counted(
    std::string_view channel, const std::function<std::vector<std::byte>(std::span<const ChannelCount>)>& build) {
  return impl_->publish_counted(channel, build);
}

Refusals& Group::refusals() const noexcept { return *impl_->refusals; }

int Group::effective_recv_buffer() const noexcept { return impl_->effective_rcvbuf; }

}  // namespace lcmx::udpm
