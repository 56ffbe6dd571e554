#include <catch2/catch.hpp>
#include <random>

#include "lcmx/udpm/udpm.hpp"
#include "support.hpp"

using namespace lcmx::udpm;
using namespace lcmx::udpm::test;

TEST_CASE("parse_datagram reads LC02", "[unit][wire]") {
  const auto data = make_payload(3, 100);
  const auto d = lc02(42, "POSE", data);
  const auto p = parse_datagram(d);
  REQUIRE(p);
  CHECK_FALSE(p->fragment);
  CHECK(p->sequence == 42);
  CHECK(p->channel == "POSE");
  CHECK(p->payload.size() == 100);
  CHECK(p->payload.data() == d.data() + 8 + 5);
  CHECK(p->total_size == 100);
  CHECK(p->fragment_offset == 0);
  CHECK(p->fragment_no == 0);
  CHECK(p->fragment_count == 1);

  // empty payload, empty channel, 63-byte channel
  CHECK(parse_datagram(lc02(1, "X", {}))->payload.empty());
  CHECK(parse_datagram(lc02(1, "", data))->channel.empty());
  const std::string c63(63, 'c');
  CHECK(parse_datagram(lc02(1, c63, data))->channel == c63);
}

TEST_CASE("parse_datagram reads LC03 fragments", "[unit][wire]") {
  const auto data = make_payload(9, 200000);
  const auto frags = lc03_message(7, "IMAGE", data);
  REQUIRE(frags.size() == 4);  // ceil((6 + 200000) / 65487)
  CHECK(datagram_count(5, data.size()) == 4);
  std::size_t covered = 0;
  for (std::size_t i = 0; i < frags.size(); ++i) {
    CHECK(frags[i].size() <= kMaxDatagramSize);
    const auto p = parse_datagram(frags[i]);
    REQUIRE(p);
    CHECK(p->fragment);
    CHECK(p->sequence == 7);
    CHECK(p->total_size == 200000);
    CHECK(p->fragment_no == i);
    CHECK(p->fragment_count == 4);
    CHECK(p->fragment_offset == covered);
    CHECK(p->channel == (i == 0 ? "IMAGE" : ""));
    CHECK(std::memcmp(p->payload.data(), data.data() + covered, p->payload.size()) == 0);
    covered += p->payload.size();
  }
  CHECK(covered == data.size());
}

TEST_CASE("datagram_count switches to LC03 exactly where liblcm 1.3.1 does", "[unit][wire]") {
  CHECK(datagram_count(4, 65499 - 5) == 1);
  CHECK(datagram_count(4, 65499 - 5 + 1) == 2);
  CHECK(datagram_count(0, 0) == 1);
  CHECK(datagram_count(63, kMaxMessageSize) == (64 + kMaxMessageSize + 65486) / 65487);
}

