// lcmx::shm multi-process tests (fork()ed writers/readers, kill -9). Label: integration.
// Children communicate through pipes; every wait has a deadline; a watchdog per test.
#include <catch2/catch.hpp>

#include <deque>
#include <random>
#include <thread>

#include "lcmx/shm/futex.hpp"
#include "lcmx/shm/segment.hpp"
#include "test_util.hpp"

using namespace lcmx::shm;
using namespace lcmx::shm::test;

TEST_CASE("a slot pinned by a killed Reader is reclaimed by the Writer", "[shm][fork]") {
  Watchdog wd(20s);
  const auto base = unique_base("deadpin");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(2));
  Pipe up, down;
  Child c([&] {
    auto r = Reader::open(base + "_g0");
    up.send('R');
    if (down.recv(10s) != 'G') return 10;
    auto a = r.take();
    auto b = r.take();
    if (!a || !b) return 11;
    up.send('P');  // both slots pinned; die holding them
    park(down);
    return 0;
  });
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');
  write_msg(w, 0, 100);
  write_msg(w, 1, 100);
  down.send('G');
  REQUIRE(up.recv(10s) == 'P');
  CHECK(w.live_readers() == 1);
  // Live Reader pins both slots: the Writer drops (counted) rather than overwrite.
  write_msg(w, 2, 100);
  CHECK(w.dropped() == 1);
  c.kill9();
  CHECK(killed_by(c.wait(10s), SIGKILL));
  CHECK(w.live_readers() == 0);
  write_msg(w, 2, 100);  // pins of the dead Reader reclaimed
  write_msg(w, 3, 100);
  CHECK(w.dropped() == 1);
  auto r = Reader::open(w.segment_name());
  write_msg(w, 4, 100);
  auto s = r.take();
  REQUIRE(s);
  std::uint64_t idx = 0;
  CHECK(check_message(s->data(), s->size(), &idx));
  CHECK(idx == 4);
}

TEST_CASE("reclaim_orphans removes the segment of a Writer killed -9", "[shm][fork]") {
  Watchdog wd(20s);
  const auto base = unique_base("orphan");
  ShmGuard g(base);
  Pipe up, down;
  Child c([&] {
    auto w = Writer::create(base, opts(4));
    write_msg(w, 0, 5000);  // generation 1
    up.send('R');
    park(down);
    return 0;
  });
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');
  REQUIRE(shm_exists(base + "_g1"));
  auto rep = reclaim_orphans(base);
  CHECK(rep.removed == 0);  // owner alive
  c.kill9();
  CHECK(killed_by(c.wait(10s), SIGKILL));
  rep = reclaim_orphans(base);
  CHECK(rep.removed == 1);
  CHECK(rep.skipped == 0);
  CHECK(shm_names(base + "_").empty());
}

TEST_CASE("a stale segment of a dead Writer does not block a new Writer", "[shm][fork]") {
  Watchdog wd(20s);
  const auto base = unique_base("stale");
  ShmGuard g(base);
  Pipe up, down;
  Child c([&] {
    auto w = Writer::create(base, opts(4));
    up.send('R');
    park(down);
    return 0;
  });
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');
  CHECK_THROWS_AS(Writer::create(base, opts(4)), Error);  // owner alive
  c.kill9();
  CHECK(killed_by(c.wait(10s), SIGKILL));
  auto w = Writer::create(base, opts(4));  // stale file removed, created anew
  auto r = Reader::open(w.segment_name());
  CHECK(r.writer_alive());
  write_msg(w, 0, 64);
  CHECK(r.take().has_value());
}

