// lcmx::shm hardening tests (issue 10): process churn, containers (pid/mount namespaces
// emulated with clone flags, as `unshare --pid --fork --mount-proc` does), a full tmpfs,
// hostile files and a hostile truncating process. Label: integration.
// Every wait has a deadline; a watchdog per test; children are killed and reaped.
#include <catch2/catch.hpp>

#include <sys/stat.h>

#include <deque>

#include "lcmx/shm/detail/layout.hpp"
#include "lcmx/shm/futex.hpp"
#include "lcmx/shm/liveness.hpp"
#include "lcmx/shm/segment.hpp"
#include "test_util.hpp"

using namespace lcmx::shm;
using namespace lcmx::shm::test;
namespace d = lcmx::shm::detail;

// Under AddressSanitizer: let lcmx install its SIGBUS guard (ASan otherwise ignores a
// program's sigaction for the signals it handles). Unused in other builds.
extern "C" const char* __asan_default_options() { return "allow_user_segv_handler=1"; }

namespace {

// The test's own read-write view of a segment file (to inspect or tamper with the layout).
struct Mapped {
  void* p = MAP_FAILED;
  std::size_t n = 0;
  explicit Mapped(const std::string& name) {
    int fd = ::shm_open(("/" + name).c_str(), O_RDWR, 0);
    if (fd < 0) return;
    struct stat st {};
    ::fstat(fd, &st);
    n = static_cast<std::size_t>(st.st_size);
    p = ::mmap(nullptr, n, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    ::close(fd);
  }
  ~Mapped() {
    if (p != MAP_FAILED) ::munmap(p, n);
  }
  bool ok() const { return p != MAP_FAILED; }
  d::SegmentHeader& hdr() const { return *static_cast<d::SegmentHeader*>(p); }
  d::SubscriberEntry& sub(std::uint32_t i) const {
    return reinterpret_cast<d::SubscriberEntry*>(static_cast<char*>(p) +
                                                 hdr().subscribers_offset)[i];
  }
  d::SlotHeader& slot(std::uint32_t i) const {
    return *reinterpret_cast<d::SlotHeader*>(static_cast<char*>(p) + hdr().slots_offset +
                                             i * hdr().slot_stride);
  }
  std::atomic<std::uint64_t>& desc(std::uint32_t i) const {
    return reinterpret_cast<std::atomic<std::uint64_t>*>(static_cast<char*>(p) +
                                                         hdr().desc_offset)[i];
  }
};

// Waits (deadline, no sleep-to-synchronise) until pred() holds; polls with a short futex-free
// yield between checks.
template <class Pred>
bool eventually(Pred pred, std::chrono::milliseconds limit) {
  const auto deadline = Clock::now() + limit;
  while (Clock::now() < deadline) {
    if (pred()) return true;
    std::this_thread::yield();
  }
  return pred();
}

constexpr int kContainerFlags = CLONE_NEWPID | CLONE_NEWNS;

}  // namespace

// ---- item 4: pid namespaces ----

TEST_CASE("a Writer in another pid namespace is alive: reclaim leaves it, Readers read it",
          "[shm][pidns]") {
  Watchdog wd(20s);
  const auto base = unique_base("pidns_w");
  ShmGuard g(base);
  Pipe up, down;
  Child c(
      [&] {
        auto w = Writer::create(base, opts(8));
        up.send('R');
        if (down.recv(10s) != 'G') return 10;
        write_msg(w, 7, 200);
        up.send('W');
        park(down);
        return 0;
      },
      kContainerFlags);
  if (!c.started()) {
    WARN("cannot create a pid namespace (errno " << c.error() << "): skipped");
    return;
  }
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');
  const auto rep = reclaim_orphans(base);
  CHECK(rep.removed == 0);
  REQUIRE(shm_exists(base + "_g0"));
  auto r = Reader::open(base + "_g0");
  CHECK(r.writer_alive());
  down.send('G');
  REQUIRE(up.recv(10s) == 'W');
  auto s = r.take();
  REQUIRE(s);
  std::uint64_t idx = 0;
  CHECK(check_message(s->data(), s->size(), &idx));
  CHECK(idx == 7);
  c.kill9();
  CHECK(killed_by(c.wait(10s), SIGKILL));
  CHECK_FALSE(r.writer_alive());
  CHECK(reclaim_orphans(base).removed == 1);
}

TEST_CASE("a Reader in another pid namespace keeps its pins", "[shm][pidns]") {
  Watchdog wd(20s);
  const auto base = unique_base("pidns_r");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(2));
  Pipe up, down;
  Child c(
      [&] {
        auto r = Reader::open(base + "_g0");
        up.send('R');
        if (down.recv(10s) != 'G') return 10;
        auto a = r.take();
        auto b = r.take();
        if (!a || !b) return 11;
        up.send('P');
        if (down.recv(10s) != 'C') return 12;
        std::uint64_t ia = 0, ib = 0;
        if (!check_message(a->data(), a->size(), &ia) || ia != 0) return 13;
        if (!check_message(b->data(), b->size(), &ib) || ib != 1) return 14;
        return 0;
      },
      kContainerFlags);
  if (!c.started()) {
    WARN("cannot create a pid namespace (errno " << c.error() << "): skipped");
    return;
  }
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');
  write_msg(w, 0, 1000);
  write_msg(w, 1, 1000);
  down.send('G');
  REQUIRE(up.recv(10s) == 'P');
  CHECK(w.live_readers() == 1);
  // Both slots pinned by a live Reader of another pid namespace: never overwritten.
  for (int i = 2; i < 6; ++i) {
    try {
      write_msg(w, static_cast<std::uint64_t>(i), 1000);
    } catch (const Error&) {
    }
  }
  down.send('C');
  CHECK(exited_ok(c.wait(10s)));
}

