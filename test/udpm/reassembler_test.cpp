#include <catch2/catch.hpp>

#include "reassembler.hpp"
#include "support.hpp"

using namespace lcmx::udpm;
using namespace lcmx::udpm::test;
using detail::Reassembler;

namespace {
ParsedDatagram parsed(const std::vector<std::byte>& d) {
  auto p = parse_datagram(d);
  REQUIRE(p);
  return *p;
}
const Source kA{0x0100007f, 0x1111};
const Source kB{0x0100007f, 0x2222};
}  // namespace

TEST_CASE("Reassembler completes messages in any fragment order", "[unit][reassembly]") {
  Reassembler r({1u << 28, 16, std::chrono::seconds(1)});
  const auto data = make_payload(4, 150000);
  auto frags = lc03_message(9, "CAM", data);
  REQUIRE(frags.size() == 3);
  const auto t = Reassembler::Clock::now();
  CHECK_FALSE(r.add(parsed(frags[2]), kA, t));
  CHECK_FALSE(r.add(parsed(frags[0]), kA, t));
  CHECK_FALSE(r.add(parsed(frags[0]), kA, t));  // duplicate: ignored
  CHECK(r.stats().duplicate_fragments == 1);
  auto c = r.add(parsed(frags[1]), kA, t);
  REQUIRE(c);
  CHECK(c->channel == "CAM");
  CHECK(c->sequence == 9);
  CHECK(c->source == kA);
  REQUIRE(c->size == data.size());
  CHECK(std::memcmp(c->data.get(), data.data(), data.size()) == 0);
  CHECK(r.partial_count() == 0);
  CHECK(r.reserved_bytes() == 0);
}

TEST_CASE("Reassembler keeps (source, sequence) apart, bounds memory and expires", "[unit][reassembly]") {
  const auto data = make_payload(1, 100000);
  const auto f1 = lc03_message(1, "X", data);
  const auto t0 = Reassembler::Clock::now();

  SECTION("two sources with the same sequence interleaved") {
    Reassembler r({1u << 28, 16, std::chrono::seconds(1)});
    CHECK_FALSE(r.add(parsed(f1[0]), kA, t0));
    CHECK_FALSE(r.add(parsed(f1[0]), kB, t0));
    CHECK(r.add(parsed(f1[1]), kB, t0));
    CHECK(r.add(parsed(f1[1]), kA, t0));
  }
  SECTION("timeout drops stale partial messages") {
    Reassembler r({1u << 28, 16, std::chrono::milliseconds(100)});
    CHECK_FALSE(r.add(parsed(f1[0]), kA, t0));
    r.expire(t0 + std::chrono::milliseconds(50));
    CHECK(r.partial_count() == 1);
    r.expire(t0 + std::chrono::milliseconds(150));
    CHECK(r.partial_count() == 0);
    CHECK(r.stats().incomplete_dropped == 1);
    CHECK_FALSE(r.add(parsed(f1[1]), kA, t0));  // late fragment starts a new partial
  }
  SECTION("memory bound evicts the oldest; oversize is dropped") {
    Reassembler r({250000, 16, std::chrono::seconds(1)});
    CHECK_FALSE(r.add(parsed(lc03_message(1, "X", data)[0]), kA, t0));
    CHECK_FALSE(r.add(parsed(lc03_message(2, "X", data)[0]), kA, t0 + std::chrono::milliseconds(1)));
    CHECK(r.reserved_bytes() == 2 * Reassembler::charge(100000, 2));
    CHECK_FALSE(r.add(parsed(lc03_message(3, "X", data)[0]), kA, t0 + std::chrono::milliseconds(2)));
    CHECK(r.stats().incomplete_dropped == 1);  // sequence 1 went
    CHECK(r.partial_count() == 2);
    CHECK(r.add(parsed(lc03_message(3, "X", data)[1]), kA, t0));
    const auto big = make_payload(2, 300000);
    CHECK_FALSE(r.add(parsed(lc03_message(4, "X", big)[0]), kA, t0));
    CHECK(r.stats().oversize_dropped == 1);
  }
  SECTION("partial count bound") {
    Reassembler r({1u << 28, 2, std::chrono::seconds(1)});
    for (std::uint32_t s = 0; s < 5; ++s)
      CHECK_FALSE(r.add(parsed(lc03_message(s, "X", data)[0]), kA, t0 + std::chrono::milliseconds(s)));
    CHECK(r.partial_count() == 2);
    CHECK(r.stats().incomplete_dropped == 3);
  }
  SECTION("inconsistent fragments and gaps are malformed") {
    Reassembler r({1u << 28, 16, std::chrono::seconds(1)});
    CHECK_FALSE(r.add(parsed(lc03(7, 100, 0, 0, 2, "X", std::span(data).first(50))), kA, t0));
    CHECK_FALSE(r.add(parsed(lc03(7, 120, 50, 1, 2, std::nullopt, std::span(data).first(50))), kA, t0));
    CHECK(r.stats().malformed_dropped == 1);
    // all fragments there, but they cover only 90 of 100 bytes
    CHECK_FALSE(r.add(parsed(lc03(7, 100, 60, 1, 2, std::nullopt, std::span(data).first(40))), kA, t0));
    CHECK(r.stats().malformed_dropped == 2);
    CHECK(r.partial_count() == 0);
  }
}

