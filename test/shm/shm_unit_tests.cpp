// lcmx::shm unit tests (single process). Label: unit.
#include <catch2/catch.hpp>

#include <array>
#include <cstring>
#include <deque>
#include <thread>

#include "lcmx/shm/detail/layout.hpp"
#include "lcmx/shm/futex.hpp"
#include "lcmx/shm/segment.hpp"
#include "test_util.hpp"

using namespace lcmx::shm;
using namespace lcmx::shm::test;

namespace {

std::uint64_t index_of(const ReadSample& s) {
  std::uint64_t idx = ~0ull;
  REQUIRE(check_message(s.data(), s.size(), &idx));
  return idx;
}

}  // namespace

TEST_CASE("write then read in order", "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("order");
  ShmGuard g(base);
  auto w = Writer::create(base, opts());
  CHECK(w.segment_name() == base + "_g0");
  auto r = Reader::open(w.segment_name());
  CHECK(w.live_readers() == 1);
  CHECK_FALSE(r.has_data());
  CHECK_FALSE(r.take().has_value());
  for (std::uint64_t i = 0; i < 5; ++i) CHECK(write_msg(w, i, 16 + i * 100) == i);
  CHECK(w.published() == 5);
  CHECK(r.has_data());
  for (std::uint64_t i = 0; i < 5; ++i) {
    auto s = r.take();
    REQUIRE(s);
    CHECK(s->sequence() == i);
    CHECK(s->size() == 16 + i * 100);
    CHECK(index_of(*s) == i);
  }
  CHECK_FALSE(r.take().has_value());
  CHECK_FALSE(r.has_data());
  CHECK(r.received() == 5);
  CHECK(r.drops() == 0);
  CHECK(r.writer_alive());
}

TEST_CASE("a Reader starts at the next commit, and open by base name works", "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("late");
  ShmGuard g(base);
  auto w = Writer::create(base, opts());
  write_msg(w, 0, 32);
  write_msg(w, 1, 32);
  auto r = Reader::open(base);  // base name: newest generation
  CHECK(r.segment_name() == base + "_g0");
  CHECK_FALSE(r.take().has_value());
  write_msg(w, 2, 32);
  auto s = r.take();
  REQUIRE(s);
  CHECK(index_of(*s) == 2);
  CHECK(s->sequence() == 2);
}

TEST_CASE("a lagging Reader counts exact drops and never sees a torn message", "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("lag");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8));
  auto r = Reader::open(w.segment_name());
  for (std::uint64_t i = 0; i < 50; ++i) write_msg(w, i, 16 + (i * 37) % 4000);
  std::uint64_t expect = 42;
  while (auto s = r.take()) {
    CHECK(index_of(*s) == expect);
    CHECK(s->sequence() == expect);
    ++expect;
  }
  CHECK(expect == 50);
  CHECK(r.received() == 8);
  CHECK(r.drops() == 42);
  // Interleaved: lag by slot_count + 3 twice more.
  for (int round = 0; round < 2; ++round) {
    for (std::uint64_t i = 0; i < 11; ++i) write_msg(w, 50 + round * 11 + i, 100);
    while (auto s = r.take()) index_of(*s);
  }
  CHECK(r.received() + r.drops() == 72);
  CHECK(r.drops() == 42 + 6);
}

TEST_CASE("pinned samples are never overwritten while held", "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("pin");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(6));
  auto r = Reader::open(w.segment_name());
  for (std::uint64_t i = 0; i < 4; ++i) write_msg(w, i, 2000);
  std::vector<ReadSample> held;
  for (int i = 0; i < Reader::kMaxPins; ++i) {
    auto s = r.take();
    REQUIRE(s);
    held.push_back(std::move(*s));
  }
  CHECK_THROWS_MATCHES(r.take(), Error,
                       Catch::Predicate<Error>([](const Error& e) {
                         return e.code() == Errc::invalid_argument;
                       }));
  // 4 of 6 slots pinned: the writer cycles through the 2 free ones.
  for (std::uint64_t i = 4; i < 100; ++i) write_msg(w, i, 1000 + i);
  for (std::uint64_t i = 0; i < 4; ++i) {
    CHECK(index_of(held[i]) == i);
    CHECK(held[i].size() == 2000);
  }
  held.clear();
  std::uint64_t last = 0;
  while (auto s = r.take()) last = index_of(*s);
  CHECK(last == 99);
  CHECK(r.received() + r.drops() == 100);
}

