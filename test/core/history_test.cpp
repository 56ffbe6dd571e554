// Keep last N (PublisherOptions::history; docs/ARCHITECTURE.md "Keep last N") in one process
// (in-process subscribers). Across processes: test/integration; across hosts: test/multihost
// and test/bridge.
#include <catch2/catch.hpp>

#include <atomic>
#include <cstring>
#include <fstream>
#include <mutex>
#include <set>
#include <thread>
#include <vector>

#include "core_support.hpp"
#include "lcmx/udpm/udpm.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "lcmx_msgs/history_t.hpp"

using namespace lcmx::core_test;

namespace {

// Raw messages: 8 bytes of sequence number, then `size - 8` bytes of a pattern.
std::vector<std::byte> raw(std::int64_t seq, std::size_t size = 64) {
  std::vector<std::byte> b(std::max<std::size_t>(size, 8));
  std::memcpy(b.data(), &seq, 8);
  for (std::size_t i = 8; i < b.size(); ++i) b[i] = static_cast<std::byte>((i * 31 + static_cast<std::size_t>(seq)) & 0xff);
  return b;
}

std::int64_t raw_seq(std::span<const std::byte> b) {
  std::int64_t s = -1;
  if (b.size() >= 8) std::memcpy(&s, b.data(), 8);
  return s;
}

bool raw_ok(std::span<const std::byte> b) {
  const auto want = raw(raw_seq(b), b.size());
  return std::equal(b.begin(), b.end(), want.begin(), want.end());
}

// What a subscriber got, from any thread.
struct Seen {
  std::mutex mu;
  std::vector<std::int64_t> seqs;
  bool bad = false;
  void add(std::int64_t s, bool ok = true) {
    std::lock_guard lock(mu);
    seqs.push_back(s);
    bad = bad || !ok;
  }
  std::vector<std::int64_t> get() {
    std::lock_guard lock(mu);
    return seqs;
  }
  std::size_t size() {
    std::lock_guard lock(mu);
    return seqs.size();
  }
};

std::vector<std::int64_t> range(std::int64_t from, std::int64_t to) {  // [from, to)
  std::vector<std::int64_t> v;
  for (auto i = from; i < to; ++i) v.push_back(i);
  return v;
}

}  // namespace

TEST_CASE("keep last N, in-process: a late subscriber gets the last N first, then live ones, once", "[core][history]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n", manual());
  lcmx::PublisherOptions po;
  po.history = 3;
  auto pub = node.advertise<lcmx_examples::pose_t>("HIST_INTRA", po);
  for (int i = 0; i < 5; ++i) pub.publish(pose(i));
  Seen typed, bytes;
  auto s1 = node.subscribe<lcmx_examples::pose_t>("HIST_INTRA", [&](const lcmx_examples::pose_t& p) {
    typed.add(static_cast<std::int64_t>(p.position[0]));
  });
  // A raw subscriber gets the kept messages encoded.
  auto s2 = node.subscribe_raw("HIST_INTRA", [&](const lcmx::RawMessage& m) {
    lcmx_examples::pose_t p;
    const bool ok = p.decode(m.data.data(), 0, static_cast<int>(m.data.size())) >= 0;
    bytes.add(ok ? static_cast<std::int64_t>(p.position[0]) : -1, ok);
  });
  while (node.spin_once(0ms) > 0) {
  }
  CHECK(typed.get() == std::vector<std::int64_t>{2, 3, 4});
  CHECK(bytes.get() == std::vector<std::int64_t>{2, 3, 4});
  for (int i = 5; i < 8; ++i) pub.publish(pose(i));
  while (node.spin_once(0ms) > 0) {
  }
  CHECK(typed.get() == range(2, 8));
  CHECK(bytes.get() == range(2, 8));
  CHECK_FALSE(bytes.bad);
  // Fewer published than kept: all of them.
  po.history = 10;
  auto pub2 = node.advertise_raw("HIST_INTRA_RAW", po);
  for (int i = 0; i < 4; ++i) pub2.publish(raw(i));
  Seen late;
  auto s3 = node.subscribe_raw("HIST_INTRA_RAW", [&](const lcmx::RawMessage& m) { late.add(raw_seq(m.data), raw_ok(m.data)); });
  while (node.spin_once(0ms) > 0) {
  }
  CHECK(late.get() == range(0, 4));
  CHECK_FALSE(late.bad);
}

TEST_CASE("keep last N: history 0 is volatile, more than kMaxHistory is refused, shm_slots is raised to fit",
          "[core][history][errors]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n", manual());
  auto pub = node.advertise<lcmx_examples::pose_t>("HIST_NONE");
  for (int i = 0; i < 5; ++i) pub.publish(pose(i));
  Seen seen;
  auto s = node.subscribe<lcmx_examples::pose_t>("HIST_NONE", [&](const lcmx_examples::pose_t& p) {
    seen.add(static_cast<std::int64_t>(p.position[0]));
  });
  while (node.spin_once(0ms) > 0) {
  }
  CHECK(seen.size() == 0);
  lcmx::PublisherOptions po;
  po.history = lcmx::PublisherOptions::kMaxHistory + 1;
  try {
    (void)node.advertise_raw("HIST_TOO_MANY", po);
    FAIL("no error");
  } catch (const lcmx::Error& e) {
    CHECK(e.code() == lcmx::Errc::invalid_argument);
    CHECK(std::string(e.what()).find("history") != std::string::npos);
  }
  po.history = 20;  // > shm_slots (8): raised to 21
  po.shm_slots = 8;
  CHECK_NOTHROW(node.advertise_raw("HIST_MANY", po));
}

