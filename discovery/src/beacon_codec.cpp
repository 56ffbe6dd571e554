#include "lcmx/discovery/beacon_codec.hpp"

#include <cstdint>

#include "lcmx/lcmtypes/envelope.hpp"

namespace lcmx::discovery {

std::vector<std::byte> encode_beacon(const lcmx_msgs::beacon_t& beacon) {
  std::vector<std::byte> out(static_cast<std::size_t>(beacon.getEncodedSize()));
  const int n = beacon.encode(out.data(), 0, static_cast<int>(out.size()));
  out.resize(n < 0 ? 0 : static_cast<std::size_t>(n));
  return out;
}

std::optional<lcmx_msgs::beacon_t> decode_beacon(std::span<const std::byte> bytes,
                                                 std::string* why) {
  auto reject = [&](const char* reason) -> std::optional<lcmx_msgs::beacon_t> {
    if (why) *why = reason;
    return std::nullopt;
  };
  if (bytes.size() < 12) return reject("shorter than a beacon header");
  if (bytes.size() > (64u << 20)) return reject("larger than 64 MiB");
  lcmtypes::Reader head(bytes);
  if (!head.fingerprint(lcmx_msgs::beacon_t::getHash())) return reject("not a beacon_t (fingerprint)");
  // The checked decoder: every count and length against the bytes left before anything is
  // sized (lcmx/lcmtypes/envelope.hpp).
  lcmx_msgs::beacon_t b;
  if (!lcmtypes::decode(bytes, b)) return reject("malformed beacon (lengths or counts out of range)");
  if (b.version != kBeaconVersion) return reject("unsupported beacon version");
  return b;
}

std::vector<std::byte> encode_host_beacon(const lcmx_msgs::host_beacon_t& beacon) {
  std::vector<std::byte> out(static_cast<std::size_t>(beacon.getEncodedSize()));
  beacon.encode(out.data(), 0, static_cast<int>(out.size()));
  return out;
}

std::int64_t fingerprint_of(std::span<const std::byte> bytes) {
  if (bytes.size() < 8) return 0;
  std::int64_t hash = 0;
  for (int i = 0; i < 8; ++i)
    hash = static_cast<std::int64_t>((static_cast<std::uint64_t>(hash) << 8) |
                                     std::to_integer<std::uint8_t>(bytes[i]));
  return hash;
}

std::optional<lcmx_msgs::host_beacon_t> decode_host_beacon(std::span<const std::byte> bytes, std::string* why) {
  auto reject = [&](const char* w) -> std::optional<lcmx_msgs::host_beacon_t> {
    if (why) *why = w;
    return std::nullopt;
  };
  if (bytes.size() < 12) return reject("shorter than a host beacon header");
  if (bytes.size() > (16u << 20)) return reject("larger than 16 MiB");
  if (fingerprint_of(bytes) != lcmx_msgs::host_beacon_t::getHash()) return reject("not a host_beacon_t (fingerprint)");
  lcmx_msgs::host_beacon_t b;
  if (!lcmtypes::decode(bytes, b)) return reject("malformed host beacon (lengths or counts out of range)");
  if (b.version != kHostBeaconVersion) return reject("unsupported host beacon version");
  return b;
}

std::vector<std::byte> encode_records(std::uint64_t host_id, std::span<const std::vector<std::byte>> records) {
  std::size_t total = kBatchHeaderBytes;
  for (const auto& r : records) total += r.size() - 8;
  std::vector<std::byte> out(total);
  lcmtypes::Writer w(out);
  w.i64(lcmx_msgs::records_t::getHash());
  w.i32(kBeaconVersion);
  w.i64(static_cast<std::int64_t>(host_id));
  w.i32(static_cast<std::int32_t>(records.size()));
  for (const auto& r : records) w.bytes(std::span(r).subspan(8));  // without its fingerprint
  return out;
}

std::optional<lcmx_msgs::records_t> decode_records(std::span<const std::byte> bytes, std::string* why) {
  auto reject = [&](const char* w) -> std::optional<lcmx_msgs::records_t> {
    if (why) *why = w;
    return std::nullopt;
  };
  if (bytes.size() < kBatchHeaderBytes) return reject("shorter than a records header");
  if (bytes.size() > (16u << 20)) return reject("larger than 16 MiB");
  if (fingerprint_of(bytes) != lcmx_msgs::records_t::getHash()) return reject("not a records_t (fingerprint)");
  lcmx_msgs::records_t r;
  if (!lcmtypes::decode(bytes, r)) return reject("malformed records (lengths or counts out of range)");
  if (r.version != kBeaconVersion) return reject("unsupported records version");
  for (const auto& b : r.records) {
    if (b.version != kBeaconVersion) return reject("a record of an unsupported version in a batch");
    if (b.host_id != r.host_id) return reject("a record of another host in a batch");
  }
  return r;
}

std::optional<std::vector<lcmx_msgs::beacon_t>> decode_any_records(std::span<const std::byte> bytes, std::string* why) {
  const auto fp = fingerprint_of(bytes);
  if (fp == lcmx_msgs::records_t::getHash()) {
    auto r = decode_records(bytes, why);
    if (!r) return std::nullopt;
    return std::move(r->records);
  }
  auto b = decode_beacon(bytes, why);
  if (!b) return std::nullopt;
  return std::vector<lcmx_msgs::beacon_t>{std::move(*b)};
}

}  // namespace lcmx::discovery