TEST_CASE("all slots pinned by a live Reader: the message is dropped and counted, then recovers",
          "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("allpin");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(2));
  auto r = Reader::open(w.segment_name());
  write_msg(w, 0, 64);
  write_msg(w, 1, 64);
  auto a = r.take();
  auto b = r.take();
  REQUIRE(a);
  REQUIRE(b);
  CHECK(write_msg(w, 2, 64) == 2);  // nowhere to write: dropped, counted, never thrown
  CHECK(w.dropped() == 1);
  CHECK(index_of(*a) == 0);
  CHECK(index_of(*b) == 1);
  a.reset();
  CHECK(write_msg(w, 3, 64) == 3);
  auto c = r.take();
  REQUIRE(c);
  CHECK(index_of(*c) == 3);
  CHECK(r.drops() == 1);  // the Reader counts the dropped message too
}

TEST_CASE("WriteLoan destroyed without commit publishes nothing", "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("abort");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(4));
  auto r = Reader::open(w.segment_name());
  {
    auto l = w.loan(100);
    CHECK(l.capacity() >= 100);
    std::memset(l.data(), 0xAB, 100);
    CHECK_THROWS_AS(w.loan(10), Error);  // one loan at a time
  }
  CHECK(w.published() == 0);
  CHECK_FALSE(r.has_data());
  CHECK_FALSE(r.take().has_value());
  {  // moved-from loans do not abort twice; the moved-to one aborts
    auto l = w.loan(10);
    auto l2 = std::move(l);
  }
  CHECK(write_msg(w, 0, 40) == 0);
  auto s = r.take();
  REQUIRE(s);
  CHECK(index_of(*s) == 0);
  CHECK(r.drops() == 0);
  // zero-copy loan + commit
  auto l = w.loan(64);
  fill_message(reinterpret_cast<unsigned char*>(l.data()), 64, 1);
  CHECK(w.commit(std::move(l), 64) == 1);
  auto s2 = r.take();
  REQUIRE(s2);
  CHECK(index_of(*s2) == 1);
}

TEST_CASE("growth across generations: a following Reader receives everything in order",
          "[shm]") {
  Watchdog wd(15s);
  const auto base = unique_base("grow");
  ShmGuard g(base);
  auto wo = opts(4);
  auto w = Writer::create(base, wo);
  auto r = Reader::open(w.segment_name());
  const std::size_t sizes[] = {100, 5000, 9000, 20000, 300000, 1 << 20};  // each grows
  std::uint64_t idx = 0;
  std::uint64_t got = 0;
  int gen = 0;
  for (std::size_t sz : sizes) {
    // 3 messages per size (< slot_count), the Reader reads only every other size: it must
    // follow generations containing messages published before it arrived.
    for (int k = 0; k < 3; ++k) write_msg(w, idx++, sz - k);
    if (sz > 4096) ++gen;
    CHECK(w.segment_name() == base + "_g" + std::to_string(gen));
    // Generations the Reader has not left yet keep their names.
    // (the Reader catches up at even generations): 1, 2, 3, 2, 3, 2
    CHECK(shm_names(base + "_g").size() == (gen == 0 ? 1u : gen % 2 ? 2u : 3u));
    if (gen % 2 == 0) {
      while (auto s = r.take()) CHECK(index_of(*s) == got++);
    }
  }
  while (auto s = r.take()) CHECK(index_of(*s) == got++);
  CHECK(got == idx);
  CHECK(r.drops() == 0);
  CHECK(r.received() == idx);
  CHECK(r.segment_name() == w.segment_name());
  CHECK(w.published() == idx);
  write_msg(w, idx++, 16);  // a commit releases the generations nobody uses any more
  CHECK(shm_names(base + "_g").size() == 1);
  REQUIRE(r.take());
  // A new Reader opening an old (unlinked) generation name lands on the newest.
  auto r2 = Reader::open(base + "_g0");
  CHECK(r2.segment_name() == w.segment_name());
  write_msg(w, idx, 16);
  auto s = r2.take();
  REQUIRE(s);
  CHECK(s->sequence() == idx);
}

