#include "lcmx/discovery/beacon_codec.hpp"

#include <cstdint>
#include <cstring>

namespace lcmx::discovery {
namespace {

// Walks an LCM encoding without allocating. Every read checks the bytes left.
class Walker {
 public:
  explicit Walker(std::span<const std::byte> b) : b_(b) {}

  bool skip(std::size_t n) {
    if (n > b_.size() - pos_) return fail();
    pos_ += n;
    return ok_;
  }
  bool i8() { return skip(1); }
  bool i32(std::int32_t* out = nullptr) {
    if (4 > b_.size() - pos_) return fail();
    std::uint32_t v = 0;
    for (int i = 0; i < 4; ++i) v = (v << 8) | std::to_integer<std::uint32_t>(b_[pos_ + i]);
    pos_ += 4;
    if (out) *out = static_cast<std::int32_t>(v);
    return ok_;
  }
  bool i64() { return skip(8); }
  bool f64() { return skip(8); }
  // LCM string: int32 length including the NUL, then the bytes; the last must be NUL.
  bool str() {
    std::int32_t len = 0;
    if (!i32(&len) || len < 1) return fail();
    if (static_cast<std::size_t>(len) > b_.size() - pos_) return fail();
    // Exactly one NUL, at the end: LCM encoders stop at the first NUL, so a string with an
    // inner NUL was not written by one (and would not survive re-encoding).
    for (std::int32_t i = 0; i < len - 1; ++i)
      if (b_[pos_ + i] == std::byte{0}) return fail();
    if (b_[pos_ + len - 1] != std::byte{0}) return fail();
    pos_ += static_cast<std::size_t>(len);
    return ok_;
  }
  // A count field: non-negative and small enough that `count` elements of at least
  // `min_element` bytes fit in what is left.
  bool count(std::int32_t* n, std::size_t min_element) {
    if (!i32(n) || *n < 0) return fail();
    if (static_cast<std::size_t>(*n) * min_element > b_.size() - pos_) return fail();
    return ok_;
  }
  bool ok() const { return ok_; }

 private:
  bool fail() { ok_ = false; return false; }
  std::span<const std::byte> b_;
  std::size_t pos_ = 0;
  bool ok_ = true;
};

constexpr std::size_t kMinString = 5;  // int32 length + NUL

bool walk_match(Walker& w) {
  return w.i64() && w.i64() && w.str() && w.i64() && w.i64();
}

bool walk_endpoint(Walker& w) {
  // id, kind, node, topic, type_name, fingerprint, shm_segment, large, max_message_size,
  // history, messages, drops, rate_hz
  if (!(w.i64() && w.i8() && w.str() && w.str() && w.str() && w.i64() && w.str() && w.i8() &&
        w.i64() && w.i32() && w.i64() && w.i64() && w.f64()))
    return false;
  std::int32_t n = 0;
  if (!w.count(&n, 8 + 8 + kMinString + 8 + 8)) return false;
  for (std::int32_t i = 0; i < n; ++i)
    if (!walk_match(w)) return false;
  if (!w.count(&n, kMinString)) return false;
  for (std::int32_t i = 0; i < n; ++i)
    if (!w.str()) return false;
  return true;
}

bool walk_beacon(Walker& w) {
  // fingerprint, version, participant_id, host_id, pid, start_time, pid_namespace,
  // process_name, sequence, revision, flags, lease_ms, timestamp_us, scope, local_source,
  // vehicle_source
  if (!(w.i64() && w.i32() && w.i64() && w.i64() && w.i32() && w.i64() && w.i64() && w.str() &&
        w.i64() && w.i64() && w.i8() && w.i32() && w.i64() && w.i8() && w.str() && w.str()))
    return false;
  std::int32_t n = 0;
  if (!w.count(&n, kMinString)) return false;
  for (std::int32_t i = 0; i < n; ++i)
    if (!w.str()) return false;
  constexpr std::size_t kMinEndpoint = 8 + 1 + 4 * kMinString + 1 + 8 * 5 + 4 + 4 + 4;
  if (!w.count(&n, kMinEndpoint)) return false;
  for (std::int32_t i = 0; i < n; ++i)
    if (!walk_endpoint(w)) return false;
  if (!w.count(&n, kMinString)) return false;  // carried
  for (std::int32_t i = 0; i < n; ++i)
    if (!w.str()) return false;
  return w.ok();
}

}  // namespace

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
  std::int64_t hash = 0;
  for (int i = 0; i < 8; ++i)
    hash = static_cast<std::int64_t>((static_cast<std::uint64_t>(hash) << 8) |
                                     std::to_integer<std::uint8_t>(bytes[i]));
  if (hash != lcmx_msgs::beacon_t::getHash()) return reject("not a beacon_t (fingerprint)");
  Walker w(bytes);
  if (!walk_beacon(w)) return reject("malformed beacon (lengths or counts out of range)");
  lcmx_msgs::beacon_t b;
  if (b.decode(bytes.data(), 0, static_cast<int>(bytes.size())) < 0)
    return reject("lcm-gen decode failed");
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
  Walker w(bytes);
  std::int32_t n = 0, wanted = 0;
  // fingerprint, version, kind, scope, host_id, registry_id, speaker, sequence, lease_ms,
  // digest, count, num_entries, participants[], revisions[], target_host, num_wanted, wanted[]
  const bool ok = w.i64() && w.i32() && w.i8() && w.i8() && w.i64() && w.i64() && w.i64() && w.i64() &&
                  w.i32() && w.i64() && w.i32() && w.count(&n, 16) && w.skip(static_cast<std::size_t>(n) * 16) &&
                  w.i64() && w.count(&wanted, 8) && w.skip(static_cast<std::size_t>(wanted) * 8);
  if (!ok) return reject("malformed host beacon (lengths or counts out of range)");
  lcmx_msgs::host_beacon_t b;
  if (b.decode(bytes.data(), 0, static_cast<int>(bytes.size())) < 0) return reject("lcm-gen decode failed");
  if (b.version != kHostBeaconVersion) return reject("unsupported host beacon version");
  return b;
}

}  // namespace lcmx::discovery