// ---- item 5: clean exit after growth ----

TEST_CASE("a clean Writer exit after growth loses nothing for a lagging Reader", "[shm][exit]") {
  Watchdog wd(20s);
  const auto base = unique_base("exitgrow");
  ShmGuard g(base);
  std::optional<Writer> w = Writer::create(base, opts(8));
  std::optional<Reader> ro = Reader::open(w->segment_name());
  auto& r = *ro;
  write_msg(*w, 0, 100);
  write_msg(*w, 1, 100);
  write_msg(*w, 2, 10000);  // generation 1
  write_msg(*w, 3, 10000);
  write_msg(*w, 4, 40000);  // generation 2
  const std::uint64_t published = w->published();
  w.reset();  // clean exit while r still sits in generation 0
  // Another process starting up reclaims orphans: generations r still needs are kept.
  CHECK(reclaim_orphans(base).removed == 0);
  std::uint64_t expect = 0;
  while (auto s = r.take()) {
    std::uint64_t idx = 0;
    REQUIRE(check_message(s->data(), s->size(), &idx));
    CHECK(idx == expect);
    ++expect;
  }
  CHECK(r.received() + r.drops() == published);
  CHECK(r.received() == published);
  CHECK_FALSE(r.has_data());
  ro.reset();
  CHECK(shm_names(base + "_").empty());  // the last Reader out removed what the Writer left
}

// ---- item 6: full tmpfs, hostile files, hostile truncation ----

TEST_CASE("a full tmpfs gives Error(system), never SIGBUS", "[shm][tmpfs]") {
  Watchdog wd(20s);
  const auto base = unique_base("fulltmpfs");
  Child c(
      [&] {
        WriterOptions big = opts(8);
        big.initial_slot_size = 256 * 1024;  // 2 MiB > the 1 MiB tmpfs
        try {
          auto w = Writer::create(base + "a", big);
          return 20;  // must not succeed
        } catch (const Error& e) {
          if (e.code() != Errc::system) return 21;
        }
        auto w = Writer::create(base + "b", opts(8));  // ~40 KiB: fits
        write_msg(w, 0, 1000);
        try {
          write_msg(w, 1, 600 * 1024);  // growth to 8 x 600 KiB: does not fit
          return 22;
        } catch (const Error& e) {
          if (e.code() != Errc::system) return 23;
        }
        write_msg(w, 2, 1000);  // the Writer still works in its current generation
        return 0;
      },
      CLONE_NEWNS, [] {
        return ::mount("tmpfs", "/dev/shm", "tmpfs", MS_NOSUID | MS_NODEV, "size=1m") == 0 ? 0
                                                                                         : 96;
      });
  if (!c.started()) {
    WARN("cannot create a mount namespace (errno " << c.error() << "): skipped");
    return;
  }
  wd.watch_child(c.pid());
  const int st = c.wait(15s);
  if (WIFEXITED(st) && (WEXITSTATUS(st) == 96 || WEXITSTATUS(st) == 97)) {
    WARN("cannot mount a private tmpfs: skipped");
    return;
  }
  CHECK_FALSE(killed_by(st, SIGBUS));
  CHECK(exited_ok(st));
}

