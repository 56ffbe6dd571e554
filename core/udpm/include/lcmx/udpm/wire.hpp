#pragma once
// LCM's udpm wire format (as liblcm 1.3.1 on Linux speaks it), all integers big-endian:
//   LC02 (short):    u32 magic "LC02" | u32 sequence | channel '\0' | payload
//   LC03 (fragment): u32 magic "LC03" | u32 sequence | u32 total payload size
//                    | u32 fragment offset (into the payload) | u16 fragment no | u16 count
//                    | (fragment 0 only: channel '\0') | payload bytes
// A message goes as LC02 when channel + 1 + payload <= kShortMessageMaxSize, else as
// ceil((channel + 1 + payload) / kFragmentMaxPayload) LC03 fragments; fragment 0 carries the
// channel and kFragmentMaxPayload - (channel + 1) payload bytes, the others up to
// kFragmentMaxPayload payload bytes each. Every datagram is then at most 65507 bytes.

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>

namespace lcmx::udpm {

inline constexpr std::uint32_t kMagicShort = 0x4c433032;  // "LC02"
inline constexpr std::uint32_t kMagicLong = 0x4c433033;   // "LC03"
inline constexpr std::size_t kShortHeaderSize = 8;
inline constexpr std::size_t kLongHeaderSize = 20;
inline constexpr std::size_t kMaxChannelLength = 63;           // bytes, without the NUL
inline constexpr std::size_t kShortMessageMaxSize = 65499;     // channel + NUL + payload
inline constexpr std::size_t kFragmentMaxPayload = 65487;      // bytes after the LC03 header
inline constexpr std::size_t kMaxMessageSize = std::size_t{1} << 28;  // liblcm's receive limit
inline constexpr std::size_t kMaxDatagramSize = 65507;          // largest IPv4 UDP payload

// Number of LC03 fragments for a message, or 1 when it goes as one LC02 datagram.
constexpr std::size_t datagram_count(std::size_t channel_size, std::size_t payload_size) noexcept {
  const std::size_t n = channel_size + 1 + payload_size;
  if (n <= kShortMessageMaxSize) return 1;
  return (n + kFragmentMaxPayload - 1) / kFragmentMaxPayload;
}

struct ParsedDatagram {
  bool fragment;                      // LC03
  std::uint32_t sequence;
  std::string_view channel;           // empty view for LC03 fragments other than number 0
  std::span<const std::byte> payload;  // this datagram's payload bytes
  std::uint32_t total_size;           // LC02: payload size; LC03: the whole message's size
  std::uint32_t fragment_offset;      // LC02: 0
  std::uint16_t fragment_no;          // LC02: 0
  std::uint16_t fragment_count;       // LC02: 1
};

// Parses one datagram. Views point into `datagram`. Returns nullopt for anything malformed:
// shorter than its header, unknown magic, channel without NUL or longer than 63 bytes, LC03
// with count 0, fragment no >= count, total > kMaxMessageSize, offset + length > total,
// fragment 0 with a non-zero offset. Never reads outside `datagram`.
std::optional<ParsedDatagram> parse_datagram(std::span<const std::byte> datagram) noexcept;

// True when `channel` is a valid LCM channel name (<= 63 bytes, no NUL).
constexpr bool valid_channel(std::string_view channel) noexcept {
  return channel.size() <= kMaxChannelLength && channel.find('\0') == std::string_view::npos;
}

}  // namespace lcmx::udpm
