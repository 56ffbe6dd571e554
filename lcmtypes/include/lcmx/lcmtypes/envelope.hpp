// lcmx's own envelopes (lcmtypes/*.lcm: beacons, keep-last-N replays, service and action
// envelopes, bridge status) decoded from bytes that come from the network or a file, bounded
// before anything is allocated (DESIGN.md "Trust").
//
// One way for every envelope: a Reader walks the LCM encoding (big-endian, as lcm-gen writes
// it) and checks each read against the bytes left; an array's count is checked against the
// bytes left (count x the smallest encoding of one element) before anything is sized. So a
// decode allocates at most a small multiple of the input's size (at most 8 bytes per input
// byte: the largest ratio is a std::string, 32 bytes, for the 5 bytes of an empty LCM string),
// whatever the counts say; lcm-gen's own decode resizes to any count first.
//
// decode(bytes, T&) accepts exactly lcm-gen's encoding of a T (its fingerprint first): what
// lcm-gen's encode writes for a T decodes to an equal T, and what decodes re-encodes to the
// same bytes. Stricter than lcm-gen's decode, which is what makes that hold: a string must
// have one NUL, at its end (lcm-gen writes strings up to their first NUL); a boolean is 0 or
// 1; nothing may follow the encoding. Everything else, every truncation included, is refused
// (false; `out` is then partly written and must not be used).
//
// Services read payloads where they lie (in shared memory): ServiceRequestHeader and
// ServiceReplyHeader decode the envelope fields with views into the bytes, and the encoders
// write a header in front of a payload the caller writes in place.
//
// Thread safety: free functions on the caller's objects; nothing is shared. Errors: decoders
// return false, never throw (except std::bad_alloc from the owning decoders); encoders return
// false when the output span is too short.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "lcmx_msgs/action_feedback_t.hpp"
#include "lcmx_msgs/action_goal_ref_t.hpp"
#include "lcmx_msgs/action_goal_reply_t.hpp"
#include "lcmx_msgs/action_goal_status_t.hpp"
#include "lcmx_msgs/action_goal_t.hpp"
#include "lcmx_msgs/action_result_t.hpp"
#include "lcmx_msgs/action_status_t.hpp"
#include "lcmx_msgs/beacon_t.hpp"
#include "lcmx_msgs/bridge_status_t.hpp"
#include "lcmx_msgs/history_t.hpp"
#include "lcmx_msgs/host_beacon_t.hpp"
#include "lcmx_msgs/marker_t.hpp"
#include "lcmx_msgs/records_t.hpp"
#include "lcmx_msgs/records_z_t.hpp"
#include "lcmx_msgs/service_reply_t.hpp"
#include "lcmx_msgs/service_request_t.hpp"

namespace lcmx::lcmtypes {

// A bounded cursor over one LCM encoding. Every read checks the bytes left; the first failed
// check makes the Reader fail for good (ok() false) and every later read returns 0 or empty.
// Views (string(), bytes()) point into the input and live as long as it does.
class Reader {
 public:
  explicit Reader(std::span<const std::byte> bytes) noexcept : b_(bytes) {}

  bool ok() const noexcept { return ok_; }
  std::size_t left() const noexcept { return b_.size() - pos_; }
  std::size_t offset() const noexcept { return pos_; }
  // Everything was read and nothing failed.
  bool done() const noexcept { return ok_ && pos_ == b_.size(); }
  // Marks the encoding malformed (a value out of range). Returns false.
  bool fail() noexcept {
    ok_ = false;
    return false;
  }