TEST_CASE("segments writable by others or owned by another user are refused", "[shm][perm]") {
  Watchdog wd(10s);
  const auto base = unique_base("perm");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(4));
  const std::string path = "/dev/shm/" + w.segment_name();
  struct stat st {};
  REQUIRE(::stat(path.c_str(), &st) == 0);
  CHECK((st.st_mode & S_IWOTH) == 0);
  REQUIRE(::chmod(path.c_str(), 0666) == 0);
  CHECK_THROWS_AS(Reader::open(w.segment_name()), Error);
  REQUIRE(::chmod(path.c_str(), 0660) == 0);
  if (::geteuid() == 0) {  // root can hand the file to another user
    REQUIRE(::chown(path.c_str(), 65534, 65534) == 0);
    CHECK_THROWS_AS(Reader::open(w.segment_name()), Error);
    REQUIRE(::chown(path.c_str(), 0, 0) == 0);
  }
  CHECK_NOTHROW(Reader::open(w.segment_name()));
}

TEST_CASE("a hostile process truncating a live segment: no SIGBUS in Writer or Reader",
          "[shm][truncate]") {
  Watchdog wd(30s);
  const auto base = unique_base("trunc");
  ShmGuard g(base);
  Pipe wup, wdown, rup, rdown;
  Child writer([&] {
    auto w = Writer::create(base, opts(8));
    wup.send('R');
    // Publishes until told to stop (bounded), then once more as the final message.
    std::uint64_t i = 0;
    const auto deadline = Clock::now() + 15s;
    pollfd p{wdown.fd[0], POLLIN, 0};
    while (Clock::now() < deadline && ::poll(&p, 1, 1) == 0) write_msg(w, i++, 3000);
    if (wdown.recv(1s) != 'S') return 11;
    // After the truncation: the first write lands in the repaired (private) mapping and is
    // lost; the next loan moves to a fresh generation that the Reader follows.
    for (int k = 0; k < 20; ++k) write_msg(w, i++, 3000);
    write_msg(w, 1'000'000, 3000);
    std::fprintf(stderr, "writer: at %s, published %llu, dropped %llu\n", w.segment_name().c_str(),
                 static_cast<unsigned long long>(w.published()),
                 static_cast<unsigned long long>(w.dropped()));
    wup.send('D');
    if (wdown.recv(10s) != 'X') return 10;  // stay alive until the Reader is done
    return 0;
  });
  wd.watch_child(writer.pid());
  REQUIRE(wup.recv(10s) == 'R');
  Child reader([&] {
    auto r = Reader::open(base + "_g0");
    const auto deadline = Clock::now() + 15s;
    while (Clock::now() < deadline && !r.take()) {
    }
    rup.send(r.received() > 0 ? 'R' : 'N');
    std::uint64_t bad = 0;
    while (Clock::now() < deadline) {
      try {
        auto s = r.take();
        if (!s) continue;
        std::uint64_t idx = 0;
        if (!check_message(s->data(), s->size(), &idx)) {
          ++bad;  // a torn sample must be reported as such (see below), never as good data
          continue;
        }
        if (idx == 1'000'000) return 0;
      } catch (const Error& e) {
        std::fprintf(stderr, "reader: %s\n", e.what());
      }
    }
    std::fprintf(stderr, "reader: at %s, received %llu, drops %llu, bad %llu\n",
                 r.segment_name().c_str(), static_cast<unsigned long long>(r.received()),
                 static_cast<unsigned long long>(r.drops()), static_cast<unsigned long long>(bad));
    return 30;
  });
  wd.watch_child(reader.pid());
  REQUIRE(rup.recv(10s) == 'R');
  Child hostile([&] {
    int fd = ::shm_open(("/" + base + "_g0").c_str(), O_RDWR, 0);
    if (fd < 0) return 40;
    return ::ftruncate(fd, 0) == 0 ? 0 : 41;
  });
  CHECK(exited_ok(hostile.wait(10s)));
  wdown.send('S');
  REQUIRE(wup.recv(10s) == 'D');
  const int rs = reader.wait(20s);
  wdown.send('X');
  const int ws = writer.wait(10s);
  INFO("writer wait status " << ws << ", reader wait status " << rs);
  CHECK_FALSE(killed_by(ws, SIGBUS));
  CHECK_FALSE(killed_by(rs, SIGBUS));
  CHECK(exited_ok(ws));
  CHECK(exited_ok(rs));
}

