// lcmx::shm "keep last N" (WriterOptions::keep) and Reader::open's backlog, single process.
// Label: unit. (The cross-process case is in shm_integration_tests.cpp.)
#include <catch2/catch.hpp>

#include <cstring>
#include <vector>

#include "lcmx/shm/detail/layout.hpp"
#include "lcmx/shm/segment.hpp"
#include "test_util.hpp"

using namespace lcmx::shm;
using namespace lcmx::shm::test;

namespace {

WriterOptions keep_opts(std::uint32_t keep, std::uint32_t slots = 8) {
  WriterOptions o = opts(slots);
  o.keep = keep;
  return o;
}

struct Got {
  std::uint64_t index = 0;     // fill_message index (checksum verified)
  std::uint64_t sequence = 0;  // ReadSample::sequence()
  std::size_t size = 0;
};

// Takes every message available now (no waiting: single process, the writes are done).
std::vector<Got> drain(Reader& r) {
  std::vector<Got> out;
  while (auto s = r.take()) {
    Got g;
    REQUIRE(check_message(s->data(), s->size(), &g.index));
    REQUIRE(s->intact());
    g.sequence = s->sequence();
    g.size = s->size();
    out.push_back(g);
  }
  return out;
}

std::vector<std::uint64_t> indices(const std::vector<Got>& v) {
  std::vector<std::uint64_t> out;
  for (const auto& g : v) out.push_back(g.index);
  return out;
}

using V = std::vector<std::uint64_t>;

}  // namespace

TEST_CASE("keep: a Reader opened with a backlog gets the last messages, then new ones, once",
          "[shm][keep]") {
  Watchdog wd(10s);
  const auto base = unique_base("backlog");
  ShmGuard g(base);
  auto w = Writer::create(base, keep_opts(3, 8));
  for (std::uint64_t i = 1; i <= 5; ++i) CHECK(write_msg(w, i, 64) == i - 1);

  auto r3 = Reader::open(base, 3);
  auto r0 = Reader::open(base, 0);
  auto r0_default = Reader::open(base + "_g0");
  auto rbig = Reader::open(base, 100);  // more than written: everything written
  CHECK(r3.has_data());
  CHECK_FALSE(r0.has_data());

  auto got3 = drain(r3);
  CHECK(indices(got3) == V{3, 4, 5});
  for (const auto& x : got3) {
    CHECK(x.sequence == x.index - 1);  // global sequence numbers, as commit() returned them
    CHECK(x.size == 64);
  }
  CHECK(indices(drain(r0)).empty());
  CHECK(indices(drain(r0_default)).empty());
  CHECK(indices(drain(rbig)) == V{1, 2, 3, 4, 5});

  write_msg(w, 6, 100);
  write_msg(w, 7, 100);
  CHECK(indices(drain(r3)) == V{6, 7});
  CHECK(indices(drain(r0)) == V{6, 7});
  CHECK(indices(drain(r0_default)) == V{6, 7});
  CHECK(indices(drain(rbig)) == V{6, 7});
  for (const Reader* r : {&r3, &r0, &r0_default, &rbig}) CHECK(r->drops() == 0);
  CHECK(r3.received() == 5);
  CHECK(rbig.received() == 7);
}

TEST_CASE("keep: a backlog is bounded by slot_count - 1 and lapping it counts drops",
          "[shm][keep]") {
  Watchdog wd(10s);
  SECTION("bounded by slot_count - 1") {
    const auto base = unique_base("backlogcap");
    ShmGuard g(base);
    auto w = Writer::create(base, keep_opts(3, 8));
    for (std::uint64_t i = 1; i <= 20; ++i) write_msg(w, i, 64);
    auto r = Reader::open(base, 1000);
    CHECK(indices(drain(r)) == V{14, 15, 16, 17, 18, 19, 20});
    CHECK(r.drops() == 0);
  }
  SECTION("a backlog message overwritten before take() is a drop") {
    const auto base = unique_base("backloglap");
    ShmGuard g(base);
    auto w = Writer::create(base, keep_opts(3, 4));
    for (std::uint64_t i = 1; i <= 3; ++i) write_msg(w, i, 64);
    auto r = Reader::open(base, 3);  // starts at 1
    write_msg(w, 4, 64);
    write_msg(w, 5, 64);  // overwrites 1 (4 slots)
    CHECK(indices(drain(r)) == V{2, 3, 4, 5});
    CHECK(r.drops() == 1);
  }
}