TEST_CASE("a sample of an old generation stays valid after the Reader moved on", "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("oldpin");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(4));
  auto r = Reader::open(w.segment_name());
  write_msg(w, 0, 1000);
  auto old = r.take();
  REQUIRE(old);
  write_msg(w, 1, 10000);  // generation 1
  auto s = r.take();
  REQUIRE(s);
  CHECK(index_of(*s) == 1);
  CHECK(r.segment_name() == base + "_g1");
  CHECK(index_of(*old) == 0);
  old.reset();
  s.reset();
  CHECK(w.live_readers() == 1);
}

TEST_CASE("too_large, bad options and bad names", "[shm]") {
  const auto base = unique_base("large");
  ShmGuard g(base);
  auto wo = opts();
  wo.max_message_size = 10000;
  auto w = Writer::create(base, wo);
  CHECK_THROWS_MATCHES(w.loan(10001), Error, Catch::Predicate<Error>([](const Error& e) {
                         return e.code() == Errc::too_large;
                       }));
  auto l = w.loan(10000);  // exactly the bound: grows, fine
  CHECK(l.capacity() >= 10000);
  auto bad = [](const std::string& name, WriterOptions o) {
    try {
      Writer::create(name, o);
    } catch (const Error& e) {
      return e.code() == Errc::invalid_argument;
    }
    return false;
  };
  CHECK(bad("nope_" + base, opts()));
  CHECK(bad(base + "/x", opts()));
  auto o = opts();
  o.slot_count = 1;
  CHECK(bad(base + "x", o));
  o = opts();
  o.initial_slot_size = o.max_message_size + 1;
  CHECK(bad(base + "x", o));
  // Same name while the owner is alive: refused.
  CHECK_THROWS_MATCHES(Writer::create(base, opts()), Error,
                       Catch::Predicate<Error>([](const Error& e) {
                         return e.code() == Errc::system;
                       }));
}

TEST_CASE("open of a missing segment throws not_found", "[shm]") {
  const auto base = unique_base("missing");
  auto is = [](Errc c) {
    return Catch::Predicate<Error>([c](const Error& e) { return e.code() == c; });
  };
  CHECK_THROWS_MATCHES(Reader::open(base + "_g0"), Error, is(Errc::not_found));
  CHECK_THROWS_MATCHES(Reader::open(base), Error, is(Errc::not_found));
  CHECK_THROWS_MATCHES(Reader::open(""), Error, is(Errc::invalid_argument));
}

TEST_CASE("corrupt, foreign and truncated files: Error(corrupt), reclaim skips them",
          "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("corrupt");
  ShmGuard g(base);
  // A real segment image to damage.
  std::vector<unsigned char> image;
  {
    const auto src = unique_base("corruptsrc");
    ShmGuard gs(src);
    auto w = Writer::create(src, opts(4));
    write_msg(w, 0, 100);
    image = read_shm_file(w.segment_name());
  }
  REQUIRE(image.size() > 1024);
  std::vector<unsigned char> garbage(4096);
  for (std::size_t i = 0; i < garbage.size(); ++i) garbage[i] = static_cast<unsigned char>(i * 7);
  auto hostile = image;  // valid magic, absurd slot_count
  auto* h = reinterpret_cast<lcmx::shm::detail::SegmentHeader*>(hostile.data());
  h->slot_count = 0xFFFFFFFFu;
  auto hostile2 = image;  // consistent-looking but huge slot size: total > file
  auto* h2 = reinterpret_cast<lcmx::shm::detail::SegmentHeader*>(hostile2.data());
  h2->slot_size = 1ull << 30;
  h2->total_size = lcmx::shm::detail::make_geometry(h2->slot_count, h2->max_subscribers,
                                                    h2->slot_size).total_size;
  struct Case {
    std::string name;
    std::vector<unsigned char> bytes;
  };
  std::vector<Case> cases = {
      {base + "_empty_g0", {}},
      {base + "_tiny_g0", std::vector<unsigned char>(10, 0x4c)},
      {base + "_foreign_g0", garbage},
      {base + "_trunc_g0", std::vector<unsigned char>(image.begin(), image.begin() + 512)},
      {base + "_hostile_g0", hostile},
      {base + "_hostile2_g0", hostile2},
  };
  for (const auto& c : cases) write_shm_file(c.name, c.bytes.data(), c.bytes.size());
  for (const auto& c : cases) {
    INFO(c.name);
    CHECK_THROWS_MATCHES(Reader::open(c.name), Error, Catch::Predicate<Error>([](const Error& e) {
                           return e.code() == Errc::corrupt;
                         }));
  }
  auto rep = reclaim_orphans(base);
  CHECK(rep.removed == 0);
  CHECK(rep.skipped == cases.size());
  for (const auto& c : cases) CHECK(shm_exists(c.name));
}