TEST_CASE("a Writer killed -9 mid-write never delivers that message", "[shm][fork]") {
  Watchdog wd(20s);
  const auto base = unique_base("midwrite");
  ShmGuard g(base);
  Pipe up, down;
  Child c([&] {
    auto w = Writer::create(base, opts(4));
    up.send('R');
    if (down.recv(10s) != 'G') return 10;
    write_msg(w, 0, 1000);
    auto l = w.loan(1000);
    std::memset(l.data(), 0x5A, 500);  // half written
    ::raise(SIGKILL);
    return 0;
  });
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');
  auto r = Reader::open(base + "_g0");
  down.send('G');
  CHECK(killed_by(c.wait(10s), SIGKILL));
  auto s = r.take();
  REQUIRE(s);
  std::uint64_t idx = 99;
  CHECK(check_message(s->data(), s->size(), &idx));
  CHECK(idx == 0);
  CHECK_FALSE(r.take().has_value());
  CHECK_FALSE(r.has_data());
  CHECK_FALSE(r.writer_alive());
  s.reset();
  auto rep = reclaim_orphans(base);
  CHECK(rep.removed == 1);
}

TEST_CASE("wait_any wakes a Reader in another process on commit", "[shm][fork][futex]") {
  Watchdog wd(20s);
  const auto base = unique_base("xwake");
  ShmGuard g(base);
  Pipe up, down;
  Child c([&] {
    auto w = Writer::create(base, opts(4));
    up.send('R');
    if (down.recv(10s) != 'G') return 10;
    write_msg(w, 7, 100);
    if (down.recv(10s) != 'Q') return 11;
    return 0;
  });
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');
  auto r = Reader::open(base + "_g0");
  {  // idle: times out
    WaitToken t = r.arm();
    REQUIRE_FALSE(r.has_data());
    CHECK(wait_any({&t, 1}, 50ms) == WaitResult::timeout);
    r.disarm();
  }
  WaitToken t = r.arm();
  REQUIRE_FALSE(r.has_data());
  down.send('G');
  const auto t0 = Clock::now();
  WaitResult res = WaitResult::woken;  // stays so if the commit beat us to has_data()
  while (!r.has_data() && Clock::now() - t0 < 10s) res = wait_any({&t, 1}, 10s);
  r.disarm();
  CHECK(res == WaitResult::woken);
  CHECK(Clock::now() - t0 < 5s);
  auto s = r.take();
  REQUIRE(s);
  std::uint64_t idx = 0;
  CHECK(check_message(s->data(), s->size(), &idx));
  CHECK(idx == 7);
  down.send('Q');
  CHECK(exited_ok(c.wait(10s)));
  CHECK_FALSE(r.writer_alive());
}

TEST_CASE("stress: fork()ed writer, 2 readers, random sizes, checksums, growth",
          "[shm][fork][stress]") {
  Watchdog wd(50s, "stress");
  const auto base = unique_base("stress");
  ShmGuard g(base);
  const std::uint64_t total = kSanitized ? 20000 : 100000;
  Pipe up, down;
  Child c([&] {
    auto w = Writer::create(base, opts(16));
    up.send('R');
    if (down.recv(10s) != 'G') return 10;
    std::mt19937_64 rng(12345);
    std::vector<unsigned char> buf(40000);
    for (std::uint64_t i = 0; i < total; ++i) {
      // Mostly small, sometimes large: grows 4 KiB -> 8 -> 16 -> 32 -> 64 KiB on the way.
      const std::uint64_t cap = i < total / 4 ? 4000 : i < total / 2 ? 12000 : 40000;
      const std::size_t sz = 16 + rng() % (rng() % 8 == 0 ? cap : 2000);
      auto l = w.loan(sz);
      fill_message(reinterpret_cast<unsigned char*>(l.data()), sz, i);
      w.commit(std::move(l), sz);
    }
    if (w.published() != total) return 12;
    if (down.recv(40s) != 'Q') return 11;  // readers may still follow generations by name
    return 0;
  });
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');

  struct Result {
    std::uint64_t received = 0, drops = 0, torn = 0, disorder = 0, pinned_changed = 0;
    std::uint64_t last = 0;
    bool timed_out = false;
  };
  Result res[2];
  std::optional<Reader> readers[2];
  for (auto& r : readers) r.emplace(Reader::open(base + "_g0"));
  const auto deadline = Clock::now() + 40s;
  auto run = [&](Reader& r, Result& out, std::size_t keep) {
    std::deque<std::pair<ReadSample, std::uint64_t>> held;  // exercise pins under load
    bool first = true;
    while (r.received() + r.drops() < total) {
      if (Clock::now() > deadline) {
        out.timed_out = true;
        break;
      }
      auto s = r.take();
      if (!s) {
        WaitToken t = r.arm();
        if (!r.has_data()) wait_any({&t, 1}, 200ms);
        r.disarm();
        continue;
      }
      std::uint64_t idx = 0;
      if (!check_message(s->data(), s->size(), &idx)) {
        ++out.torn;
        continue;
      }
      if ((!first && idx <= out.last) || idx != s->sequence()) ++out.disorder;
      first = false;
      out.last = idx;
      held.emplace_back(std::move(*s), idx);
      if (held.size() > keep) {
        std::uint64_t again = 0;
        const auto& h = held.front();
        if (!check_message(h.first.data(), h.first.size(), &again) || again != h.second) {
          ++out.pinned_changed;
        }
        held.pop_front();
      }
    }
    out.received = r.received();
    out.drops = r.drops();
  };
  std::thread t1([&] { run(*readers[0], res[0], 0); });
  std::thread t2([&] { run(*readers[1], res[1], 3); });
  down.send('G');
  t1.join();
  t2.join();
  down.send('Q');
  CHECK(exited_ok(c.wait(20s)));
  for (const auto& r : res) {
    INFO("received " << r.received << " drops " << r.drops);
    CHECK_FALSE(r.timed_out);
    CHECK(r.torn == 0);
    CHECK(r.disorder == 0);
    CHECK(r.pinned_changed == 0);
    CHECK(r.received + r.drops == total);
    CHECK(r.received > 0);
    CHECK(r.last == total - 1);
  }
}

