// Encoding and hostile-input-safe decoding of discovery beacons (lcmx_msgs::beacon_t).
#pragma once

#include <cstddef>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "lcmx_msgs/beacon_t.hpp"
#include "lcmx_msgs/host_beacon_t.hpp"

namespace lcmx::discovery {

inline constexpr const char* kBeaconChannel = "LCMX_BEACON";
inline constexpr int kBeaconVersion = 6;
inline constexpr int kHostBeaconVersion = 1;

// Encodes a beacon (lcm-gen encoding with its fingerprint, as LCM tools expect).
std::vector<std::byte> encode_beacon(const lcmx_msgs::beacon_t& beacon);

// Decodes a beacon received from the network. Before handing the bytes to lcm-gen's decoder
// it walks the encoding and checks every count and string length against the bytes that are
// left, so a malformed or hostile datagram can neither crash nor make it allocate more than
// the datagram's size. Returns nullopt and sets *why (if given) for anything malformed, for a
// wrong fingerprint and for an unsupported version.
std::optional<lcmx_msgs::beacon_t> decode_beacon(std::span<const std::byte> bytes,
                                                 std::string* why = nullptr);

// The speakers' messages (docs/discovery.md "Speaker protocol"); decoded with the same checks.
std::vector<std::byte> encode_host_beacon(const lcmx_msgs::host_beacon_t& beacon);
std::optional<lcmx_msgs::host_beacon_t> decode_host_beacon(std::span<const std::byte> bytes,
                                                           std::string* why = nullptr);
// The lcm-gen fingerprint an encoding starts with (0 if shorter than 8 bytes).
std::int64_t fingerprint_of(std::span<const std::byte> bytes);

}  // namespace lcmx::discovery