TEST_CASE("reclaim leaves a live Writer's segment alone", "[shm]") {
  const auto base = unique_base("live");
  ShmGuard g(base);
  auto w = Writer::create(base, opts());
  auto rep = reclaim_orphans(base);
  CHECK(rep.removed == 0);
  CHECK(rep.skipped == 0);
  CHECK(shm_exists(w.segment_name()));
}

TEST_CASE("a second Writer of a live base is refused, with WriterOptions::unique_base at generation 0",
          "[shm]") {
  const auto base = unique_base("twice");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(4));
  auto vouched = opts(4);
  vouched.unique_base = true;
  CHECK_THROWS_AS(Writer::create(base, opts(4)), Error);
  CHECK_THROWS_AS(Writer::create(base, vouched), Error);  // O_EXCL and the live owner's lock
  // Grown to generation 1, no Reader: generation 0 is gone, only the scan of /dev/shm finds
  // the live Writer (the check unique_base skips: its caller's names cannot collide).
  write_msg(w, 0, 10000);
  REQUIRE(w.segment_name() == base + "_g1");
  REQUIRE(shm_names(base + "_g") == std::vector<std::string>{base + "_g1"});
  try {
    (void)Writer::create(base, opts(4));
    FAIL("a live Writer at a later generation was not found");
  } catch (const Error& e) {
    CHECK(std::string(e.what()).find("in use by a live Writer") != std::string::npos);
  }
  CHECK(shm_names(base + "_g") == std::vector<std::string>{base + "_g1"});
}

TEST_CASE("Writer destruction unlinks, Readers keep their mapping", "[shm]") {
  const auto base = unique_base("close");
  ShmGuard g(base);
  std::optional<Writer> w = Writer::create(base, opts());
  auto r = Reader::open(w->segment_name());
  write_msg(*w, 0, 300);
  const std::string name = w->segment_name();
  w.reset();
  CHECK_FALSE(shm_exists(name));
  CHECK_FALSE(r.writer_alive());
  auto s = r.take();
  REQUIRE(s);
  CHECK(index_of(*s) == 0);
  CHECK_FALSE(r.has_data());
}

TEST_CASE("wait_any: idle wait times out and costs no CPU", "[shm][futex]") {
  Watchdog wd(10s);
  const auto base = unique_base("idle");
  ShmGuard g(base);
  auto w = Writer::create(base, opts());
  auto r = Reader::open(w.segment_name());
  WaitToken t = r.arm();
  REQUIRE_FALSE(r.has_data());
  const double cpu0 = thread_cpu_ms();
  const auto t0 = Clock::now();
  CHECK(wait_any({&t, 1}, 200ms) == WaitResult::timeout);
  const auto elapsed = Clock::now() - t0;
  const double cpu = thread_cpu_ms() - cpu0;
  r.disarm();
  CHECK(elapsed >= 190ms);
  CHECK(cpu < 10.0);  // blocked in the kernel, not polling
}