// Keep last N after a truncation: the Writer's move to a fresh generation carries nothing
// it cannot read safely (the truncated file reads zeros), and what it delivers is intact.
TEST_CASE("keep: a truncated generation carries nothing into the fresh one", "[shm][truncate][keep]") {
  Watchdog wd(20s);
  const auto base = unique_base("trunckeep");
  ShmGuard g(base);
  Child writer([&] {
    WriterOptions o = opts(8);
    o.keep = 3;
    auto w = Writer::create(base, o);
    for (std::uint64_t i = 1; i <= 3; ++i) write_msg(w, i, 64);
    int fd = ::shm_open(("/" + base + "_g0").c_str(), O_RDWR, 0);
    if (fd < 0 || ::ftruncate(fd, 0) != 0) return 40;
    ::close(fd);
    // The first write after the truncation faults (lost); the next moves to generation 1.
    for (std::uint64_t i = 4; i <= 6; ++i) write_msg(w, i, 64);
    if (w.segment_name() != base + "_g1") return 41;
    const auto img = read_shm_file(base + "_g1");
    if (img.size() < sizeof(d::SegmentHeader)) return 42;
    std::uint32_t carried = ~0u;
    std::memcpy(&carried, img.data() + offsetof(d::SegmentHeader, carried), 4);
    if (carried != 0) return 43;
    auto r = Reader::open(base, 7);
    std::uint64_t last = 0;
    while (auto s = r.take()) {
      std::uint64_t idx = 0;
      if (!check_message(s->data(), s->size(), &idx) || !s->intact()) return 44;
      if (idx <= last || idx < 4) return 45;  // in order, nothing from the truncated file
      last = idx;
    }
    return last == 6 ? 0 : 46;
  });
  wd.watch_child(writer.pid());
  const int ws = writer.wait(15s);
  INFO("writer wait status " << ws);
  CHECK_FALSE(killed_by(ws, SIGBUS));
  CHECK(exited_ok(ws));
}

// ---- item 7: geometry ----

TEST_CASE("default options: 9 and 32 Readers holding pins never make write() throw",
          "[shm][geometry]") {
  Watchdog wd(20s);
  for (std::uint32_t nreaders : {9u, 32u}) {
    const auto base = unique_base("pins");
    ShmGuard g(base);
    auto w = Writer::create(base, WriterOptions{});
    std::vector<Reader> readers;
    for (std::uint32_t i = 0; i < nreaders; ++i) readers.push_back(Reader::open(w.segment_name()));
    std::vector<std::deque<ReadSample>> held(nreaders);
    // Round robin: after message m, Reader m % n takes what it can and keeps the newest
    // sample pinned, so every Reader pins a different slot: 8 slots, 9+ pinning Readers.
    for (std::uint64_t m = 0; m < 200; ++m) {
      REQUIRE_NOTHROW(write_msg(w, m, 128));
      auto& h = held[m % nreaders];
      h.clear();
      while (auto s = readers[m % nreaders].take()) {
        h.clear();
        h.push_back(std::move(*s));
      }
    }
    CHECK(w.dropped() > 0);  // the situation really arose
    for (std::uint32_t i = 0; i < nreaders; ++i) {
      for (auto& s : held[i]) {
        std::uint64_t idx = 0;
        CHECK(check_message(s.data(), s.size(), &idx));  // pinned: never overwritten
        CHECK(idx == s.sequence());
      }
      held[i].clear();
      while (readers[i].take()) {
      }
      CHECK(readers[i].received() + readers[i].drops() == w.published());
    }
  }
}

