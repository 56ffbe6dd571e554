// libFuzzer target: lcmx::udpm::parse_datagram and the private LC03 Reassembler.
//
// Checks, for every datagram:
//  - parse_datagram agrees with an independent reading of the wire format in wire.hpp
//    (accept/reject and every field), and its views lie inside the datagram;
// and for the Reassembler, after every add() and expire():
//  - partial_count() <= max_partials and reserved_bytes() <= max_bytes;
//  - a completed message has the declared total size, the fragment's source and sequence,
//    the channel of a fragment 0 fed for that (source, sequence), and every byte of it was
//    sent at that offset by a fragment fed for that (source, sequence): no byte is made up.
// A failed check prints what failed and aborts, which libFuzzer reports as a crash.
// Input layout: udpm_input.hpp.

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <iterator>
#include <map>
#include <optional>
#include <span>
#include <string_view>
#include <tuple>
#include <vector>

#include "../../core/udpm/src/reassembler.hpp"  // private header: reached by path on purpose
#include "lcmx/udpm/wire.hpp"
#include "udpm_input.hpp"

namespace {

using lcmx::udpm::ParsedDatagram;
using lcmx::udpm::Source;
using Reassembler = lcmx::udpm::detail::Reassembler;

#define FUZZ_CHECK(cond)                                                                  \
  do {                                                                                    \
    if (!(cond)) {                                                                        \
      std::fprintf(stderr, "fuzz_udpm_datagram: check failed: %s (%s:%d)\n", #cond,      \
                   __FILE__, __LINE__);                                                   \
      std::abort();                                                                       \
    }                                                                                     \
  } while (0)

std::uint32_t be32(const std::byte* p) {
  return std::uint32_t(p[0]) << 24 | std::uint32_t(p[1]) << 16 | std::uint32_t(p[2]) << 8 |
         std::uint32_t(p[3]);
}
std::uint16_t be16(const std::byte* p) {
  return static_cast<std::uint16_t>(std::uint32_t(p[0]) << 8 | std::uint32_t(p[1]));
}

// Reference reading of wire.hpp's format, written independently of wire.cpp.
std::optional<ParsedDatagram> reference_parse(std::span<const std::byte> d) {
  using namespace lcmx::udpm;
  if (d.size() < kShortHeaderSize) return std::nullopt;
  const std::uint32_t magic = be32(d.data());
  ParsedDatagram p{};
  p.sequence = be32(d.data() + 4);
  std::size_t pos = 0;
  auto read_channel = [&]() -> bool {  // NUL-terminated, at most kMaxChannelLength bytes
    for (std::size_t i = pos; i < d.size() && i - pos <= kMaxChannelLength; ++i) {
      if (d[i] == std::byte{0}) {
        p.channel = std::string_view(reinterpret_cast<const char*>(d.data() + pos), i - pos);
        pos = i + 1;
        return true;
      }
    }
    return false;
  };
  if (magic == kMagicShort) {
    pos = kShortHeaderSize;
    if (!read_channel()) return std::nullopt;
    p.fragment = false;
    p.payload = d.subspan(pos);
    p.total_size = static_cast<std::uint32_t>(p.payload.size());
    p.fragment_offset = 0;
    p.fragment_no = 0;
    p.fragment_count = 1;
    return p;
  }
  if (magic != kMagicLong || d.size() < kLongHeaderSize) return std::nullopt;
  p.fragment = true;
  p.total_size = be32(d.data() + 8);
  p.fragment_offset = be32(d.data() + 12);
  p.fragment_no = be16(d.data() + 16);
  p.fragment_count = be16(d.data() + 18);
  if (p.fragment_count == 0 || p.fragment_no >= p.fragment_count) return std::nullopt;
  if (p.total_size > kMaxMessageSize) return std::nullopt;
  pos = kLongHeaderSize;
  if (p.fragment_no == 0) {
    if (p.fragment_offset != 0) return std::nullopt;
    if (!read_channel()) return std::nullopt;
  }
  p.payload = d.subspan(pos);
  if (std::uint64_t{p.fragment_offset} + p.payload.size() > p.total_size) return std::nullopt;
  return p;
}

bool inside(std::span<const std::byte> outer, const void* begin, std::size_t size) {
  const auto* b = static_cast<const std::byte*>(begin);
  if (size == 0) return true;  // an empty view may point anywhere
  return b >= outer.data() && size <= outer.size() &&
         b - outer.data() <= static_cast<std::ptrdiff_t>(outer.size() - size);
}

// Parses one datagram and checks the result against the reference. Returns the parse.
std::optional<ParsedDatagram> checked_parse(std::span<const std::byte> d) {
  const auto got = lcmx::udpm::parse_datagram(d);
  const auto want = reference_parse(d);
  FUZZ_CHECK(got.has_value() == want.has_value());
  if (!got) return got;
  FUZZ_CHECK(inside(d, got->channel.data(), got->channel.size()));
  FUZZ_CHECK(inside(d, got->payload.data(), got->payload.size()));
  FUZZ_CHECK(lcmx::udpm::valid_channel(got->channel));
  FUZZ_CHECK(got->fragment == want->fragment);
  FUZZ_CHECK(got->sequence == want->sequence);
  FUZZ_CHECK(got->channel == want->channel);
  FUZZ_CHECK(got->payload.size() == want->payload.size());
  FUZZ_CHECK(got->payload.empty() || got->payload.data() == want->payload.data());
  FUZZ_CHECK(got->total_size == want->total_size);
  FUZZ_CHECK(got->fragment_offset == want->fragment_offset);
  FUZZ_CHECK(got->fragment_no == want->fragment_no);
  FUZZ_CHECK(got->fragment_count == want->fragment_count);
  return got;
}

// Every LC03 fragment fed for one (source, sequence) since its last completion.
struct Fed {
  ParsedDatagram d;  // views into the fuzz input, alive for the whole run
};
using Key = std::tuple<std::uint32_t, std::uint16_t, std::uint32_t>;

void check_complete(const Reassembler::Complete& c, const ParsedDatagram& last, Source source,
                    const std::vector<Fed>& fed) {
  FUZZ_CHECK(c.size == last.total_size);
  FUZZ_CHECK(c.source == source);
  FUZZ_CHECK(c.sequence == last.sequence);
  FUZZ_CHECK(c.size == 0 || c.data != nullptr);
  bool channel_seen = false;
  for (const Fed& f : fed)
    if (f.d.fragment_no == 0 && f.d.channel == c.channel) channel_seen = true;
  FUZZ_CHECK(channel_seen);
  // Every byte must come from a fragment of this message (same declared size and count).
  for (std::size_t i = 0; i < c.size; ++i) {
    bool covered = false;
    for (const Fed& f : fed) {
      if (f.d.total_size != c.size || f.d.fragment_count != last.fragment_count) continue;
      if (i < f.d.fragment_offset || i - f.d.fragment_offset >= f.d.payload.size()) continue;
      if (f.d.payload[i - f.d.fragment_offset] == c.data[i]) {
        covered = true;
        break;
      }
    }
    if (!covered) {
      std::fprintf(stderr,
                   "fuzz_udpm_datagram: completed message (size %u, %u fragments) byte %zu was "
                   "not sent by any of its %zu fragments\n",
                   c.size, static_cast<unsigned>(last.fragment_count), i, fed.size());
      for (const Fed& f : fed)
        std::fprintf(stderr, "  fragment %u/%u offset %u length %zu total %u\n",
                     static_cast<unsigned>(f.d.fragment_no),
                     static_cast<unsigned>(f.d.fragment_count), f.d.fragment_offset,
                     f.d.payload.size(), f.d.total_size);
      std::abort();
    }
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::span<const std::byte> input(reinterpret_cast<const std::byte*>(data), size);
  checked_parse(input);
  if (input.empty()) return 0;

  const auto& preset = lcmx::fuzz::kPresets[std::to_integer<std::size_t>(input[0]) %
                                            std::size(lcmx::fuzz::kPresets)];
  const Reassembler::Limits limits{
      preset.max_bytes, preset.max_partials,
      std::chrono::duration_cast<Reassembler::Clock::duration>(preset.timeout)};
  Reassembler r(limits);
  auto now = Reassembler::Clock::time_point{} + std::chrono::hours(1);
  std::map<Key, std::vector<Fed>> fed;

  auto check_bounds = [&] {
    FUZZ_CHECK(r.partial_count() <= limits.max_partials);
    FUZZ_CHECK(r.reserved_bytes() <= limits.max_bytes);
  };

  std::size_t pos = 1;
  while (pos + 3 <= input.size()) {
    const unsigned control = std::to_integer<unsigned>(input[pos]);
    const std::size_t length = be16(input.data() + pos + 1);
    pos += 3;
    const auto datagram = input.subspan(pos, std::min(length, input.size() - pos));
    pos += datagram.size();

    now += lcmx::fuzz::kAdvanceStep * (control >> lcmx::fuzz::kControlAdvanceShift);
    if (control & lcmx::fuzz::kControlExpire) {
      r.expire(now);
      check_bounds();
    }
    const auto& src = lcmx::fuzz::kSources[control & lcmx::fuzz::kControlSourceMask];
    const Source source{src[0], static_cast<std::uint16_t>(src[1])};

    const auto parsed = checked_parse(datagram);
    if (!parsed || !parsed->fragment) continue;
    const Key key{source.address_be, source.port_be, parsed->sequence};
    auto& list = fed[key];
    list.push_back(Fed{*parsed});
    auto complete = r.add(*parsed, source, now);
    check_bounds();
    if (complete) {
      check_complete(*complete, *parsed, source, list);
      list.clear();  // the Reassembler forgot this (source, sequence): so do we
    }
  }
  r.expire(now + std::chrono::hours(1));
  FUZZ_CHECK(r.partial_count() == 0);
  FUZZ_CHECK(r.reserved_bytes() == 0);
  return 0;
}