// Keep last N across processes: a Writer child with keep = 3; the parent opens with a backlog
// before and after the child's growth.
TEST_CASE("keep: a Reader in another process gets the backlog and the carried messages once",
          "[shm][fork][keep]") {
  Watchdog wd(30s);
  const auto base = unique_base("xkeep");
  ShmGuard g(base);
  Pipe up, down;
  Child c([&] {
    WriterOptions o = opts(8);
    o.keep = 3;
    auto w = Writer::create(base, o);
    for (std::uint64_t i = 1; i <= 5; ++i) write_msg(w, i, 64);
    up.send('R');
    if (down.recv(10s) != 'G') return 10;
    write_msg(w, 6, 10000);  // > 4096-byte slots: generation 1 carries 3, 4, 5
    write_msg(w, 7, 64);
    if (w.segment_name() != base + "_g1" || w.published() != 7) return 12;
    up.send('W');
    if (down.recv(10s) != 'Q') return 11;
    return 0;
  });
  wd.watch_child(c.pid());
  REQUIRE(up.recv(10s) == 'R');

  // Takes messages until `want` arrived or the deadline passed (futex wait, no sleeps).
  auto collect = [](Reader& r, std::size_t want) {
    std::vector<std::uint64_t> got;
    const auto deadline = Clock::now() + 10s;
    while (got.size() < want && Clock::now() < deadline) {
      if (auto s = r.take()) {
        std::uint64_t idx = 0;
        REQUIRE(check_message(s->data(), s->size(), &idx));
        REQUIRE(s->intact());
        CHECK(s->sequence() == idx - 1);
        got.push_back(idx);
        continue;
      }
      WaitToken t = r.arm();
      if (!r.has_data()) wait_any({&t, 1}, 100ms);
      r.disarm();
    }
    return got;
  };
  using V = std::vector<std::uint64_t>;
  auto early = Reader::open(base, 3);
  CHECK(collect(early, 3) == V{3, 4, 5});
  down.send('G');
  REQUIRE(up.recv(10s) == 'W');
  CHECK(collect(early, 2) == V{6, 7});
  auto late = Reader::open(base, 4);
  CHECK(late.segment_name() == base + "_g1");
  CHECK(collect(late, 4) == V{4, 5, 6, 7});
  CHECK_FALSE(early.take().has_value());  // nothing twice
  CHECK_FALSE(late.take().has_value());
  CHECK(early.drops() == 0);
  CHECK(late.drops() == 0);
  down.send('Q');
  CHECK(exited_ok(c.wait(10s)));
}