  std::int8_t i8() noexcept { return need(1) ? static_cast<std::int8_t>(b_[pos_++]) : 0; }
  std::int16_t i16() noexcept { return static_cast<std::int16_t>(be(2)); }
  std::int32_t i32() noexcept { return static_cast<std::int32_t>(be(4)); }
  std::int64_t i64() noexcept { return static_cast<std::int64_t>(be(8)); }
  float f32() noexcept {
    const auto v = static_cast<std::uint32_t>(be(4));
    float f;
    std::memcpy(&f, &v, sizeof f);
    return f;
  }
  double f64() noexcept {
    const std::uint64_t v = be(8);
    double d;
    std::memcpy(&d, &v, sizeof d);
    return d;
  }
  // LCM's boolean: one byte, 0 or 1 (what every LCM encoder writes).
  bool boolean() noexcept {
    const auto v = i8();
    if (v != 0 && v != 1) fail();
    return v == 1;
  }
  // An LCM string: int32 length counting the NUL (1 .. left), the bytes with no NUL among
  // them, then the NUL. The view excludes the NUL.
  std::string_view string() noexcept {
    const std::int32_t n = i32();
    if (!ok_ || n < 1 || static_cast<std::size_t>(n) > left()) return fail(), std::string_view();
    const char* p = reinterpret_cast<const char*>(b_.data() + pos_);
    const auto len = static_cast<std::size_t>(n) - 1;
    if (p[len] != '\0' || std::memchr(p, 0, len) != nullptr) return fail(), std::string_view();
    pos_ += static_cast<std::size_t>(n);
    return {p, len};
  }
  // The next `n` bytes, in place.
  std::span<const std::byte> bytes(std::size_t n) noexcept {
    if (!need(n)) return {};
    const auto s = b_.subspan(pos_, n);
    pos_ += n;
    return s;
  }
  // The bytes an array's count may claim: those left, less those held for the later
  // elements of the arrays being read (Hold).
  std::size_t room() const noexcept { return left() > held_ ? left() - held_ : 0; }
  // An array's length (an int32 read just before, or a size member): refused when negative
  // or when `n` elements of at least `min_element_size` encoded bytes each cannot fit in the
  // room left. Check it before sizing anything for the array. Returns n, or 0 on failure.
  std::size_t count(std::int32_t n, std::size_t min_element_size) noexcept {
    if (!ok_ || n < 0) return fail(), 0;
    if (min_element_size != 0 && static_cast<std::size_t>(n) > room() / min_element_size) return fail(), 0;
    return static_cast<std::size_t>(n);
  }
  // While one element of an array is read, the bytes its later siblings need at least are
  // held: an array inside the element cannot count them too. Without it a nested count could
  // claim the bytes its parent's count already claimed (a 5 KB bridge_status_t sized 12 bytes
  // of vectors per input byte). Scoped; holds nest.
  class Hold {
   public:
    Hold(Reader& r, std::size_t bytes) noexcept : r_(r), bytes_(bytes) { r_.held_ += bytes_; }
    ~Hold() { r_.held_ -= bytes_; }
    Hold(const Hold&) = delete;
    Hold& operator=(const Hold&) = delete;

   private:
    Reader& r_;
    std::size_t bytes_;
  };
  // The 8-byte fingerprint an LCM message starts with; fails unless it is `expected`.
  bool fingerprint(std::int64_t expected) noexcept { return i64() == expected && ok_ ? true : fail(); }

 private:
  bool need(std::size_t n) noexcept {
    if (!ok_ || n > left()) return fail();
    return true;
  }
  std::uint64_t be(int n) noexcept {
    if (!need(static_cast<std::size_t>(n))) return 0;
    std::uint64_t v = 0;
    for (int i = 0; i < n; ++i) v = (v << 8) | std::to_integer<std::uint64_t>(b_[pos_++]);
    return v;
  }

  std::span<const std::byte> b_;
  std::size_t pos_ = 0;
  std::size_t held_ = 0;  // Hold
  bool ok_ = true;
};

// The encoded size of an LCM string (int32 length, the bytes up to the first NUL, the NUL):
// what lcm-gen writes for it.
inline std::size_t encoded_string_size(std::string_view s) noexcept {
  const void* nul = s.empty() ? nullptr : std::memchr(s.data(), 0, s.size());  // (an empty view's data() may be null)
  const std::size_t len = nul ? static_cast<std::size_t>(static_cast<const char*>(nul) - s.data()) : s.size();
  return 4 + len + 1;
}

// Writes an LCM encoding into a span, checking its end (ok() false once a write did not fit;
// nothing is written past the span). Strings are written as lcm-gen writes them: up to
// their first NUL.
class Writer {
 public:
  explicit Writer(std::span<std::byte> out) noexcept : b_(out) {}
  bool ok() const noexcept { return ok_; }
  std::size_t offset() const noexcept { return pos_; }

