// Lifecycle and robustness of the core inside one process (issue 10): executor deadlines and
// faults, node identity in the executor's cache, Loans outliving or racing their publisher,
// waiting on more futex words than futex_waitv takes, default lease.
#include <unistd.h>

#include <atomic>
#include <catch2/catch.hpp>
#include <cstring>
#include <mutex>
#include <optional>
#include <thread>
#include <vector>

#include "core_support.hpp"
#include "lcmx/core.hpp"
#include "lcmx/shm/futex.hpp"

namespace {

using namespace std::chrono_literals;
using lcmx::core_test::eventually;
using lcmx::core_test::manual;
using lcmx::core_test::test_options;

std::string channel(const char* base) { return std::string(base) + "_" + std::to_string(::getpid()); }

}  // namespace

TEST_CASE("spin_once(timeout) returns when its deadline passes, whatever the moment", "[core][executor][lifecycle]") {
  // The deadline can pass between the executor's check and its wait; a negative wait means
  // "forever" to the futex layer. Many short timeouts hit that window.
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("m", manual());
  const auto ch = channel("SPIN_DEADLINE");
  auto pub = node.advertise_raw(ch);
  auto sub = node.subscribe_raw(ch, [](const lcmx::RawMessage&) {});
  std::atomic<bool> done{false};
  std::thread t([&] {
    for (int i = 0; i < 20000; ++i) node.spin_once(std::chrono::nanoseconds((i % 400) * 50));
    done = true;
  });
  const bool finished = eventually([&] { return done.load(); }, 10000ms);
  // A stuck spin_once is woken by a message, so the test ends either way.
  const std::byte b{1};
  while (!done.load()) {
    pub.publish({&b, 1});
    std::this_thread::yield();
  }
  t.join();
  CHECK(finished);
}

TEST_CASE("a node allocated where a destroyed one was gets its own callbacks run (executor cache keyed by id)",
          "[core][executor][lifecycle]") {
  auto rt = lcmx::Runtime::create(test_options());
  const auto ch = channel("NODE_ABA");
  int failures = 0;
  for (int attempt = 0; attempt < 30; ++attempt) {
    {
      // This thread's executor cache now holds node A: no subscriber, version 2.
      auto a = rt.create_node("a", manual());
      { auto s = a.subscribe_raw(ch + "_x", [](const lcmx::RawMessage&) {}); }
      a.spin_once(0ms);
    }
    auto filler = rt.create_node("filler", manual());  // frees A's memory (expired weak_ptr)
    auto b = rt.create_node("b", manual());              // often at A's address
    int got = 0;
    auto s1 = b.subscribe_raw(ch, [&](const lcmx::RawMessage&) { ++got; });
    auto s2 = b.subscribe_raw(ch + "_y", [](const lcmx::RawMessage&) {});  // version 2 too
    auto pub = b.advertise_raw(ch);
    const std::byte x{3};
    pub.publish({&x, 1});
    b.spin_once(200ms);
    if (got != 1) ++failures;
  }
  CHECK(failures == 0);
}

TEST_CASE("a Loan outliving its RawPublisher handle stays writable and is dropped safely", "[core][loan][lifecycle]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  const auto ch = channel("LOAN_OUTLIVES");
  std::optional<lcmx::RawPublisher> pub = node.advertise_raw(ch);
  lcmx::Loan loan = pub->loan(4096);
  REQUIRE(loan.capacity() >= 4096);
  pub.reset();  // the handle is gone; the Loan keeps the publisher and its memory
  std::memset(loan.data(), 0x5a, 4096);
  CHECK(std::to_integer<int>(loan.data()[4095]) == 0x5a);
  loan = lcmx::Loan{};  // dropped: nothing published, slot given back
  CHECK_FALSE(loan);
}

TEST_CASE("publish() while a Loan is out: another thread waits for it - the holder's thread gets a clear error",
          "[core][loan][lifecycle]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  const auto ch = channel("LOAN_RACE");
  std::mutex mu;
  std::vector<int> got;
  auto sub = node.subscribe_raw(ch, [&](const lcmx::RawMessage& m) {
    std::lock_guard lock(mu);
    got.push_back(std::to_integer<int>(m.data[0]));
  });
  auto pub = node.advertise_raw(ch);
  auto loan = pub.loan(8);
  loan.data()[0] = std::byte{1};

  // Same thread: it would wait for itself.
  const std::byte two{2};
  CHECK_THROWS_AS(pub.publish({&two, 1}), lcmx::Error);
  CHECK_THROWS_AS(pub.loan(8), lcmx::Error);

  // Another thread: waits until the loan is published, then publishes.
  std::atomic<bool> finished{false};
  std::string error;
  std::thread t([&] {
    try {
      pub.publish({&two, 1});
    } catch (const std::exception& e) {
      error = e.what();
    }
    finished = true;
  });
  // It must still be waiting (before the fix it threw at once).
  CHECK_FALSE(eventually([&] { return finished.load(); }, 300ms));
  pub.publish(std::move(loan), 1);
  t.join();
  CHECK(error.empty());
  REQUIRE(eventually([&] {
    std::lock_guard lock(mu);
    return got.size() == 2;
  }));
  std::lock_guard lock(mu);
  CHECK(got == std::vector<int>{1, 2});

  // A Loan is published only by its own publisher.
  auto other = node.advertise_raw(ch + "_other");
  auto l2 = other.loan(8);
  CHECK_THROWS_AS(pub.publish(std::move(l2), 1), lcmx::Error);
  CHECK(l2);  // left as it was
}

TEST_CASE("wait_any on more futex words than futex_waitv takes: a wake-up on any of them is seen",
          "[core][executor][lifecycle]") {
  constexpr std::size_t kWords = 200;
  std::vector<std::atomic<std::uint32_t>> words(kWords);
  std::vector<lcmx::shm::WaitToken> tokens;
  for (auto& w : words) tokens.push_back({&w, 0, /*process_private=*/true});
  for (std::size_t which : {std::size_t{0}, std::size_t{127}, std::size_t{128}, kWords - 1}) {
    for (auto& w : words) w.store(0);
    std::thread waker([&] {
      words[which].store(1);
      lcmx::shm::futex_wake_all_private(&words[which]);
    });
    const auto t0 = std::chrono::steady_clock::now();
    const auto r = lcmx::shm::wait_any(tokens, 5s);
    const auto took = std::chrono::steady_clock::now() - t0;
    waker.join();
    INFO("token " << which);
    CHECK(r == lcmx::shm::WaitResult::woken);
    CHECK(took < 2s);
  }
  // Nothing changes: the timeout holds.
  for (auto& w : words) w.store(0);
  CHECK(lcmx::shm::wait_any(tokens, 20ms) == lcmx::shm::WaitResult::timeout);
}

TEST_CASE("default lease across hosts is at most 1.5 s, with several beacons per lease", "[core][lifecycle]") {
  const lcmx::RuntimeOptions o;
  CHECK(o.lease <= 1500ms);
  CHECK(o.beacon_period * 2 < o.lease);
}