TEST_CASE("wait_any wakes a waiting thread on commit (one and several tokens)",
          "[shm][futex]") {
  Watchdog wd(20s);
  const auto b1 = unique_base("wake1");
  const auto b2 = unique_base("wake2");
  ShmGuard g1(b1), g2(b2);
  auto w1 = Writer::create(b1, opts());
  auto w2 = Writer::create(b2, opts());
  auto r1 = Reader::open(w1.segment_name());
  auto r2 = Reader::open(w2.segment_name());
  for (int several = 0; several < 2; ++several) {
    std::atomic<int> state{0};  // 1: armed and about to wait; 2: woke with data
    std::thread waiter([&] {
      std::array<WaitToken, 2> t{r1.arm(), r2.arm()};
      state.store(1);
      const auto deadline = Clock::now() + 10s;
      while (!r1.has_data() && !r2.has_data() && Clock::now() < deadline) {
        wait_any({t.data(), several ? 2u : 1u}, 1s);
      }
      r1.disarm();
      r2.disarm();
      state.store(r1.has_data() || r2.has_data() ? 2 : 3);
    });
    while (state.load() == 0) std::this_thread::yield();
    (several ? w2 : w1).write("x", 1);
    waiter.join();
    CHECK(state.load() == 2);
    while (r1.take()) {
    }
    while (r2.take()) {
    }
  }
  // Two tokens, nothing published: times out.
  std::array<WaitToken, 2> t{r1.arm(), r2.arm()};
  CHECK(wait_any(t, 50ms) == WaitResult::timeout);
  r1.disarm();
  r2.disarm();
  INFO("futex_waitv supported: " << futex_waitv_supported());
  CHECK_THROWS_AS(wait_any({}, 1ms), Error);
}

TEST_CASE("a Reader re-armed without disarming is woken by every later commit",
          "[shm][futex]") {
  Watchdog wd(20s);
  const auto base = unique_base("rearm");
  ShmGuard g(base);
  auto w = Writer::create(base, opts());
  auto r = Reader::open(w.segment_name());
  for (int round = 0; round < 20; ++round) {
    std::atomic<int> state{0};  // 1: (re-)armed and about to wait; 2: woke with data
    std::thread waiter([&] {
      WaitToken t = r.arm();  // still armed from the previous round
      state.store(1);
      const auto deadline = Clock::now() + 10s;
      while (!r.has_data() && Clock::now() < deadline) {
        wait_any({&t, 1}, 1s);
        t = r.arm();
      }
      state.store(r.has_data() ? 2 : 3);  // no disarm: stays armed into the next round
    });
    while (state.load() == 0) std::this_thread::yield();
    w.write("x", 1);
    waiter.join();
    CHECK(state.load() == 2);
    while (r.take()) {
    }
  }
  r.disarm();
  r.disarm();  // idempotent
}

TEST_CASE("process-private futex words: wait_any and futex_wake_all_private", "[shm][futex]") {
  Watchdog wd(20s);
  std::atomic<std::uint32_t> word{0}, other{0};
  std::atomic<int> state{0};
  std::thread waiter([&] {
    std::array<WaitToken, 2> t{WaitToken{&other, 0, true}, WaitToken{&word, 0, true}};
    state.store(1);
    const auto deadline = Clock::now() + 10s;
    while (word.load() == 0 && Clock::now() < deadline) wait_any({t.data(), 2u}, 1s);
    state.store(word.load() != 0 ? 2 : 3);
  });
  while (state.load() == 0) std::this_thread::yield();
  word.store(1);
  futex_wake_all_private(&word);
  waiter.join();
  CHECK(state.load() == 2);
  WaitToken one{&word, 1, true};
  CHECK(wait_any({&one, 1}, 50ms) == WaitResult::timeout);
}

TEST_CASE("a Writer growing wakes Readers sleeping on the old generation", "[shm][futex]") {
  Watchdog wd(10s);
  const auto base = unique_base("growwake");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(4));
  auto r = Reader::open(w.segment_name());
  WaitToken t = r.arm();
  REQUIRE_FALSE(r.has_data());
  std::vector<unsigned char> big(9000);
  fill_message(big.data(), big.size(), 0);
  w.write(big.data(), big.size());  // moves to generation 1
  CHECK(wait_any({&t, 1}, 5s) == WaitResult::woken);
  r.disarm();
  CHECK(r.has_data());
  auto s = r.take();
  REQUIRE(s);
  CHECK(index_of(*s) == 0);
  CHECK(r.segment_name() == base + "_g1");
}