// ---- item 8: follow failure, dead readers, wedged entries, probe ----

TEST_CASE("a failing generation follow backs off instead of failing on every call",
          "[shm][follow]") {
  Watchdog wd(20s);
  const auto base = unique_base("follow");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8, 1));
  auto a = Reader::open(w.segment_name());
  write_msg(w, 0, 100);
  write_msg(w, 1, 10000);  // generation 1
  std::optional<Reader> b = Reader::open(base + "_g1");  // fills g1's one entry
  write_msg(w, 2, 10000);
  auto s = a.take();
  REQUIRE(s);
  s.reset();
  int errors = 0;
  for (int i = 0; i < 100; ++i) {
    try {
      a.take();
    } catch (const Error& e) {
      CHECK(e.code() == Errc::no_subscriber_slot);
      ++errors;
    }
  }
  CHECK(errors == 1);          // reported once, then retried later
  CHECK_FALSE(a.has_data());   // no busy loop while backing off
  CHECK(a.retry_at() > Clock::now());  // ... and the executor knows when to look again
  b.reset();
  std::vector<std::uint64_t> got;
  CHECK(eventually(
      [&] {
        try {
          while (auto x = a.take()) got.push_back(x->sequence());
        } catch (const Error&) {
        }
        return got.size() == 2;
      },
      5s));
  CHECK(got == std::vector<std::uint64_t>{1, 2});
  CHECK(a.drops() == 0);
}

TEST_CASE("an armed Reader killed -9 is reclaimed in the current generation", "[shm][reclaim]") {
  Watchdog wd(20s);
  const auto base = unique_base("deadarmed");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8, 4));
  Pipe up, down;
  Child c([&] {
    auto r = Reader::open(base + "_g0");
    r.arm();  // dies armed
    up.send('A');
    park(down);
    return 0;
  });
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'A');
  Mapped m(w.segment_name());
  REQUIRE(m.ok());
  CHECK(m.hdr().waiters.load() == 1);
  c.kill9();
  CHECK(killed_by(c.wait(10s), SIGKILL));
  // The Writer notices within a bounded number of commits / time.
  CHECK(eventually(
      [&] {
        write_msg(w, 0, 64);
        return m.hdr().waiters.load() == 0 && w.registered_readers() == 0;
      },
      5s));
}

TEST_CASE("entries wedged mid-register or mid-reclaim by a killed process are reclaimed",
          "[shm][wedged]") {
  Watchdog wd(20s);
  const auto base = unique_base("wedged");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8, 2));
  {
    Mapped m(w.segment_name());
    REQUIRE(m.ok());
    // What a process killed between the claim CAS and the pid store, or inside a reclaim,
    // leaves behind (state values of layout v2: 1 = claiming, 3 = reclaiming).
    m.sub(0).state.store(1);
    m.sub(0).pid.store(0);
    m.sub(1).state.store(3);
    m.sub(1).pid.store(0);
    m.hdr().sub_high_water.store(2);
  }
  auto r = Reader::open(w.segment_name());
  write_msg(w, 0, 64);
  CHECK(r.take().has_value());
}

TEST_CASE("a Writer preempted during a pin probe causes no drop", "[shm][probe]") {
  Watchdog wd(10s);
  const auto base = unique_base("probe");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8));
  auto r = Reader::open(w.segment_name());
  write_msg(w, 0, 64);
  Mapped m(w.segment_name());
  REQUIRE(m.ok());
  const std::uint32_t slot = d::desc_slot(m.desc(0).load());
  // The Writer stored WRITING to probe the slot's pins and was preempted before restoring it.
  m.slot(slot).seq.store(d::kSlotWriting);
  CHECK_FALSE(r.take().has_value());
  CHECK(r.drops() == 0);
  m.slot(slot).seq.store(0);  // the probe ends: the message was never touched
  auto s = r.take();
  REQUIRE(s);
  CHECK(s->sequence() == 0);
  CHECK(r.drops() == 0);
}

