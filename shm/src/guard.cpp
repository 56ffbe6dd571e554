// SIGBUS guard for segment mappings.
//
// Another process with write access can ftruncate a segment file while we have it mapped;
// touching a page past the new end then raises SIGBUS, which would kill the process (seals
// cannot prevent it: F_ADD_SEALS is not available on shm_open files). lcmx installs one
// process-wide SIGBUS handler (SA_SIGINFO, on the first mapping) that looks the faulting
// address up in a fixed table of this process's segment mappings. If it belongs to one, the
// handler maps anonymous zero pages over the rest of that mapping (MAP_FIXED) and marks the
// mapping "faulted"; the faulting instruction is restarted and reads zeros instead of
// crashing (the technique Wayland's wl_shm uses for client buffers). Readers and Writers
// check the mark and treat the generation as lost (counted), see reader.cpp / writer.cpp.
// A SIGBUS for any other address goes to the previous handler (or the default action).
//
// Async-signal safety: the table is a fixed array of atomics; the handler only loads them
// and calls mmap (a raw syscall; also what Wayland does). Limits: kSlots mappings guarded at
// once (more are mapped unguarded, with a warning); a program that installs its own SIGBUS
// handler after lcmx replaces this one (documented in shm/README.md).
#include <signal.h>
#include <sys/mman.h>
#include <unistd.h>

#include <spdlog/spdlog.h>

#include <atomic>
#include <cstdint>
#include <mutex>

#include "impl.hpp"

namespace lcmx::shm::detail {
namespace {

constexpr int kSlots = 4096;

struct GuardSlot {
  std::atomic<std::uintptr_t> base{0};
  std::atomic<std::size_t> len{0};
  std::atomic<std::uint32_t> faulted{0};
};

GuardSlot g_slots[kSlots];
std::mutex g_mu;  // registration only (never taken in the handler)
struct sigaction g_previous {};
bool g_installed = false;
std::uintptr_t g_page = 4096;  // set before the handler is installed (sysconf is not
                               // async-signal-safe)

void on_sigbus(int sig, siginfo_t* info, void* ctx) {
  const auto addr = reinterpret_cast<std::uintptr_t>(info->si_addr);
  for (auto& s : g_slots) {
    const std::uintptr_t base = s.base.load(std::memory_order_acquire);
    const std::size_t len = s.len.load(std::memory_order_acquire);
    if (base == 0 || addr < base || addr >= base + len) continue;
    const std::uintptr_t from = addr & ~(g_page - 1);
    void* r = ::mmap(reinterpret_cast<void*>(from), base + len - from, PROT_READ | PROT_WRITE,
                     MAP_FIXED | MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (r == MAP_FAILED) break;  // cannot repair: fall through to the previous action
    s.faulted.store(1, std::memory_order_release);
    return;
  }
  // Not ours: behave as if we were not installed.
  if ((g_previous.sa_flags & SA_SIGINFO) != 0 && g_previous.sa_sigaction != nullptr) {
    g_previous.sa_sigaction(sig, info, ctx);
    return;
  }
  if (g_previous.sa_handler != SIG_DFL && g_previous.sa_handler != SIG_IGN &&
      g_previous.sa_handler != nullptr) {
    g_previous.sa_handler(sig);
    return;
  }
  // Default action: restore it; returning re-executes the access, which faults again.
  struct sigaction dfl {};
  dfl.sa_handler = SIG_DFL;
  ::sigemptyset(&dfl.sa_mask);
  ::sigaction(SIGBUS, &dfl, nullptr);
}

}  // namespace

int guard_register(void* base, std::size_t len) noexcept {
  std::lock_guard lock(g_mu);
  if (!g_installed) {
    if (const long p = ::sysconf(_SC_PAGESIZE); p > 0) g_page = static_cast<std::uintptr_t>(p);
    struct sigaction sa {};
    sa.sa_sigaction = on_sigbus;
    sa.sa_flags = SA_SIGINFO | SA_NODEFER | SA_ONSTACK;
    ::sigemptyset(&sa.sa_mask);
    if (::sigaction(SIGBUS, &sa, &g_previous) == 0) g_installed = true;
  }
  for (int i = 0; i < kSlots; ++i) {
    auto& s = g_slots[i];
    if (s.base.load(std::memory_order_relaxed) != 0) continue;
    s.faulted.store(0, std::memory_order_relaxed);
    s.len.store(len, std::memory_order_release);
    s.base.store(reinterpret_cast<std::uintptr_t>(base), std::memory_order_release);
    return i;
  }
  spdlog::warn("lcmx shm: more than {} mappings; this one is not guarded against truncation",
               kSlots);
  return -1;
}

void guard_unregister(int slot) noexcept {
  if (slot < 0 || slot >= kSlots) return;
  std::lock_guard lock(g_mu);
  g_slots[slot].base.store(0, std::memory_order_release);
  g_slots[slot].len.store(0, std::memory_order_release);
}

bool guard_faulted(int slot) noexcept {
  if (slot < 0 || slot >= kSlots) return false;
  return g_slots[slot].faulted.load(std::memory_order_acquire) != 0;
}

}  // namespace lcmx::shm::detail
