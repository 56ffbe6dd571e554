// Encoding and hostile-input-safe decoding of discovery beacons (lcmx_msgs::beacon_t).
#pragma once

#include <cstddef>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "lcmx_msgs/beacon_t.hpp"
#include "lcmx_msgs/host_beacon_t.hpp"
#include "lcmx_msgs/records_t.hpp"
#include "lcmx_msgs/records_z_t.hpp"

namespace lcmx::discovery {

inline constexpr const char* kBeaconChannel = "LCMX_BEACON";
inline constexpr int kBeaconVersion = 6;
inline constexpr int kHostBeaconVersion = 1;

// Encodes a beacon (lcm-gen encoding with its fingerprint, as LCM tools expect).
std::vector<std::byte> encode_beacon(const lcmx_msgs::beacon_t& beacon);

// Decodes a beacon received from the network with lcmx's checked decoder
// (lcmx/lcmtypes/envelope.hpp): every count and string length is checked against the bytes
// that are left before anything is sized, so a malformed or hostile datagram can neither
// crash nor make it allocate more than a small multiple of the datagram's size. Accepts
// exactly lcm-gen's encoding of a beacon_t (nothing after it). Returns nullopt and sets *why
// (if given) for anything malformed, for a wrong fingerprint and for an unsupported version.
std::optional<lcmx_msgs::beacon_t> decode_beacon(std::span<const std::byte> bytes,
                                                 std::string* why = nullptr);

// The speakers' messages (docs/discovery.md "Speaker protocol"); decoded with the same checks.
std::vector<std::byte> encode_host_beacon(const lcmx_msgs::host_beacon_t& beacon);
std::optional<lcmx_msgs::host_beacon_t> decode_host_beacon(std::span<const std::byte> bytes,
                                                           std::string* why = nullptr);

// Batches (records_t): records and goodbyes of one host that a speaker sends together, at most
// kBatchBytes of records_t before compression (a record larger than a batch goes alone), and
// at the end of a pass the speaker's heartbeat as of those records. encode_records builds the
// batch from encode_beacon()'s bytes (and encode_host_beacon()'s for the heartbeat, empty for
// none) without decoding them (a nested struct is its top-level encoding without the
// fingerprint); every element must be a beacon_t encoding. decode_records checks like
// decode_beacon, that every record is of the batch's version and host, and that a heartbeat is
// one KIND_HEARTBEAT of the host.
inline constexpr std::size_t kBatchBytes = 32768;
// fingerprint, version, host, record count, heartbeat count
inline constexpr std::size_t kBatchHeaderBytes = 8 + 4 + 8 + 4 + 4;
std::vector<std::byte> encode_records(std::uint64_t host_id, std::span<const std::vector<std::byte>> records,
                                      std::span<const std::byte> heartbeat = {});
std::optional<lcmx_msgs::records_t> decode_records(std::span<const std::byte> bytes, std::string* why = nullptr);

// Compressed batches (records_z_t, docs/discovery.md "Compressed batches"). encode_batch gives
// what a speaker sends for records of one host (and its heartbeat, if not empty): the smallest
// of the record alone (a beacon_t; one record and no heartbeat only), the records_t, and the
// records_t deflated by zlib (records_z_t; only up to kMaxInflatedBytes). decode_batch takes a records_t or a records_z_t: a compressed one is
// inflated only if it declares at most kMaxInflatedBytes and at most kMaxInflateRatio times its
// deflated bytes (a hostile datagram cannot make a receiver allocate more than that), must
// inflate to exactly its declared size with no bytes after the stream, and must hold a
// records_t of its own host (then checked as decode_records does).
inline constexpr std::size_t kMaxInflatedBytes = 4u << 20;
inline constexpr std::size_t kMaxInflateRatio = 1032;  // deflate's own limit, about 1032:1
//
// A base (docs/discovery.md "Compressed against a base"): a record of the same host that every
// receiver holds, whose encode_beacon() bytes are zlib's preset dictionary, so a record much
// like one already heard (its previous revision, another process of the same program) costs
// a fraction of its bytes. The receiver finds the base named by batch_base() in its table and
// hands its bytes to decode_batch; zlib checks they are the ones deflated against.
struct BatchBase {
  std::int64_t participant = 0;
  std::int64_t revision = 0;
  std::span<const std::byte> bytes;  // encode_beacon() of that record, as sent
};
std::vector<std::byte> encode_batch(std::uint64_t host_id, std::span<const std::vector<std::byte>> records,
                                    std::span<const std::byte> heartbeat = {}, const BatchBase* base = nullptr);
// The (participant, revision) a compressed batch was deflated against; (0, 0): none, or not a
// records_z_t.
std::pair<std::int64_t, std::int64_t> batch_base(std::span<const std::byte> bytes);
std::optional<lcmx_msgs::records_t> decode_batch(std::span<const std::byte> bytes, std::string* why = nullptr,
                                                 std::span<const std::byte> base = {});
// Whichever of the three a discovery datagram holds: its records (a beacon_t is one). nullopt and
// *why for anything else or malformed. For tools and tests that watch a group's records.
std::optional<std::vector<lcmx_msgs::beacon_t>> decode_any_records(std::span<const std::byte> bytes,
                                                                   std::string* why = nullptr);

// The lcm-gen fingerprint an encoding starts with (0 if shorter than 8 bytes).
std::int64_t fingerprint_of(std::span<const std::byte> bytes);

}  // namespace lcmx::discovery
