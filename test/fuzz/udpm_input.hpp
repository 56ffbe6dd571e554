#pragma once
// Input layout of fuzz_udpm_datagram, shared by the fuzz target and the seed generator.
//
//   u8 preset                      limits of the Reassembler: kPresets[preset % size]
//   then records, until the input ends:
//     u8 control                   bits 0-1: source (kSources), bit 2: expire() before it,
//                                  bits 3-7: clock advance before it, in 10 ms steps
//     u16 length (big-endian)      datagram length; the last one is cut to what is left
//     length bytes                 the datagram, fed to parse_datagram (and the Reassembler
//                                  when it is a valid LC03 fragment)
// The whole input is also parsed once as one datagram.

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

namespace lcmx::fuzz {

struct LimitsPreset {
  std::size_t max_bytes;
  std::size_t max_partials;
  std::chrono::milliseconds timeout;
};

// Small limits so eviction and oversize paths are reached; bounded so that memory stays far
// below -rss_limit_mb even with every partial reserved.
inline constexpr LimitsPreset kPresets[] = {
    {std::size_t{1} << 20, 4, std::chrono::milliseconds(100)},
    {4096, 2, std::chrono::milliseconds(50)},
    {0, 0, std::chrono::milliseconds(10)},
    {std::size_t{1} << 26, 8, std::chrono::milliseconds(1000)},
};

inline constexpr std::uint32_t kSources[4][2] = {  // {address_be, port_be}
    {0x0100007f, 0x1111}, {0x0100007f, 0x2222}, {0x0200000a, 0x1111}, {0x0300000a, 0x3333}};

inline constexpr unsigned kControlSourceMask = 0x03;
inline constexpr unsigned kControlExpire = 0x04;
inline constexpr unsigned kControlAdvanceShift = 3;
inline constexpr std::chrono::milliseconds kAdvanceStep{10};

// Appends one record to `out`.
inline void append_record(std::vector<std::byte>& out, std::uint8_t control,
                          std::span<const std::byte> datagram) {
  out.push_back(std::byte{control});
  out.push_back(std::byte(static_cast<std::uint8_t>(datagram.size() >> 8)));
  out.push_back(std::byte(static_cast<std::uint8_t>(datagram.size())));
  out.insert(out.end(), datagram.begin(), datagram.end());
}

}  // namespace lcmx::fuzz
