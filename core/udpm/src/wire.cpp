#include "lcmx/udpm/wire.hpp"

#include <cstring>

namespace lcmx::udpm {
namespace {

std::uint32_t load_u32(const std::byte* p) noexcept {
  return (std::uint32_t(p[0]) << 24) | (std::uint32_t(p[1]) << 16) | (std::uint32_t(p[2]) << 8) |
         std::uint32_t(p[3]);
}
std::uint16_t load_u16(const std::byte* p) noexcept {
  return static_cast<std::uint16_t>((std::uint32_t(p[0]) << 8) | std::uint32_t(p[1]));
}

// Channel at the start of `rest`: up to the first NUL, which must lie within `rest` and within
// kMaxChannelLength + 1 bytes. Returns the channel length, or -1.
long channel_length(std::span<const std::byte> rest) noexcept {
  const std::size_t limit = rest.size() < kMaxChannelLength + 1 ? rest.size() : kMaxChannelLength + 1;
  const void* nul = std::memchr(rest.data(), 0, limit);
  if (nul == nullptr) return -1;
  return static_cast<const std::byte*>(nul) - rest.data();
}

}  // namespace

std::optional<ParsedDatagram> parse_datagram(std::span<const std::byte> d) noexcept {
  if (d.size() < kShortHeaderSize) return std::nullopt;
  const std::uint32_t magic = load_u32(d.data());
  ParsedDatagram out{};
  out.sequence = load_u32(d.data() + 4);

  if (magic == kMagicShort) {
    const auto rest = d.subspan(kShortHeaderSize);
    const long ch = channel_length(rest);
    if (ch < 0) return std::nullopt;
    const std::size_t n = static_cast<std::size_t>(ch);
    out.fragment = false;
    out.channel = std::string_view(reinterpret_cast<const char*>(rest.data()), n);
    out.payload = rest.subspan(n + 1);
    out.total_size = static_cast<std::uint32_t>(out.payload.size());
    out.fragment_offset = 0;
    out.fragment_no = 0;
    out.fragment_count = 1;
    return out;
  }
  if (magic != kMagicLong) return std::nullopt;
  if (d.size() < kLongHeaderSize) return std::nullopt;

  out.fragment = true;
  out.total_size = load_u32(d.data() + 8);
  out.fragment_offset = load_u32(d.data() + 12);
  out.fragment_no = load_u16(d.data() + 16);
  out.fragment_count = load_u16(d.data() + 18);
  if (out.fragment_count == 0 || out.fragment_no >= out.fragment_count) return std::nullopt;
  if (out.total_size > kMaxMessageSize) return std::nullopt;

  auto rest = d.subspan(kLongHeaderSize);
  if (out.fragment_no == 0) {
    if (out.fragment_offset != 0) return std::nullopt;
    const long ch = channel_length(rest);
    if (ch < 0) return std::nullopt;
    const std::size_t n = static_cast<std::size_t>(ch);
    out.channel = std::string_view(reinterpret_cast<const char*>(rest.data()), n);
    rest = rest.subspan(n + 1);
  }
  // 64-bit sum: offset and size are both < 2^32.
  if (std::uint64_t{out.fragment_offset} + rest.size() > out.total_size) return std::nullopt;
  out.payload = rest;
  return out;
}

}  // namespace lcmx::udpm
