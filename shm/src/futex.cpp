// Futex helpers. Words in shared memory (mapped by several processes) are never waited on or
// woken with FUTEX_PRIVATE_FLAG: private futexes are keyed by (mm, address). Words a caller
// marks process_private (e.g. a node's doorbell) use it: cheaper keys on wait and wake.
#include "lcmx/shm/futex.hpp"

#include <linux/futex.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <cstring>
#include <ctime>
#include <vector>

#ifndef SYS_futex_waitv
#define SYS_futex_waitv 449
#endif
#ifndef FUTEX_32
#define FUTEX_32 2
struct futex_waitv {
  std::uint64_t val;
  std::uint64_t uaddr;
  std::uint32_t flags;
  std::uint32_t __reserved;
};
#endif
#ifndef FUTEX_WAITV_MAX
#define FUTEX_WAITV_MAX 128
#endif

namespace lcmx::shm {
namespace {

std::uint32_t* addr(const std::atomic<std::uint32_t>* w) {
  static_assert(sizeof(std::atomic<std::uint32_t>) == sizeof(std::uint32_t));
  return reinterpret_cast<std::uint32_t*>(const_cast<std::atomic<std::uint32_t>*>(w));
}

Error sys_error(const char* what, int err) {
  return Error(Errc::system, std::string(what) + ": " + std::strerror(err));
}

timespec to_timespec(std::chrono::nanoseconds ns) {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(ns.count() / 1'000'000'000);
  ts.tv_nsec = static_cast<long>(ns.count() % 1'000'000'000);
  return ts;
}

std::chrono::nanoseconds mono_now() {
  timespec ts{};
  ::clock_gettime(CLOCK_MONOTONIC, &ts);
  return std::chrono::seconds(ts.tv_sec) + std::chrono::nanoseconds(ts.tv_nsec);
}

// FUTEX_WAIT (shared) with a relative timeout (negative: forever).
WaitResult wait_one(const WaitToken& t, std::chrono::nanoseconds timeout) {
  timespec ts = to_timespec(timeout.count() < 0 ? std::chrono::nanoseconds(0) : timeout);
  long rc = ::syscall(SYS_futex, addr(t.word), t.process_private ? FUTEX_WAIT_PRIVATE : FUTEX_WAIT,
                      t.expected,
                      timeout.count() < 0 ? nullptr : &ts, nullptr, 0);
  if (rc == 0) return WaitResult::woken;
  switch (errno) {
    case EAGAIN: return WaitResult::woken;   // value already differs
    case EINTR: return WaitResult::woken;    // spurious, allowed by the contract
    case ETIMEDOUT: return WaitResult::timeout;
    default: throw sys_error("futex(FUTEX_WAIT)", errno);
  }
}

// Several tokens without futex_waitv: poll the values, sleep on the first word <= 1 ms.
WaitResult wait_fallback(std::span<const WaitToken> tokens, std::chrono::nanoseconds timeout) {
  const auto deadline = mono_now() + timeout;
  for (;;) {
    for (const auto& t : tokens) {
      if (t.word->load(std::memory_order_seq_cst) != t.expected) return WaitResult::woken;
    }
    auto step = std::chrono::nanoseconds(std::chrono::milliseconds(1));
    if (timeout.count() >= 0) {
      auto left = deadline - mono_now();
      if (left.count() <= 0) return WaitResult::timeout;
      step = std::min(step, left);
    }
    if (wait_one(tokens[0], step) == WaitResult::woken &&
        tokens[0].word->load(std::memory_order_seq_cst) != tokens[0].expected) {
      return WaitResult::woken;
    }
  }
}

std::atomic<int> g_waitv_state{0};  // 0 unknown, 1 supported, -1 not supported

// futex_waitv on up to FUTEX_WAITV_MAX tokens, relative timeout (negative: forever).
WaitResult wait_v(std::span<const WaitToken> tokens, std::chrono::nanoseconds timeout) {
  futex_waitv w[FUTEX_WAITV_MAX];
  std::memset(w, 0, tokens.size() * sizeof(w[0]));
  for (std::size_t i = 0; i < tokens.size(); ++i) {
    w[i].val = tokens[i].expected;
    w[i].uaddr = reinterpret_cast<std::uintptr_t>(addr(tokens[i].word));
    w[i].flags = FUTEX_32 | (tokens[i].process_private ? FUTEX_PRIVATE_FLAG : 0);
  }
  timespec abs{};
  if (timeout.count() >= 0) abs = to_timespec(mono_now() + timeout);  // absolute, MONOTONIC
  long rc = ::syscall(SYS_futex_waitv, w, static_cast<unsigned>(tokens.size()), 0u,
                      timeout.count() < 0 ? nullptr : &abs, CLOCK_MONOTONIC);
  if (rc >= 0) return WaitResult::woken;
  switch (errno) {
    case EAGAIN: return WaitResult::woken;
    case EINTR: return WaitResult::woken;
    case ETIMEDOUT: return WaitResult::timeout;
    case ENOSYS:
      g_waitv_state.store(-1, std::memory_order_relaxed);
      return wait_fallback(tokens, timeout);
    default: throw sys_error("futex_waitv", errno);
  }
}

// More tokens than one futex_waitv takes. The kernel sleeps on the first FUTEX_WAITV_MAX
// (the caller's first tokens: a node's doorbell and its first readers) for at most
// kChunkStep at a time; between sleeps every word is compared with its expected value. No
// wake-up is lost: a wake on a token outside the sleeping set always comes with a changed
// word (futex protocol: the waker changes the word before waking), which the next
// comparison sees, kChunkStep later at the latest.
constexpr std::chrono::nanoseconds kChunkStep = std::chrono::milliseconds(1);

WaitResult wait_chunked(std::span<const WaitToken> tokens, std::chrono::nanoseconds timeout) {
  const auto deadline = mono_now() + timeout;
  const auto head = tokens.first(FUTEX_WAITV_MAX);
  for (;;) {
    for (const auto& t : tokens)
      if (t.word->load(std::memory_order_seq_cst) != t.expected) return WaitResult::woken;
    auto step = kChunkStep;
    if (timeout.count() >= 0) {
      const auto left = deadline - mono_now();
      if (left.count() <= 0) return WaitResult::timeout;
      step = std::min(step, left);
    }
    if (wait_v(head, step) == WaitResult::woken) {
      for (const auto& t : head)
        if (t.word->load(std::memory_order_seq_cst) != t.expected) return WaitResult::woken;
    }
  }
}

}  // namespace

int futex_wake_all(const std::atomic<std::uint32_t>* word) noexcept {
  long rc = ::syscall(SYS_futex, addr(word), FUTEX_WAKE, INT_MAX, nullptr, nullptr, 0);
  return rc < 0 ? 0 : static_cast<int>(rc);
}

int futex_wake_all_private(const std::atomic<std::uint32_t>* word) noexcept {
  long rc = ::syscall(SYS_futex, addr(word), FUTEX_WAKE_PRIVATE, INT_MAX, nullptr, nullptr, 0);
  return rc < 0 ? 0 : static_cast<int>(rc);
}

bool futex_waitv_supported() noexcept {
  int s = g_waitv_state.load(std::memory_order_relaxed);
  if (s == 0) {
    // nr_futexes == 0 is EINVAL when the syscall exists, ENOSYS otherwise.
    long rc = ::syscall(SYS_futex_waitv, nullptr, 0u, 0u, nullptr, CLOCK_MONOTONIC);
    s = (rc < 0 && errno == ENOSYS) ? -1 : 1;
    g_waitv_state.store(s, std::memory_order_relaxed);
  }
  return s > 0;
}

WaitResult wait_any(std::span<const WaitToken> tokens, std::chrono::nanoseconds timeout) {
  if (tokens.empty()) throw Error(Errc::invalid_argument, "wait_any: no token");
  for (const auto& t : tokens) {
    if (t.word == nullptr) throw Error(Errc::invalid_argument, "wait_any: null futex word");
  }
  if (tokens.size() == 1) return wait_one(tokens[0], timeout);
  if (!futex_waitv_supported()) return wait_fallback(tokens, timeout);
  if (tokens.size() > FUTEX_WAITV_MAX) return wait_chunked(tokens, timeout);
  return wait_v(tokens, timeout);
}

}  // namespace lcmx::shm