TEST_CASE("two threads: writer and reader, no torn reads", "[shm]") {
  Watchdog wd(30s);
  const auto base = unique_base("threads");
  ShmGuard g(base);
  auto wo = opts(8);
  auto w = Writer::create(base, wo);
  auto r = Reader::open(w.segment_name());
  const std::uint64_t total = kSanitized ? 3000 : 20000;
  std::thread writer([&] {
    std::vector<unsigned char> buf(20000);
    for (std::uint64_t i = 0; i < total; ++i) {
      const std::size_t sz = 16 + (i * 7919) % (i < total / 2 ? 4000 : 16000);
      fill_message(buf.data(), sz, i);
      w.write(buf.data(), sz);
    }
  });
  std::uint64_t last = 0;
  bool first = true, torn = false, order = true;
  const auto deadline = Clock::now() + 25s;
  while (r.received() + r.drops() < total && Clock::now() < deadline) {
    if (auto s = r.take()) {
      std::uint64_t idx = 0;
      if (!check_message(s->data(), s->size(), &idx)) torn = true;
      if (!first && idx <= last) order = false;
      if (idx != s->sequence()) order = false;
      last = idx;
      first = false;
      continue;
    }
    WaitToken t = r.arm();
    if (!r.has_data()) wait_any({&t, 1}, 100ms);
    r.disarm();
  }
  writer.join();
  CHECK_FALSE(torn);
  CHECK(order);
  CHECK(r.received() + r.drops() == total);
  CHECK(r.received() > 0);
}

TEST_CASE("tampered descriptors and sizes are dropped, never read out of bounds", "[shm]") {
  Watchdog wd(10s);
  const auto base = unique_base("tamper");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(4));
  auto r = Reader::open(w.segment_name());
  write_msg(w, 0, 100);
  write_msg(w, 1, 100);
  write_msg(w, 2, 100);
  {
    namespace d = lcmx::shm::detail;
    int fd = ::shm_open(("/" + w.segment_name()).c_str(), O_RDWR, 0);
    REQUIRE(fd >= 0);
    const auto geo = d::make_geometry(4, 8, 4096);
    void* m = ::mmap(nullptr, geo.total_size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    ::close(fd);
    REQUIRE(m != MAP_FAILED);
    auto* b = static_cast<std::byte*>(m);
    auto* desc = reinterpret_cast<std::atomic<std::uint64_t>*>(b + geo.desc_offset);
    auto slot = [&](std::uint32_t i) {
      return reinterpret_cast<d::SlotHeader*>(b + geo.slots_offset + i * geo.slot_stride);
    };
    desc[0].store(d::pack_desc(0, 60000));  // slot index out of range
    slot(1)->size = std::uint64_t{1} << 40; // size larger than the slot
    ::munmap(m, geo.total_size);
  }
  auto s = r.take();
  REQUIRE(s);
  CHECK(index_of(*s) == 2);
  CHECK(r.drops() == 2);
  CHECK(r.received() == 1);
}

// The Writer's per-message bits (Writer::commit's `flags`; the core stamps a message's class
// there for the Message Bridges): read back with the message, also by a late Reader of a kept
// message carried into a larger generation.
TEST_CASE("per-message flags: read with the message, carried into a new generation", "[shm][keep]") {
  Watchdog wd(15s);
  const auto base = unique_base("flags");
  ShmGuard g(base);
  WriterOptions o = opts(8);
  o.keep = 2;
  auto w = Writer::create(base, o);
  auto r = Reader::open(w.segment_name());
  std::vector<unsigned char> msg(64, 7);
  w.write(msg.data(), msg.size(), 3);
  w.write(msg.data(), msg.size());  // none
  auto l = w.loan(64);
  std::memcpy(l.data(), msg.data(), 64);
  w.commit(std::move(l), 64, 2);
  for (std::uint64_t want : {3u, 0u, 2u}) {
    auto s = r.take();
    REQUIRE(s);
    CHECK(s->flags() == want);
    auto moved = std::move(*s);
    CHECK(moved.flags() == want);
  }
  // A larger message moves the Writer to a new generation carrying the last 2: their flags too.
  std::vector<unsigned char> big(1 << 16, 9);
  w.write(big.data(), big.size(), 1);
  auto late = Reader::open(base, 2);
  std::vector<std::uint64_t> seen;
  while (auto s = late.take()) seen.push_back(s->flags());
  CHECK(seen == std::vector<std::uint64_t>{2, 1});
}