  void i8(std::int8_t v) noexcept { be(static_cast<std::uint8_t>(v), 1); }
  void i32(std::int32_t v) noexcept { be(static_cast<std::uint32_t>(v), 4); }
  void i64(std::int64_t v) noexcept { be(static_cast<std::uint64_t>(v), 8); }
  void string(std::string_view s) noexcept {
    const std::size_t len = encoded_string_size(s) - 5;
    if (!need(len + 5)) return;
    i32(static_cast<std::int32_t>(len + 1));
    if (len > 0) std::memcpy(b_.data() + pos_, s.data(), len);
    pos_ += len;
    b_[pos_++] = std::byte{0};
  }
  void bytes(std::span<const std::byte> s) noexcept {
    if (!need(s.size())) return;
    if (!s.empty()) std::memcpy(b_.data() + pos_, s.data(), s.size());
    pos_ += s.size();
  }

 private:
  bool need(std::size_t n) noexcept {
    if (!ok_ || n > b_.size() - pos_) return ok_ = false;
    return true;
  }
  void be(std::uint64_t v, int n) noexcept {
    if (!need(static_cast<std::size_t>(n))) return;
    for (int i = n - 1; i >= 0; --i) b_[pos_++] = static_cast<std::byte>((v >> (8 * i)) & 0xff);
  }

  std::span<std::byte> b_;
  std::size_t pos_ = 0;
  bool ok_ = true;
};

// --- Checked decoders: one per lcmx_msgs type (see the file comment) -----------------------

bool decode(std::span<const std::byte> bytes, lcmx_msgs::beacon_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::host_beacon_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::marker_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::records_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::records_z_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::endpoint_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::match_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::history_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::history_message_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::service_request_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::service_reply_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::action_goal_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::action_goal_reply_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::action_goal_ref_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::action_goal_status_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::action_result_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::action_feedback_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::action_status_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::bridge_status_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::bridge_peer_status_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::bridge_link_status_t& out);
bool decode(std::span<const std::byte> bytes, lcmx_msgs::bridge_channel_status_t& out);

// lcm-gen's encoding of `m` (fingerprint first), for envelopes built as lcm-gen structs.
template <class T>
std::vector<std::byte> encode(const T& m) {
  std::vector<std::byte> b(static_cast<std::size_t>(m.getEncodedSize()));
  m.encode(b.data(), 0, static_cast<int>(b.size()));
  return b;
}

// --- Service envelopes in place ------------------------------------------------------------

// service_request_t up to its payload. Decoded views point into the decoded bytes.
struct ServiceRequestHeader {
  std::int64_t client_id = 0, request_id = 0, server_participant = 0, server_id = 0,
               client_participant = 0, request_fingerprint = 0, response_fingerprint = 0;
  std::string_view reply_channel;
};
// Byte offset of (server_participant, server_id) in an encoded request: a client patches the
// target in place when it sends a call to another server.
inline constexpr std::size_t kServiceRequestTargetOffset = 8 + 8 + 8;

// service_reply_t up to its payload.
struct ServiceReplyHeader {
  std::int64_t client_id = 0, request_id = 0, server_participant = 0, server_id = 0,
               reply_endpoint = 0, request_fingerprint = 0, response_fingerprint = 0;
  std::string_view request_type, response_type;
  std::int8_t status = lcmx_msgs::service_reply_t::OK;
  std::string_view error;
};

// Bytes from the fingerprint through the payload's size field: the payload follows.
std::size_t header_size(const ServiceRequestHeader& h) noexcept;
std::size_t header_size(const ServiceReplyHeader& h) noexcept;
// Writes the header (fingerprint first) and a payload size of `payload_size` into the first
// header_size(h) bytes of `out`; the caller writes the payload after it. False (nothing
// usable written) when `out` is too short or payload_size exceeds INT32_MAX.
bool encode_header(const ServiceRequestHeader& h, std::size_t payload_size, std::span<std::byte> out) noexcept;
bool encode_header(const ServiceReplyHeader& h, std::size_t payload_size, std::span<std::byte> out) noexcept;
// Decodes an envelope whose payload stays where it lies: `payload` views the bytes. As the
// owning decoders: exactly one encoding, every count checked; false for anything else.
bool decode(std::span<const std::byte> bytes, ServiceRequestHeader& h, std::span<const std::byte>& payload) noexcept;
bool decode(std::span<const std::byte> bytes, ServiceReplyHeader& h, std::span<const std::byte>& payload) noexcept;

}  // namespace lcmx::lcmtypes
