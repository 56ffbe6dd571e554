// ReadSample::detach / DetachedSample (issue 15 item 1: zero-copy hand-off of a pinned
// sample to another thread, e.g. ZeroMQ's I/O thread). Label: unit (built into
// lcmx_shm_tests, so scripts/tsan.sh -R shm/ covers the cross-thread release).
#include <catch2/catch.hpp>

#include <condition_variable>
#include <deque>
#include <mutex>
#include <optional>
#include <thread>
#include <vector>

#include "lcmx/shm/segment.hpp"
#include "test_util.hpp"

using namespace lcmx::shm;
using namespace lcmx::shm::test;

namespace {

template <class S>
std::uint64_t index_of_sample(const S& s) {
  std::uint64_t idx = ~0ull;
  REQUIRE(check_message(s.data(), s.size(), &idx));
  return idx;
}

}  // namespace

TEST_CASE("detach: kMaxDetached samples at most, one pin always left for take()",
          "[shm][detach]") {
  Watchdog wd(10s);
  const auto base = unique_base("detach_max");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8));
  auto r = Reader::open(w.segment_name());
  for (std::uint64_t i = 0; i < 6; ++i) write_msg(w, i, 3000);
  std::vector<DetachedSample> held;
  for (int i = 0; i < Reader::kMaxDetached; ++i) {
    auto s = r.take();
    REQUIRE(s);
    auto d = s->detach();
    REQUIRE(d);
    CHECK_FALSE(s->intact());  // *this is empty after a successful detach
    CHECK(d->intact());
    held.push_back(std::move(*d));
  }
  CHECK(r.detached() == Reader::kMaxDetached);
  // The last pin: take() still works; detaching it is refused and leaves it usable.
  auto s = r.take();
  REQUIRE(s);
  CHECK_FALSE(s->detach());
  CHECK(r.detach_refused() == 1);
  CHECK(s->intact());
  CHECK(index_of_sample(*s) == 3);
  // Every pin in use (3 detached + 1 sample): take() refuses clearly.
  CHECK_THROWS_AS(r.take(), Error);
  s.reset();
  // Releasing a detached sample gives its pin back to take() and to detach().
  for (std::uint64_t i = 0; i < held.size(); ++i) CHECK(index_of_sample(held[i]) == i);
  held.erase(held.begin());
  CHECK(r.detached() == Reader::kMaxDetached - 1);
  auto s2 = r.take();
  REQUIRE(s2);
  CHECK(index_of_sample(*s2) == 4);
  auto d2 = s2->detach();
  REQUIRE(d2);
  CHECK(r.detached() == Reader::kMaxDetached);
  d2.reset();
  held.clear();
  CHECK(r.detached() == 0);
  CHECK(w.dropped() == 0);
}

TEST_CASE("detached samples released on another thread while the owner keeps taking",
          "[shm][detach]") {
  Watchdog wd(60s);
  const auto base = unique_base("detach_mt");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8));
  auto r = Reader::open(w.segment_name());
  constexpr std::uint64_t kMessages = kSanitized ? 2000 : 20000;
  std::mutex mu;
  std::condition_variable cv;
  std::deque<DetachedSample> queue;
  bool done = false;
  std::uint64_t released = 0, bad = 0;
  // The "I/O thread": checks each message on its own thread, then destroys it there.
  std::thread io([&] {
    for (;;) {
      std::optional<DetachedSample> d;
      {
        std::unique_lock lock(mu);
        cv.wait(lock, [&] { return done || !queue.empty(); });
        if (queue.empty()) return;
        d.emplace(std::move(queue.front()));
        queue.pop_front();
      }
      std::uint64_t idx = 0;
      // The payload is the guarantee (intact() may see a Writer probe of this slot that was
      // preempted for longer than its bounded re-check: conservative, never a false "intact").
      if (!check_message(d->data(), d->size(), &idx)) ++bad;
      d.reset();  // the release under test: kPinFree store + ledger bit, on this thread
      ++released;
    }
  });
  std::uint64_t next = 0, zero_copy = 0, copied = 0;
  std::vector<std::byte> copy;
  for (std::uint64_t i = 0; i < kMessages; ++i) {
    write_msg(w, i, 512 + i % 3000);
    auto s = r.take();
    REQUIRE(s);
    CHECK(index_of_sample(*s) == next++);
    if (auto d = s->detach()) {
      ++zero_copy;
      std::lock_guard lock(mu);
      queue.push_back(std::move(*d));
      cv.notify_one();
    } else {
      ++copied;  // the fallback a bridge takes: copy, and the pin goes back at once
      copy.assign(s->data(), s->data() + s->size());
      CHECK(s->intact());
    }
  }
  {
    std::lock_guard lock(mu);
    done = true;
  }
  cv.notify_one();
  io.join();
  CHECK(bad == 0);
  CHECK(released == zero_copy);
  CHECK(zero_copy + copied == kMessages);
  CHECK(copied == r.detach_refused());
  CHECK(zero_copy > 0);
  CHECK(r.detached() == 0);
  CHECK(r.drops() == 0);
  // One Reader holds at most kMaxPins slots of 8: the Writer never ran out.
  CHECK(w.dropped() == 0);
}