// ---- item 1: ABA on dead entries ----

TEST_CASE("Readers opening concurrently while dead entries exist never share an entry",
          "[shm][aba]") {
  Watchdog wd(60s);
  const auto base = unique_base("aba");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8, 8));
  const std::string name = w.segment_name();
  Mapped m(name);
  REQUIRE(m.ok());
  for (int round = 0; round < 30; ++round) {
    // Two dead entries (zombies until reaped: a slow liveness check widens the race).
    std::vector<std::unique_ptr<Child>> dead;
    for (int k = 0; k < 2; ++k) {
      Pipe up;
      auto c = std::make_unique<Child>([&] {
        auto r = Reader::open(name);
        up.send('R');
        for (;;) ::pause();
        return 0;
      });
      REQUIRE(up.recv(10s) == 'R');
      dead.push_back(std::move(c));
    }
    for (auto& c : dead) c->kill9();
    // Four live openers race over the two dead entries.
    Pipe up, down;
    std::vector<std::unique_ptr<Child>> live;
    for (int k = 0; k < 4; ++k) {
      live.push_back(std::make_unique<Child>([&] {
        auto r = Reader::open(name);
        up.send('O');
        park(down);
        return 0;
      }));
      wd.watch_child(live.back()->pid());
    }
    for (int k = 0; k < 4; ++k) REQUIRE(up.recv(10s) == 'O');
    // Every live opener has its own entry.
    int active = 0;
    for (std::uint32_t i = 0; i < 8; ++i) {
      if ((m.sub(i).state.load() & 3u) == 2u) ++active;
    }
    for (auto& c : dead) c->wait(10s);
    for (auto& c : live) c->kill9();
    for (auto& c : live) c->wait(10s);
    INFO("round " << round);
    REQUIRE(active >= 4);
    // Clean the table for the next round.
    CHECK(w.live_readers() == 0);
  }
}

// ---- exported for core: owner_alive, OwnerWatch, process_tag; ReadSample::intact ----

namespace {

// Kills the Writer child and returns how long OwnerWatch took to report it (or -1).
std::chrono::microseconds watch_death(Child& c, const std::string& segment) {
  OwnerWatch watch;
  const auto key = watch.watch(segment);
  CHECK(watch.take_dead().empty());
  CHECK(owner_alive(segment));
  const auto t0 = Clock::now();
  c.kill9();
  pollfd p{watch.fd(), POLLIN, 0};
  while (Clock::now() - t0 < 5s) {
    if (::poll(&p, 1, 1000) < 0 && errno != EINTR) break;
    auto dead = watch.take_dead();
    if (!dead.empty()) {
      CHECK(dead == std::vector<std::uint64_t>{key});
      CHECK_FALSE(owner_alive(segment));
      return std::chrono::duration_cast<std::chrono::microseconds>(Clock::now() - t0);
    }
  }
  return std::chrono::microseconds(-1);
}

}  // namespace

TEST_CASE("OwnerWatch reports a Writer killed -9 (same and other pid namespace)",
          "[shm][watch]") {
  Watchdog wd(30s);
  for (int flags : {0, kContainerFlags}) {
    const auto base = unique_base("watch");
    ShmGuard g(base);
    Pipe up, down;
    Child c(
        [&] {
          auto w = Writer::create(base, opts(4));
          up.send('R');
          park(down);
          return 0;
        },
        flags);
    if (!c.started()) {
      WARN("cannot create a pid namespace: skipped");
      continue;
    }
    wd.watch_child(c.pid());
    REQUIRE(up.recv(10s) == 'R');
    const auto us = watch_death(c, base + "_g0");
    INFO("flags " << flags << ": death noticed after " << us.count() << " us");
    CHECK(us.count() >= 0);
    WARN("OwnerWatch (" << (flags == 0 ? "same pid namespace, pidfd" : "other pid namespace, inotify")
                        << "): Writer death noticed " << us.count() << " us after SIGKILL");
    c.wait(10s);
  }
}