TEST_CASE("parse_datagram rejects hostile input without reading out of bounds", "[unit][wire]") {
  const auto data = make_payload(1, 64);
  auto rejects = [](std::vector<std::byte> d) {
    // Exact-size heap copy so ASan catches any read past the end.
    auto copy = std::make_unique<std::byte[]>(d.size() == 0 ? 1 : d.size());
    if (!d.empty()) std::memcpy(copy.get(), d.data(), d.size());  // memcpy from null: UB even for 0 bytes
    return !parse_datagram(std::span<const std::byte>(copy.get(), d.size())).has_value();
  };

  SECTION("truncated headers") {
    const auto good = lc02(1, "A", data);
    for (std::size_t n = 0; n < 8; ++n) CHECK(rejects({good.begin(), good.begin() + n}));
    const auto frag = lc03(1, 100, 0, 0, 2, "A", data);
    for (std::size_t n = 8; n < 20; ++n) CHECK(rejects({frag.begin(), frag.begin() + n}));
  }
  SECTION("wrong magic") {
    auto d = lc02(1, "A", data);
    d[3] = std::byte{'4'};
    CHECK(rejects(d));
    d[0] = std::byte{0};
    CHECK(rejects(d));
  }
  SECTION("channel without NUL, or too long") {
    std::vector<std::byte> d;
    put32(d, kMagicShort);
    put32(d, 1);
    put_str(d, "NO_NUL_HERE", false);
    CHECK(rejects(d));
    CHECK(rejects(lc02(1, std::string(64, 'c'), data)));
    CHECK(rejects(lc03(1, 100, 0, 0, 2, std::string(64, 'c'), data)));
    std::vector<std::byte> f;
    put32(f, kMagicLong);
    put32(f, 1);
    put32(f, 100);
    put32(f, 0);
    put16(f, 0);
    put16(f, 2);
    put_str(f, "ABC", false);
    CHECK(rejects(f));
  }
  SECTION("bad fragment numbers, sizes and offsets") {
    CHECK(rejects(lc03(1, 100, 0, 0, 0, "A", data)));             // count 0
    CHECK(rejects(lc03(1, 100, 64, 2, 2, std::nullopt, data)));   // no == count
    CHECK(rejects(lc03(1, 100, 64, 9, 2, std::nullopt, data)));   // no > count
    CHECK(rejects(lc03(1, 100, 40, 1, 2, std::nullopt, data)));   // 40 + 64 > 100
    CHECK(rejects(lc03(1, 100, 101, 1, 2, std::nullopt, {})));    // offset past the total
    CHECK(rejects(lc03(1, 10, 0, 0, 1, "A", data)));              // first fragment > total
    CHECK(rejects(lc03(1, 100, 5, 0, 2, "A", data)));             // fragment 0 not at offset 0
    CHECK(rejects(lc03(1, (1u << 28) + 1, 0, 0, 5000, "A", data)));  // > 256 MiB
    CHECK(rejects(lc03(1, 0xffffffffu, 0xffffffc0u, 1, 2, std::nullopt, data)));  // near 2^32
    CHECK(rejects(lc03(1, 0xffffffffu, 0, 0, 0xffff, "A", data)));
    CHECK(rejects(lc03(1, 1u << 28, 0xfffffff0u, 1, 2, std::nullopt, data)));  // offset wraps
    // The limits themselves are accepted.
    CHECK_FALSE(rejects(lc03(1, 1u << 28, (1u << 28) - 64, 4000, 4100, std::nullopt, data)));
    CHECK_FALSE(rejects(lc03(1, 64, 0, 0, 1, "A", data)));
    CHECK_FALSE(rejects(lc03(1, 100, 36, 1, 2, std::nullopt, data)));
  }
  SECTION("random bytes and random mutations never crash") {
    std::mt19937 rng(12345);
    const auto good_short = lc02(5, "CHAN", data);
    const auto good_frag = lc03(5, 1000, 0, 0, 3, "CHAN", data);
    for (int i = 0; i < 20000; ++i) {
      std::vector<std::byte> d;
      if (i % 3 == 0) {
        d.resize(rng() % 100);
        for (auto& b : d) b = static_cast<std::byte>(rng());
        if (d.size() >= 4 && (rng() & 1)) {
          d[0] = std::byte{'L'}; d[1] = std::byte{'C'}; d[2] = std::byte{'0'};
          d[3] = std::byte{static_cast<unsigned char>((rng() & 1) ? '2' : '3')};
        }
      } else {
        d = (i % 3 == 1) ? good_short : good_frag;
        for (int k = 0; k < 3; ++k) d[rng() % d.size()] = static_cast<std::byte>(rng());
        d.resize(rng() % (d.size() + 1));
      }
      auto copy = std::make_unique<std::byte[]>(d.size() + 1);
      if (!d.empty()) std::memcpy(copy.get(), d.data(), d.size());  // memcpy from null: UB even for 0 bytes
      const auto p = parse_datagram(std::span<const std::byte>(copy.get(), d.size()));
      if (p) {
        // Whatever is accepted stays inside the datagram and is self-consistent.
        const auto* begin = copy.get();
        const auto* end = begin + d.size();
        REQUIRE(p->payload.data() >= begin);
        REQUIRE(p->payload.data() + p->payload.size() <= end);
        REQUIRE(p->channel.size() <= kMaxChannelLength);
        REQUIRE(p->fragment_no < p->fragment_count);
        REQUIRE(std::uint64_t{p->fragment_offset} + p->payload.size() <= p->total_size);
      }
    }
  }
}
