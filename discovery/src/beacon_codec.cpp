#include "lcmx/discovery/beacon_codec.hpp"

#include <cstdint>

#include <zlib.h>

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

std::vector<std::byte> encode_records(std::uint64_t host_id, std::span<const std::vector<std::byte>> records,
                                      std::span<const std::byte> heartbeat) {
  std::size_t total = kBatchHeaderBytes + (heartbeat.size() > 8 ? heartbeat.size() - 8 : 0);
  for (const auto& r : records) total += r.size() - 8;
  std::vector<std::byte> out(total);
  lcmtypes::Writer w(out);
  w.i64(lcmx_msgs::records_t::getHash());
  w.i32(kBeaconVersion);
  w.i64(static_cast<std::int64_t>(host_id));
  w.i32(static_cast<std::int32_t>(records.size()));
  for (const auto& r : records) w.bytes(std::span(r).subspan(8));  // without its fingerprint
  w.i32(heartbeat.size() > 8 ? 1 : 0);
  if (heartbeat.size() > 8) w.bytes(heartbeat.subspan(8));
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
  if (r.state.size() > 1) return reject("more than one heartbeat in a batch");
  for (const auto& h : r.state)
    if (h.version != kHostBeaconVersion || h.kind != lcmx_msgs::host_beacon_t::KIND_HEARTBEAT || h.host_id != r.host_id)
      return reject("a heartbeat in a batch that is not its host's heartbeat");
  return r;
}

namespace {

// The records_t `raw` deflated into a records_z_t (against `base`'s bytes as zlib's preset
// dictionary, if any); nullopt if zlib fails (it does not for sizes it accepts) or the
// records_t is larger than receivers inflate.
std::optional<std::vector<std::byte>> deflate_records(std::uint64_t host_id, std::span<const std::byte> raw,
                                                      const BatchBase* base) {
  if (raw.size() > kMaxInflatedBytes) return std::nullopt;
  z_stream s{};
  if (deflateInit(&s, Z_BEST_COMPRESSION) != Z_OK) return std::nullopt;
  struct End {
    z_stream& s;
    ~End() { deflateEnd(&s); }
  } end{s};
  if (base && deflateSetDictionary(&s, reinterpret_cast<const Bytef*>(base->bytes.data()),
                                   static_cast<uInt>(base->bytes.size())) != Z_OK)
    return std::nullopt;
  std::vector<std::byte> z(deflateBound(&s, static_cast<uLong>(raw.size())));
  s.next_in = reinterpret_cast<Bytef*>(const_cast<std::byte*>(raw.data()));  // (zlib's API is not const)
  s.avail_in = static_cast<uInt>(raw.size());
  s.next_out = reinterpret_cast<Bytef*>(z.data());
  s.avail_out = static_cast<uInt>(z.size());
  if (deflate(&s, Z_FINISH) != Z_STREAM_END) return std::nullopt;
  const auto n = static_cast<std::size_t>(s.total_out);
  constexpr std::size_t kHeader = 8 + 4 + 8 + 8 + 8 + 4 + 4;  // fingerprint, version, host, base, raw_size, num_bytes
  std::vector<std::byte> out(kHeader + n);
  lcmtypes::Writer w(out);
  w.i64(lcmx_msgs::records_z_t::getHash());
  w.i32(kBeaconVersion);
  w.i64(static_cast<std::int64_t>(host_id));
  w.i64(base ? base->participant : 0);
  w.i64(base ? base->revision : 0);
  w.i32(static_cast<std::int32_t>(raw.size()));
  w.i32(static_cast<std::int32_t>(n));
  w.bytes(std::span(z).first(n));
  if (!w.ok()) return std::nullopt;
  return out;
}

// Inflates exactly `into.size()` bytes from `in`, with `dictionary` if the stream asks for one
// (zlib checks it is the one it was deflated against: its Adler-32 is in the stream).
bool inflate_exactly(std::span<const std::uint8_t> in, std::span<std::byte> into, std::span<const std::byte> dictionary) {
  z_stream s{};
  if (inflateInit(&s) != Z_OK) return false;
  struct End {
    z_stream& s;
    ~End() { inflateEnd(&s); }
  } end{s};
  s.next_in = const_cast<Bytef*>(in.data());
  s.avail_in = static_cast<uInt>(in.size());
  s.next_out = reinterpret_cast<Bytef*>(into.data());
  s.avail_out = static_cast<uInt>(into.size());
  int r = inflate(&s, Z_FINISH);
  if (r == Z_NEED_DICT) {
    if (dictionary.empty() || inflateSetDictionary(&s, reinterpret_cast<const Bytef*>(dictionary.data()),
                                                   static_cast<uInt>(dictionary.size())) != Z_OK)
      return false;
    r = inflate(&s, Z_FINISH);
  }
  return r == Z_STREAM_END && s.total_out == into.size() && s.avail_in == 0;
}

}  // namespace

