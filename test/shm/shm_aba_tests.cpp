// Issue 10 item 1: the ABA in the reclaim of a dead Reader's entry, made deterministic.
// This binary interposes kill(2) (the static lcmx_shm's calls bind to this definition), so a
// registering process can be stopped exactly inside a liveness check of a dead entry while
// another process reclaims that entry and registers into it. With a pid-based check and a
// compare-exchange on a bare state word, the stalled process then "reclaims" the live
// Reader's entry (ABA) and both share one entry: pins clobbered, torn reads. Own binary so
// that no other test runs with kill interposed. Label: integration.
#include <catch2/catch.hpp>

#include "lcmx/shm/detail/layout.hpp"
#include "lcmx/shm/segment.hpp"
#include "test_util.hpp"

using namespace lcmx::shm;
using namespace lcmx::shm::test;
namespace d = lcmx::shm::detail;

namespace {
std::atomic<pid_t> g_hook_pid{0};
int g_hook_up = -1;
int g_hook_down = -1;
}  // namespace

// Pass-through kill; in a process that armed the hook, kill(target, 0) first reports 'K' and
// waits (bounded) for the test to let it go on.
extern "C" int kill(pid_t pid, int sig) {
  if (sig == 0 && pid != 0 && g_hook_pid.load() == pid) {
    g_hook_pid.store(0);
    char c = 'K';
    if (::write(g_hook_up, &c, 1) != 1) std::_Exit(90);
    pollfd p{g_hook_down, POLLIN, 0};
    if (::poll(&p, 1, 10000) == 1 && ::read(g_hook_down, &c, 1) != 1) std::_Exit(91);
  }
  return static_cast<int>(::syscall(SYS_kill, pid, sig));
}

TEST_CASE("a registrant stalled in a dead entry's liveness check cannot free a live entry",
          "[shm][aba]") {
  Watchdog wd(30s);
  const auto base = unique_base("abahook");
  ShmGuard g(base);
  WriterOptions o;
  o.slot_count = 8;
  o.max_subscribers = 2;
  auto w = Writer::create(base, o);
  const std::string name = w.segment_name();
  // A dead Reader's entry (killed and reaped).
  pid_t dead_pid = 0;
  {
    Pipe up;
    Child dead([&] {
      auto r = Reader::open(name);
      up.send('R');
      for (;;) ::pause();
      return 0;
    });
    REQUIRE(up.recv(10s) == 'R');
    dead_pid = dead.pid();
    dead.kill9();
    dead.wait(10s);
  }
  Pipe a_up, a_down, b_up, park_a, park_b;
  Child a([&] {
    g_hook_up = a_up.fd[1];
    g_hook_down = a_down.fd[0];
    g_hook_pid.store(dead_pid);
    auto r = Reader::open(name);
    a_up.send('O');
    park_a.recv(20s);
    return 0;
  });
  wd.watch_child(a.pid());
  const char first = a_up.recv(10s);
  REQUIRE((first == 'K' || first == 'O'));  // 'K': stalled in the check (pid-based code)
  Child b([&] {
    auto r = Reader::open(name);
    b_up.send('O');
    park_b.recv(20s);
    return 0;
  });
  wd.watch_child(b.pid());
  REQUIRE(b_up.recv(10s) == 'O');
  if (first == 'K') {
    a_down.send('G');
    REQUIRE(a_up.recv(10s) == 'O');
  }
  // Two live Readers, two distinct entries.
  CHECK(w.live_readers() == 2);
  int fd = ::shm_open(("/" + name).c_str(), O_RDONLY, 0);
  REQUIRE(fd >= 0);
  void* p = ::mmap(nullptr, 4096, PROT_READ, MAP_SHARED, fd, 0);
  ::close(fd);
  REQUIRE(p != MAP_FAILED);
  const auto* h = static_cast<const d::SegmentHeader*>(p);
  const auto* subs = reinterpret_cast<const d::SubscriberEntry*>(static_cast<const char*>(p) +
                                                                 h->subscribers_offset);
  int active = 0;
  for (int i = 0; i < 2; ++i) active += (subs[i].state.load() & 0xffu) == 2u ? 1 : 0;
  CHECK(active == 2);
  ::munmap(p, 4096);
  park_a.send('X');
  park_b.send('X');
  CHECK(exited_ok(a.wait(10s)));
  CHECK(exited_ok(b.wait(10s)));
}