TEST_CASE("keep last N, in-process: subscribers joining while a thread publishes get every message once, in order",
          "[core][history]") {
  auto rt = lcmx::Runtime::create(test_options());
  auto node = rt.create_node("n");
  lcmx::PublisherOptions po;
  po.history = 5;
  auto pub = node.advertise_raw("HIST_RACE", po);
  std::atomic<bool> stop{false};
  std::atomic<std::int64_t> published{0};
  std::thread t([&] {
    for (std::int64_t i = 0; !stop.load() && i < 2'000'000; ++i) {
      pub.publish(raw(i, 16));
      published.store(i + 1);
    }
  });
  lcmx::SubscriberOptions so;
  so.queue_depth = 1 << 20;  // every message counts: no queue drops
  std::vector<std::unique_ptr<Seen>> seen;
  std::vector<lcmx::RawSubscriber> subs;
  for (int k = 0; k < 8; ++k) {
    REQUIRE(eventually([&] { return published.load() > (k + 1) * 200; }, 5s));
    seen.push_back(std::make_unique<Seen>());
    Seen* s = seen.back().get();
    subs.push_back(node.subscribe_raw("HIST_RACE", [s](const lcmx::RawMessage& m) { s->add(raw_seq(m.data), raw_ok(m.data)); }, so));
  }
  REQUIRE(eventually([&] { return published.load() > 10'000; }, 10s));
  stop = true;
  t.join();
  const auto n = published.load();
  for (std::size_t k = 0; k < seen.size(); ++k) {
    REQUIRE(eventually([&] { auto g = seen[k]->get(); return !g.empty() && g.back() == n - 1; }, 5s));
    const auto got = seen[k]->get();
    INFO("subscriber " << k << " got " << got.size() << " from " << got.front());
    CHECK(got == range(got.front(), n));  // contiguous: nothing twice, nothing lost
    CHECK(got.size() >= 5);
    CHECK_FALSE(seen[k]->bad);
  }
}

// This process's peak resident set (VmHWM), in KiB.
static long peak_rss_kib() {
  std::ifstream in("/proc/self/status");
  std::string key;
  while (in >> key) {
    if (key == "VmHWM:") {
      long kib = 0;
      in >> kib;
      return kib;
    }
    std::getline(in, key);
  }
  return -1;
}

// Issue 34: twenty 70-byte LCMX_HISTORY datagrams took a subscriber to 1.29 GB peak RSS (the
// replay's lcm-gen decode sized its vector to the count first). Every runtime reads the
// replays of its groups before it looks at whom they are for.
TEST_CASE("keep last N over UDP: replay datagrams whose count says 50,000,000 messages allocate nothing",
          "[core][history][trust]") {
  auto opts = test_options();
  auto rt = lcmx::Runtime::create(opts);
  auto node = rt.create_node("bomb", manual());
  std::atomic<int> after{0};
  auto sub = node.subscribe_raw("HISTORY_BOMB_AFTER", [&](const lcmx::RawMessage&) { ++after; });
  // A sender on the host-local group that is no participant (its datagrams are handled in
  // the order they were sent).
  auto stock = lcmx::udpm::Group::open(lcmx::udpm::parse_url(opts.discovery_url));
  lcmx_msgs::history_t h{};
  h.publisher_participant = 1;
  h.subscriber_participant = static_cast<std::int64_t>(rt.participant_id());
  h.channel = "POSE";
  h.num_messages = 0;
  std::vector<std::byte> bomb(static_cast<std::size_t>(h.getEncodedSize()));
  h.encode(bomb.data(), 0, static_cast<int>(bomb.size()));
  const std::uint32_t count = 50000000;  // num_messages, the last field written
  for (int i = 0; i < 4; ++i) bomb[bomb.size() - 4 + i] = static_cast<std::byte>(count >> (24 - 8 * i));
  bomb.resize(70, std::byte{0x41});
  const long before = peak_rss_kib();
  REQUIRE(before > 0);
  for (int i = 0; i < 20; ++i) stock.publish("LCMX_HISTORY", bomb);  // core/src: kHistoryChannel
  const std::vector<std::byte> marker(8, std::byte{1});
  stock.publish("HISTORY_BOMB_AFTER", marker);  // arrives after the twenty: they were handled
  REQUIRE(eventually([&] {
    node.spin_once(5ms);
    return after.load() >= 1;
  }));
  INFO("peak RSS before " << before << " KiB, after " << peak_rss_kib() << " KiB");
  CHECK(peak_rss_kib() - before < 64 * 1024);
}
