// `floor`: the smallest shared-memory ping-pong this machine can do. One POSIX shm segment
// holds a header (futex words, send timestamp) and one buffer; the publisher memcpys the
// payload in and FUTEX_WAKEs, the subscriber FUTEX_WAITs, memcpys it out into its own
// preallocated buffer, computes now - send_ns and acks through a second futex word.
#include <fcntl.h>
#include <linux/futex.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "latency/roles.hpp"

namespace lcmxbench {
namespace {

constexpr std::size_t kCacheLine = 64;
constexpr std::uint32_t kFloorVersion = 1;

// Lives in shared memory. Publisher writes seq/send_ns/size and the buffer, then bumps `msg`
// (release); the subscriber reads them after seeing `msg` change (acquire). The subscriber
// writes ack_seq, then bumps `ack` (release); the publisher reads ack_seq after (acquire).
struct FloorHeader {
  std::uint32_t version;
  std::uint32_t reserved0;
  std::uint64_t capacity;  // buffer bytes after the header
  std::uint8_t reserved1[kCacheLine - 16];
  // publisher -> subscriber line
  std::atomic<std::uint32_t> msg;   // futex word: messages published
  std::atomic<std::uint32_t> stop;  // 1: publisher is done
  std::int64_t seq;
  std::int64_t send_ns;
  std::uint64_t size;
  std::uint8_t reserved2[kCacheLine - 32];
  // subscriber -> publisher line
  std::atomic<std::uint32_t> ack;  // futex word: messages acknowledged
  std::uint32_t reserved3;
  std::int64_t ack_seq;
  std::uint8_t reserved4[kCacheLine - 16];
};
static_assert(std::atomic<std::uint32_t>::is_always_lock_free);
static_assert(sizeof(FloorHeader) == 3 * kCacheLine);
static_assert(offsetof(FloorHeader, msg) == kCacheLine);
static_assert(offsetof(FloorHeader, ack) == 2 * kCacheLine);

long futex(std::atomic<std::uint32_t>* word, int op, std::uint32_t val, const timespec* ts) {
  // Shared (not FUTEX_PRIVATE) futex: the word is in a MAP_SHARED mapping of two processes.
  return ::syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(word), op, val, ts, nullptr, 0);
}

// Waits while *word == seen, up to timeout_ns. Returns the new value or `seen` on timeout.
std::uint32_t wait_change(std::atomic<std::uint32_t>* word, std::uint32_t seen, std::int64_t timeout_ns) {
  const std::int64_t deadline = now_ns() + timeout_ns;
  for (;;) {
    const std::uint32_t v = word->load(std::memory_order_acquire);
    if (v != seen) return v;
    const std::int64_t left = deadline - now_ns();
    if (left <= 0) return seen;
    timespec ts{static_cast<time_t>(left / 1'000'000'000), static_cast<long>(left % 1'000'000'000)};
    futex(word, FUTEX_WAIT, seen, &ts);  // EAGAIN (changed), EINTR, ETIMEDOUT: re-check
  }
}

std::string shm_name(const RoleConfig& cfg) { return "/" + cfg.name + "_floor"; }

struct Mapping {
  void* addr = MAP_FAILED;
  std::size_t len = 0;
  ~Mapping() {
    if (addr != MAP_FAILED) ::munmap(addr, len);
  }
  FloorHeader* header() const { return static_cast<FloorHeader*>(addr); }
  std::byte* buffer() const { return static_cast<std::byte*>(addr) + sizeof(FloorHeader); }
};

}  // namespace