TEST_CASE("keep: growth carries the last messages into the new generation", "[shm][keep]") {
  Watchdog wd(10s);
  const auto base = unique_base("carry");
  ShmGuard g(base);
  auto w = Writer::create(base, keep_opts(3, 8));
  auto before_taken = Reader::open(base);  // takes 1..3 before the growth
  auto before_idle = Reader::open(base);   // takes nothing before the growth
  for (std::uint64_t i = 1; i <= 3; ++i) write_msg(w, i, 64 + i);
  CHECK(indices(drain(before_taken)) == V{1, 2, 3});

  CHECK(write_msg(w, 4, 10000) == 3);  // > 4096-byte slots: generation 1
  REQUIRE(w.segment_name() == base + "_g1");
  CHECK(w.published() == 4);  // carried messages are not new messages

  // The header of generation 1: version 4, carried 3, first_global_seq of seq 0 = 4 - 1 - 3.
  const auto img = read_shm_file(base + "_g1");
  REQUIRE(img.size() >= sizeof(detail::SegmentHeader));
  std::uint32_t version = 0, carried = 0;
  std::uint64_t first = ~0ull, write_seq = 0;
  std::memcpy(&version, img.data() + offsetof(detail::SegmentHeader, version), 4);
  std::memcpy(&carried, img.data() + offsetof(detail::SegmentHeader, carried), 4);
  std::memcpy(&first, img.data() + offsetof(detail::SegmentHeader, first_global_seq), 8);
  std::memcpy(&write_seq, img.data() + offsetof(detail::SegmentHeader, write_seq), 8);
  CHECK(version == detail::kVersion);
  CHECK(version == 5);
  CHECK(carried == 3);
  CHECK(first == 0);
  CHECK(write_seq == 4);

  auto late = Reader::open(base, 4);
  CHECK(late.segment_name() == base + "_g1");
  const auto got = drain(late);
  REQUIRE(indices(got) == V{1, 2, 3, 4});
  for (const auto& x : got) {
    CHECK(x.sequence == x.index - 1);
    CHECK(x.size == (x.index == 4 ? 10000u : 64u + x.index));
  }
  auto late2 = Reader::open(base + "_g0", 2);  // by an old name: follows to the newest
  CHECK(indices(drain(late2)) == V{3, 4});

  CHECK(indices(drain(before_taken)) == V{4});
  CHECK(indices(drain(before_idle)) == V{1, 2, 3, 4});

  write_msg(w, 5, 64);
  for (Reader* r : {&before_taken, &before_idle, &late, &late2}) {
    CHECK(indices(drain(*r)) == V{5});
    CHECK(r->drops() == 0);
  }
  CHECK(before_idle.received() == 5);
  CHECK(before_taken.received() == 5);
}

TEST_CASE("keep: carried messages survive two growths and are delivered once", "[shm][keep]") {
  Watchdog wd(10s);
  const auto base = unique_base("carry2");
  ShmGuard g(base);
  auto w = Writer::create(base, keep_opts(3, 8));
  auto early = Reader::open(base);
  for (std::uint64_t i = 1; i <= 3; ++i) write_msg(w, i, 64);
  CHECK(write_msg(w, 4, 10000) == 3);   // g1: carries 1, 2, 3
  CHECK(write_msg(w, 5, 30000) == 4);   // g2: carries 2, 3, 4
  REQUIRE(w.segment_name() == base + "_g2");
  CHECK(w.published() == 5);
  auto late = Reader::open(base, 7);
  const auto got = drain(late);
  REQUIRE(indices(got) == V{2, 3, 4, 5});
  for (const auto& x : got) CHECK(x.sequence == x.index - 1);
  CHECK(indices(drain(early)) == V{1, 2, 3, 4, 5});
  CHECK(early.drops() == 0);
  CHECK(late.drops() == 0);
  write_msg(w, 6, 64);
  CHECK(indices(drain(early)) == V{6});
  CHECK(indices(drain(late)) == V{6});
}