TEST_CASE("Reassembler: a source flooding partial messages evicts its own, not others' in flight",
          "[unit][reassembly]") {
  // kB sends first fragments of messages it never completes (a hostile or broken sender on the
  // group); kA's message, in flight meanwhile, still completes.
  const auto data = make_payload(1, 100000);
  const auto a = lc03_message(1, "CAM", data);
  const auto t0 = Reassembler::Clock::now();
  for (const std::size_t limit_bytes : {std::size_t{1} << 28, std::size_t{450000}}) {
    INFO("max_bytes " << limit_bytes);
    Reassembler r({limit_bytes, 4, std::chrono::seconds(1)});
    CHECK_FALSE(r.add(parsed(a[0]), kA, t0));
    for (std::uint32_t s = 0; s < 100; ++s)
      CHECK_FALSE(r.add(parsed(lc03_message(1000 + s, "X", data)[0]), kB, t0 + std::chrono::milliseconds(1 + s)));
    CHECK(r.partial_count() <= 4);
    CHECK(r.reserved_bytes() <= limit_bytes);
    CHECK(r.stats().incomplete_dropped >= 96);
    auto c = r.add(parsed(a[1]), kA, t0 + std::chrono::milliseconds(200));
    REQUIRE(c);
    CHECK(c->size == data.size());
  }
}

TEST_CASE("Reassembler: bookkeeping of fragment sets is bounded, not only their bytes", "[unit][reassembly]") {
  // A first fragment may announce 65535 fragments of a 1-byte message: the seen flags and
  // extents of such partial messages (~590 KB each) were not counted against max_bytes, so 256
  // of them held ~150 MB under a 1 MiB limit.
  const auto data = make_payload(2, 16);
  const auto t0 = Reassembler::Clock::now();
  const std::size_t limit = 1u << 20;
  Reassembler r({limit, 256, std::chrono::seconds(1)});
  for (std::uint32_t s = 0; s < 100; ++s)
    CHECK_FALSE(r.add(parsed(lc03(s, 1, 0, 0, 65535, "X", std::span(data).first(1))), kB,
                      t0 + std::chrono::milliseconds(s)));
  CHECK(r.partial_count() == 1);
  CHECK(r.reserved_bytes() == Reassembler::charge(1, 65535));
  CHECK(r.reserved_bytes() <= limit);
  // A set whose bookkeeping alone exceeds the limit is oversize.
  Reassembler small({100000, 16, std::chrono::seconds(1)});
  CHECK_FALSE(small.add(parsed(lc03(1, 1, 0, 0, 65535, "X", std::span(data).first(1))), kB, t0));
  CHECK(small.stats().oversize_dropped == 1);
  CHECK(small.partial_count() == 0);
}