int run_floor_sub(const RoleConfig& cfg) {
  const std::string name = shm_name(cfg);
  const std::size_t cap = max_size(cfg.plan);
  const int fd = ::shm_open(name.c_str(), O_CREAT | O_EXCL | O_RDWR, 0600);
  if (fd < 0) {
    report_error("floor: shm_open " + name + ": " + std::strerror(errno));
    return 1;
  }
  struct Unlink {
    std::string n;
    ~Unlink() { ::shm_unlink(n.c_str()); }
  } unlink_guard{name};
  Mapping m;
  m.len = sizeof(FloorHeader) + cap;
  if (::ftruncate(fd, static_cast<off_t>(m.len)) != 0) {
    report_error(std::string("floor: ftruncate: ") + std::strerror(errno));
    ::close(fd);
    return 1;
  }
  m.addr = ::mmap(nullptr, m.len, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  ::close(fd);
  if (m.addr == MAP_FAILED) {
    report_error(std::string("floor: mmap: ") + std::strerror(errno));
    return 1;
  }
  FloorHeader* h = new (m.addr) FloorHeader{};
  h->version = kFloorVersion;
  h->capacity = cap;
  std::memset(m.buffer(), 0, cap);  // fault the pages in once, outside the measurement

  std::vector<std::byte> out(cap);  // the subscriber's own preallocated buffer
  std::memset(out.data(), 0, cap);
  Recorder rec(cfg.plan);
  report_line("ready");

  std::uint32_t seen = 0;
  const std::int64_t give_up = now_ns() + 600'000'000'000;  // bounded: 10 min at most
  while (now_ns() < give_up) {
    const std::uint32_t v = wait_change(&h->msg, seen, 100'000'000);
    if (v == seen) continue;
    seen = v;
    if (h->stop.load(std::memory_order_acquire) != 0) break;
    const std::size_t size = h->size;
    const std::int64_t seq = h->seq;
    const std::int64_t send_ns = h->send_ns;
    std::memcpy(out.data(), m.buffer(), size);
    const std::int64_t lat = now_ns() - send_ns;
    rec.record(size, seq, lat);
    h->ack_seq = seq;
    h->ack.fetch_add(1, std::memory_order_release);
    futex(&h->ack, FUTEX_WAKE, 1, nullptr);
  }
  rec.report();
  report_line("done");
  return 0;
}

int run_floor_pub(const RoleConfig& cfg) {
  const std::string name = shm_name(cfg);
  const int fd = ::shm_open(name.c_str(), O_RDWR, 0);
  if (fd < 0) {
    report_error("floor: shm_open " + name + ": " + std::strerror(errno));
    return 1;
  }
  Mapping m;
  m.len = sizeof(FloorHeader) + max_size(cfg.plan);
  m.addr = ::mmap(nullptr, m.len, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  ::close(fd);
  if (m.addr == MAP_FAILED) {
    report_error(std::string("floor: mmap: ") + std::strerror(errno));
    return 1;
  }
  FloorHeader* h = m.header();
  if (h->version != kFloorVersion || h->capacity < max_size(cfg.plan)) {
    report_error("floor: segment " + name + " has a bad header");
    return 1;
  }
  std::vector<std::byte> payload;
  std::uint32_t acked = h->ack.load(std::memory_order_acquire);

  Driver d;
  d.prepare = [&](std::size_t size) {
    payload.assign(size, std::byte{0});
    for (std::size_t i = 0; i < size; ++i) payload[i] = static_cast<std::byte>(i * 31u);
  };
  d.send = [&](std::int64_t seq, std::size_t size) {
    const std::int64_t t = now_ns();
    h->seq = seq;
    h->send_ns = t;
    h->size = size;
    std::memcpy(m.buffer(), payload.data(), size);
    h->msg.fetch_add(1, std::memory_order_release);
    futex(&h->msg, FUTEX_WAKE, 1, nullptr);
  };
  d.wait_ack = [&](std::int64_t seq, int timeout_ms) {
    const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(timeout_ms) * 1'000'000;
    for (;;) {
      const std::uint32_t v = wait_change(&h->ack, acked, deadline - now_ns());
      if (v == acked) return false;
      acked = v;
      if (h->ack_seq == seq) return true;
    }
  };
  const bool ok = run_driver(cfg, d);
  h->stop.store(1, std::memory_order_release);
  h->msg.fetch_add(1, std::memory_order_release);
  futex(&h->msg, FUTEX_WAKE, 1, nullptr);
  report_line("done");
  return ok ? 0 : 1;
}

}  // namespace lcmxbench