TEST_CASE("keep: without keep, growth carries nothing", "[shm][keep]") {
  Watchdog wd(10s);
  const auto base = unique_base("nocarry");
  ShmGuard g(base);
  auto w = Writer::create(base, keep_opts(0, 8));
  auto early = Reader::open(base);
  for (std::uint64_t i = 1; i <= 3; ++i) write_msg(w, i, 64);
  write_msg(w, 4, 10000);
  REQUIRE(w.segment_name() == base + "_g1");
  auto late = Reader::open(base, 4);
  CHECK(indices(drain(late)) == V{4});
  CHECK(indices(drain(early)) == V{1, 2, 3, 4});
  CHECK(early.drops() == 0);
  CHECK(late.drops() == 0);
}

TEST_CASE("keep: keep >= slot_count is invalid_argument", "[shm][keep]") {
  Watchdog wd(10s);
  const auto base = unique_base("keepbad");
  ShmGuard g(base);
  auto is_invalid = Catch::Predicate<Error>(
      [](const Error& e) { return e.code() == Errc::invalid_argument; }, "invalid_argument");
  CHECK_THROWS_MATCHES(Writer::create(base, keep_opts(8, 8)), Error, is_invalid);
  CHECK_THROWS_MATCHES(Writer::create(base, keep_opts(100, 8)), Error, is_invalid);
  CHECK_FALSE(shm_exists(base + "_g0"));
  auto w = Writer::create(base, keep_opts(7, 8));  // slot_count - 1 is fine
  CHECK(w.segment_name() == base + "_g0");
}

// Reader::open's since (the start-up race, issue 37): what a Writer committed at or after a
// time, as far as its ring holds it.
TEST_CASE("since: a Writer made after `since` is read from its first message, what its ring lost is counted",
          "[shm][keep][since]") {
  Watchdog wd(10s);
  const auto base = unique_base("since_new");
  ShmGuard g(base);
  const auto before = monotonic_ns();
  auto w = Writer::create(base, opts(8));  // no keep: the ring alone
  for (std::uint64_t i = 1; i <= 5; ++i) write_msg(w, i, 64);
  auto r = Reader::open(base, 0, before);
  CHECK(indices(drain(r)) == V{1, 2, 3, 4, 5});
  CHECK(r.drops() == 0);
  // Lapped before the Reader came: 7 slots' worth is still there, the first 13 are lost.
  const auto base2 = unique_base("since_lapped");
  ShmGuard g2(base2);
  auto w2 = Writer::create(base2, opts(8));
  for (std::uint64_t i = 1; i <= 20; ++i) write_msg(w2, i, 64);
  auto r2 = Reader::open(base2, 0, before);
  CHECK(indices(drain(r2)) == V{14, 15, 16, 17, 18, 19, 20});
  CHECK(r2.drops() == 13);
  write_msg(w2, 21, 64);
  CHECK(indices(drain(r2)) == V{21});
}

TEST_CASE("since: a Writer made before `since` is read from its first message committed at or after it",
          "[shm][keep][since]") {
  Watchdog wd(10s);
  const auto base = unique_base("since_old");
  ShmGuard g(base);
  auto w = Writer::create(base, opts(8));
  for (std::uint64_t i = 1; i <= 3; ++i) write_msg(w, i, 64);
  const auto since = monotonic_ns();
  for (std::uint64_t i = 4; i <= 5; ++i) write_msg(w, i, 64);
  auto r = Reader::open(base, 0, since);
  CHECK(indices(drain(r)) == V{4, 5});
  CHECK(r.drops() == 0);
  // A backlog reaching further back wins: the older of the two starts.
  auto rb = Reader::open(base, 4, since);
  CHECK(indices(drain(rb)) == V{2, 3, 4, 5});
  // since in the future: nothing before the next commit.
  auto rf = Reader::open(base, 0, monotonic_ns() + 1000000000ull);
  CHECK(indices(drain(rf)).empty());
  write_msg(w, 6, 64);
  CHECK(indices(drain(rf)) == V{6});
}