std::vector<std::byte> encode_batch(std::uint64_t host_id, std::span<const std::vector<std::byte>> records,
                                    std::span<const std::byte> heartbeat, const BatchBase* base) {
  if (records.empty()) return {};
  auto batch = encode_records(host_id, records, heartbeat);
  const auto z = deflate_records(host_id, batch, base && !base->bytes.empty() ? base : nullptr);
  const bool alone = records.size() == 1 && heartbeat.empty();  // a plain beacon_t
  auto plain = alone ? records.front() : std::move(batch);
  if (z && z->size() < plain.size()) return *z;
  return plain;
}

std::pair<std::int64_t, std::int64_t> batch_base(std::span<const std::byte> bytes) {
  if (fingerprint_of(bytes) != lcmx_msgs::records_z_t::getHash()) return {0, 0};
  lcmtypes::Reader r(bytes);
  r.bytes(8 + 4 + 8);
  const auto participant = r.i64();
  const auto revision = r.i64();
  return r.ok() ? std::make_pair(participant, revision) : std::make_pair(std::int64_t{0}, std::int64_t{0});
}

std::optional<lcmx_msgs::records_t> decode_batch(std::span<const std::byte> bytes, std::string* why,
                                                 std::span<const std::byte> base) {
  auto reject = [&](const char* w) -> std::optional<lcmx_msgs::records_t> {
    if (why) *why = w;
    return std::nullopt;
  };
  if (fingerprint_of(bytes) != lcmx_msgs::records_z_t::getHash()) return decode_records(bytes, why);
  if (bytes.size() > (16u << 20)) return reject("larger than 16 MiB");
  lcmx_msgs::records_z_t z;
  if (!lcmtypes::decode(bytes, z)) return reject("malformed compressed records (lengths or counts out of range)");
  if (z.version != kBeaconVersion) return reject("unsupported records version");
  if (z.base_participant != 0 && base.empty()) return reject("compressed against a record not given");
  const auto declared = static_cast<std::size_t>(z.raw_size < 0 ? 0 : z.raw_size);
  if (z.raw_size < static_cast<std::int32_t>(kBatchHeaderBytes) || declared > kMaxInflatedBytes ||
      declared > kMaxInflateRatio * z.deflated.size())
    return reject("compressed records of an impossible size");
  std::vector<std::byte> raw(declared);
  if (!inflate_exactly(z.deflated, raw, z.base_participant != 0 ? base : std::span<const std::byte>{}))
    return reject("compressed records that do not inflate to their size (or against another base)");
  auto r = decode_records(raw, why);
  if (r && r->host_id != z.host_id) return reject("compressed records of another host");
  return r;
}

std::optional<std::vector<lcmx_msgs::beacon_t>> decode_any_records(std::span<const std::byte> bytes, std::string* why) {
  const auto fp = fingerprint_of(bytes);
  if (fp == lcmx_msgs::records_t::getHash() || fp == lcmx_msgs::records_z_t::getHash()) {
    auto r = decode_batch(bytes, why);
    if (!r) return std::nullopt;
    return std::move(r->records);
  }
  auto b = decode_beacon(bytes, why);
  if (!b) return std::nullopt;
  return std::vector<lcmx_msgs::beacon_t>{std::move(*b)};
}

}  // namespace lcmx::discovery