TEST_CASE("a slow holder of detached samples: the Writer never blocks, drops are counted",
          "[shm][detach]") {
  Watchdog wd(10s);
  const auto base = unique_base("detach_slow");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(4));  // fewer slots than pins: the Writer can starve
  auto r = Reader::open(w.segment_name());
  for (std::uint64_t i = 0; i < 4; ++i) write_msg(w, i, 100);
  std::vector<DetachedSample> held;
  for (int i = 0; i < Reader::kMaxDetached; ++i) {
    auto s = r.take();
    REQUIRE(s);
    held.push_back(std::move(*s->detach()));
  }
  auto last = r.take();
  REQUIRE(last);
  // Every slot pinned: commits return at once, dropped and counted (never blocked).
  const auto t0 = Clock::now();
  for (std::uint64_t i = 4; i < 104; ++i) write_msg(w, i, 100);
  CHECK(Clock::now() - t0 < 5s);
  CHECK(w.dropped() == 100);
  last.reset();
  CHECK_FALSE(r.take());  // the 100 dropped messages were never in a slot
  CHECK(r.drops() == 100);
  // One holder releases (on another thread): the Writer publishes again.
  std::thread([d = std::move(held.back())]() mutable { DetachedSample x = std::move(d); }).join();
  held.pop_back();
  write_msg(w, 104, 100);
  CHECK(w.dropped() == 100);
  auto s = r.take();
  REQUIRE(s);
  CHECK(index_of_sample(*s) == 104);
  for (std::uint64_t i = 0; i < held.size(); ++i) CHECK(index_of_sample(held[i]) == i);
}

TEST_CASE("a detached sample outlives its Reader and keeps its slot pinned", "[shm][detach]") {
  Watchdog wd(10s);
  const auto base = unique_base("detach_outlive");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(2));
  std::optional<DetachedSample> d;
  {
    auto r = Reader::open(w.segment_name());
    write_msg(w, 7, 2500);
    auto s = r.take();
    REQUIRE(s);
    d = s->detach();
    REQUIRE(d);
  }  // the Reader is gone; its registration stays while the sample lives
  CHECK(w.registered_readers() == 1);
  // The pinned slot is skipped: with 2 slots every later message goes to the other one.
  for (std::uint64_t i = 0; i < 10; ++i) write_msg(w, 100 + i, 4000);
  CHECK(w.dropped() == 0);
  CHECK(d->intact());
  CHECK(index_of_sample(*d) == 7);
  d.reset();
  CHECK(w.registered_readers() == 0);
}

TEST_CASE("a detached sample stays valid across a generation change and the Writer's exit",
          "[shm][detach]") {
  Watchdog wd(10s);
  const auto base = unique_base("detach_gen");
  ShmGuard g(base);
  std::optional<DetachedSample> d;
  {
    auto w = Writer::create(base, opts(4));
    auto r = Reader::open(w.segment_name());
    write_msg(w, 1, 1000);
    auto s = r.take();
    REQUIRE(s);
    d = s->detach();
    REQUIRE(d);
    s.reset();
    write_msg(w, 2, 100000);  // generation 1
    write_msg(w, 3, 200000);  // generation 2
    for (std::uint64_t i = 4; i < 20; ++i) write_msg(w, i, 200000);
    std::uint64_t last = 0;
    while (auto t = r.take()) {  // the ring lapped the Reader: increasing, not contiguous
      const auto idx = index_of_sample(*t);
      CHECK(idx > last);
      last = idx;
    }
    CHECK(last == 19);
    CHECK(r.segment_name() == base + "_g2");
    CHECK(index_of_sample(*d) == 1);
    CHECK(d->intact());
    // The Reader has left generation 0; the sample still holds its entry there.
    CHECK(shm_exists(base + "_g0"));
  }  // Writer and Reader gone
  CHECK(d->size() == 1000);
  CHECK(index_of_sample(*d) == 1);
  CHECK(d->intact());
  d.reset();  // last holder: unmaps, deregisters, removes what the closed Writer left
  CHECK(shm_names(base).empty());
}