TEST_CASE("process_tag differs across pid namespaces even for equal pids", "[shm][pidns]") {
  Watchdog wd(20s);
  Pipe up;
  auto run = [&] {
    return std::make_unique<Child>(
        [&] {
          const std::string t = process_tag();
          if (::write(up.fd[1], t.data(), t.size()) != static_cast<ssize_t>(t.size())) return 1;
          up.send('\n');
          return 0;
        },
        kContainerFlags);
  };
  auto read_line = [&] {
    std::string s;
    for (char c; (c = up.recv(10s)) != 0 && c != '\n';) s += c;
    return s;
  };
  auto a = run();
  if (!a->started()) {
    WARN("cannot create a pid namespace: skipped");
    return;
  }
  const std::string ta = read_line();
  auto b = run();
  const std::string tb = read_line();
  CHECK(ta.rfind("1n", 0) == 0);  // both are pid 1 of their namespace
  CHECK(tb.rfind("1n", 0) == 0);
  CHECK(ta != tb);
  CHECK(ta != process_tag());
  CHECK(exited_ok(a->wait(10s)));
  CHECK(exited_ok(b->wait(10s)));
}

TEST_CASE("ReadSample::intact is false once the slot was rewritten or the entry taken",
          "[shm][aba]") {
  Watchdog wd(10s);
  const auto base = unique_base("intact");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(4));
  auto r = Reader::open(w.segment_name());
  write_msg(w, 0, 64);
  write_msg(w, 1, 64);
  Mapped m(w.segment_name());
  REQUIRE(m.ok());
  auto a = r.take();
  auto b = r.take();
  REQUIRE(a);
  REQUIRE(b);
  CHECK(a->intact());
  CHECK(b->intact());
  // A writer that (wrongly) reused a's slot while it was read:
  m.slot(d::desc_slot(m.desc(0).load())).seq.store(d::kSlotWriting);
  CHECK_FALSE(a->intact());
  // Our entry freed and re-claimed behind our back (what the ABA did): epoch changed.
  std::uint32_t st = m.sub(0).state.load();
  m.sub(0).state.store(d::sub_word(d::sub_epoch(st) + 2, d::kSubActive));
  CHECK_FALSE(b->intact());
}

TEST_CASE("shm_domain_id tells a private /dev/shm from the shared one", "[shm][domain]") {
  Watchdog wd(20s);
  const std::uint64_t here = shm_domain_id();
  CHECK(here != 0);
  Pipe up;
  auto report = [&] {
    const std::uint64_t id = shm_domain_id();
    if (::write(up.fd[1], &id, sizeof id) != sizeof id) return 1;
    return 0;
  };
  auto read_id = [&] {
    std::uint64_t id = 0;
    pollfd p{up.fd[0], POLLIN, 0};
    if (::poll(&p, 1, 10000) == 1 && ::read(up.fd[0], &id, sizeof id) != sizeof id) id = 0;
    return id;
  };
  {  // a container sharing /dev/shm (own pid and mount namespaces): same domain
    Child c(report, kContainerFlags);
    if (!c.started()) {
      WARN("cannot create namespaces: skipped");
      return;
    }
    CHECK(read_id() == here);
    CHECK(exited_ok(c.wait(10s)));
  }
  {  // a container with its own /dev/shm: another domain
    Child c(report, CLONE_NEWNS, [] {
      return ::mount("tmpfs", "/dev/shm", "tmpfs", MS_NOSUID | MS_NODEV, "size=1m") == 0 ? 0 : 96;
    });
    const std::uint64_t there = read_id();
    const int st = c.wait(10s);
    if (WIFEXITED(st) && WEXITSTATUS(st) == 96) {
      WARN("cannot mount a private tmpfs: skipped");
      return;
    }
    CHECK(exited_ok(st));
    CHECK(there != 0);
    CHECK(there != here);
  }
}
