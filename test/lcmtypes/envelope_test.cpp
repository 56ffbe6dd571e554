// lcmx::lcmtypes' checked decoders (lcmx/lcmtypes/envelope.hpp) against lcm-gen's code, for
// every lcmx_msgs type: random messages encoded by lcm-gen decode and re-encode to the same
// bytes; every truncation, a byte after the end, malformed strings and booleans are refused;
// and whatever the bytes (hostile counts at every offset, random mutations), a decode
// allocates at most 8 bytes per input byte (counted by this program's operator new).
#include <catch2/catch.hpp>
#include <cstdlib>
#include <cstring>
#include <new>
#include <random>
#include <string>
#include <vector>

#include "lcmx/lcmtypes/envelope.hpp"

// --- Allocation counting (this test program only) --------------------------------------------

namespace {
thread_local bool g_counting = false;
thread_local std::size_t g_allocated = 0;
}  // namespace

#if defined(__SANITIZE_ADDRESS__)
// Under AddressSanitizer its allocator serves operator new (replacing it here mixes allocators):
// its allocation hook counts instead (libsanitizer's public interface).
extern "C" int __sanitizer_install_malloc_and_free_hooks(void (*malloc_hook)(const volatile void*, std::size_t),
                                                          void (*free_hook)(const volatile void*));
namespace {
void count_allocation(const volatile void*, std::size_t n) {
  if (g_counting) g_allocated += n;
}
[[maybe_unused]] const int g_hooks_installed = __sanitizer_install_malloc_and_free_hooks(count_allocation, nullptr);
}  // namespace
#else
void* operator new(std::size_t n) {
  if (g_counting) g_allocated += n;
  if (void* p = std::malloc(n == 0 ? 1 : n)) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n) { return ::operator new(n); }
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }
#endif

namespace {

using namespace lcmx_msgs;
using Bytes = std::vector<std::byte>;

// What a decode of `in` into a fresh T allocated (the object's own buffers), and whether it
// accepted the bytes.
template <class T>
std::pair<bool, std::size_t> counted_decode(std::span<const std::byte> in) {
  T out{};
  g_allocated = 0;
  g_counting = true;
  bool ok = false;
  try {
    ok = lcmx::lcmtypes::decode(in, out);
  } catch (const std::bad_alloc&) {
    g_counting = false;
    FAIL("a decode of " << in.size() << " bytes ran out of memory");
  }
  g_counting = false;
  return {ok, g_allocated};
}

constexpr std::size_t bound(std::size_t input) { return 8 * input + 64; }

// --- Random messages ---------------------------------------------------------------------------

struct Gen {
  std::mt19937_64 rng;
  explicit Gen(std::uint64_t seed) : rng(seed) {}
  std::int64_t i64() { return static_cast<std::int64_t>(rng()); }
  std::int32_t i32() { return static_cast<std::int32_t>(rng()); }
  std::int8_t i8() { return static_cast<std::int8_t>(rng()); }
  double f64() {
    const std::uint64_t v = rng();
    double d;
    std::memcpy(&d, &v, sizeof d);
    return d;
  }
  std::size_t small(std::size_t max) { return static_cast<std::size_t>(rng() % (max + 1)); }
  // Strings with no NUL (lcm-gen writes a string up to its first NUL), short and long.
  std::string str() {
    std::string s(small(rng() % 4 == 0 ? 40 : 8), 'x');
    for (auto& c : s) c = static_cast<char>(1 + rng() % 255);
    return s;
  }
  std::vector<std::uint8_t> bytes() {
    std::vector<std::uint8_t> v(small(rng() % 4 == 0 ? 300 : 6));
    for (auto& b : v) b = static_cast<std::uint8_t>(rng());
    return v;
  }
  std::vector<std::string> strs(std::int32_t& n) {
    std::vector<std::string> v(small(3));
    for (auto& s : v) s = str();
    n = static_cast<std::int32_t>(v.size());
    return v;
  }
};

void fill(Gen& g, match_t& m) {
  m.publisher_participant = g.i64();
  m.publisher_endpoint = g.i64();
  m.path = g.str();
  m.received = g.i64();
  m.drops = g.i64();
}
void fill(Gen& g, endpoint_t& e) {
  e.id = g.i64();
  e.kind = g.i8();
  e.node = g.str();
  e.topic = g.str();
  e.type_name = g.str();
  e.fingerprint = g.i64();
  e.shm_segment = g.str();
  e.large = g.i8();
  e.max_message_size = g.i64();
  e.history = g.i32();
  e.messages = g.i64();
  e.drops = g.i64();
  e.rate_hz = g.f64();
  e.matches.resize(g.small(3));
  for (auto& m : e.matches) fill(g, m);
  e.num_matches = static_cast<std::int32_t>(e.matches.size());
  e.errors = g.strs(e.num_errors);
}
void fill(Gen& g, beacon_t& b) {
  b.version = g.i32();
  b.participant_id = g.i64();
  b.host_id = g.i64();
  b.pid = g.i32();
  b.start_time = g.i64();
  b.pid_namespace = g.i64();
  b.process_name = g.str();
  b.sequence = g.i64();
  b.revision = g.i64();
  b.flags = g.i8();
  b.lease_ms = g.i32();
  b.timestamp_us = g.i64();
  b.scope = g.i8();
  b.local_source = g.str();
  b.vehicle_source = g.str();
  b.nodes = g.strs(b.num_nodes);
  b.endpoints.resize(g.small(3));
  for (auto& e : b.endpoints) fill(g, e);
  b.num_endpoints = static_cast<std::int32_t>(b.endpoints.size());
  b.carried = g.strs(b.num_carried);
}
void fill(Gen& g, marker_t& m) {
  m.version = g.i32();
  m.participant_id = g.i64();
  m.host_id = g.i64();
  m.channel = g.str();
  m.count = g.i64();
}
void fill(Gen& g, host_beacon_t& h) {
  h.version = g.i32();
  h.kind = g.i8();
  h.scope = g.i8();
  h.host_id = g.i64();
  h.registry_id = g.i64();
  h.speaker = g.i64();
  h.sequence = g.i64();
  h.lease_ms = g.i32();
  h.digest = g.i64();
  h.count = g.i32();
  h.num_entries = static_cast<std::int32_t>(g.small(4));
  h.participants.resize(h.num_entries);
  h.revisions.resize(h.num_entries);
  for (auto& v : h.participants) v = g.i64();
  for (auto& v : h.revisions) v = g.i64();
  h.target_host = g.i64();
  h.wanted.resize(g.small(3));
  for (auto& v : h.wanted) v = g.i64();
  h.num_wanted = static_cast<std::int32_t>(h.wanted.size());
}
void fill(Gen& g, records_t& r) {
  r.version = g.i32();
  r.host_id = g.i64();
  r.records.resize(g.small(3));
  for (auto& b : r.records) fill(g, b);
  r.num_records = static_cast<std::int32_t>(r.records.size());
  r.state.resize(g.small(1));
  for (auto& h : r.state) fill(g, h);
  r.num_state = static_cast<std::int32_t>(r.state.size());
}
void fill(Gen& g, records_z_t& r) {
  r.version = g.i32();
  r.host_id = g.i64();
  r.base_participant = g.i64();
  r.base_revision = g.i64();
  r.raw_size = g.i32();
  r.deflated = g.bytes();
  r.num_bytes = static_cast<std::int32_t>(r.deflated.size());
}
void fill(Gen& g, history_message_t& m) {
  m.sent = g.i8();
  m.sequence = g.i32();
  m.data = g.bytes();
  m.size = static_cast<std::int32_t>(m.data.size());
}
void fill(Gen& g, history_t& h) {
  h.publisher_participant = g.i64();
  h.publisher_endpoint = g.i64();
  h.subscriber_participant = g.i64();
  h.subscriber_endpoint = g.i64();
  h.channel = g.str();
  h.messages.resize(g.small(4));
  for (auto& m : h.messages) fill(g, m);
  h.num_messages = static_cast<std::int32_t>(h.messages.size());
}
void fill(Gen& g, service_request_t& r) {
  r.client_id = g.i64();
  r.request_id = g.i64();
  r.server_participant = g.i64();
  r.server_id = g.i64();
  r.client_participant = g.i64();
  r.request_fingerprint = g.i64();
  r.response_fingerprint = g.i64();
  r.reply_channel = g.str();
  r.payload = g.bytes();
  r.size = static_cast<std::int32_t>(r.payload.size());
}
void fill(Gen& g, service_reply_t& r) {
  r.client_id = g.i64();
  r.request_id = g.i64();
  r.server_participant = g.i64();
  r.server_id = g.i64();
  r.reply_endpoint = g.i64();
  r.request_fingerprint = g.i64();
  r.response_fingerprint = g.i64();
  r.request_type = g.str();
  r.response_type = g.str();
  r.status = g.i8();
  r.error = g.str();
  r.payload = g.bytes();
  r.size = static_cast<std::int32_t>(r.payload.size());
}
void fill(Gen& g, action_goal_t& m) {
  m.goal_id = g.str();
  m.client_id = g.i64();
  m.goal_fingerprint = g.i64();
  m.feedback_fingerprint = g.i64();
  m.result_fingerprint = g.i64();
  m.goal = g.bytes();
  m.size = static_cast<std::int32_t>(m.goal.size());
}
void fill(Gen& g, action_goal_reply_t& m) {
  m.accepted = g.rng() % 2;
  m.types_ok = g.rng() % 2;
  m.message = g.str();
  m.cancel_server_id = g.i64();
  m.result_server_id = g.i64();
  m.goal_type = g.str();
  m.feedback_type = g.str();
  m.result_type = g.str();
}
void fill(Gen& g, action_goal_ref_t& m) { m.goal_id = g.str(); }
void fill(Gen& g, action_goal_status_t& m) {
  m.goal_id = g.str();
  m.state = g.i8();
  m.message = g.str();
  m.feedback_count = g.i32();
}
void fill(Gen& g, action_result_t& m) {
  fill(g, m.status);
  m.result = g.bytes();
  m.size = static_cast<std::int32_t>(m.result.size());
}
void fill(Gen& g, action_feedback_t& m) {
  m.goal_id = g.str();
  m.feedback = g.bytes();
  m.size = static_cast<std::int32_t>(m.feedback.size());
}
void fill(Gen& g, action_status_t& m) {
  m.server_participant = g.i64();
  m.goal_server_id = g.i64();
  m.cancel_server_id = g.i64();
  m.result_server_id = g.i64();
  m.goal_type = g.str();
  m.feedback_type = g.str();
  m.result_type = g.str();
  m.goal_fingerprint = g.i64();
  m.feedback_fingerprint = g.i64();
  m.result_fingerprint = g.i64();
  m.goals.resize(g.small(4));
  for (auto& s : m.goals) fill(g, s);
  m.num_goals = static_cast<std::int32_t>(m.goals.size());
}
void fill(Gen& g, bridge_link_status_t& m) {
  m.name = g.str();
  m.address = g.str();
  m.up = g.i8();
  m.active = g.i8();
  m.bytes_sent = g.i64();
  m.bytes_received = g.i64();
  m.heartbeat_age_ms = g.i64();
  m.rtt_us = g.i32();
}
void fill(Gen& g, bridge_channel_status_t& m) {
  m.name = g.str();
  m.messages_sent = g.i64();
  m.bytes_sent = g.i64();
  m.drops = g.i64();
  m.queued = g.i32();
  m.messages_received = g.i64();
  m.bytes_received = g.i64();
  m.lost = g.i64();
}
void fill(Gen& g, bridge_peer_status_t& m) {
  m.name = g.str();
  m.up = g.i8();
  m.active_link = g.str();
  m.failovers = g.i64();
  m.links.resize(g.small(2));
  for (auto& l : m.links) fill(g, l);
  m.num_links = static_cast<std::int32_t>(m.links.size());
  m.channels.resize(g.small(2));
  for (auto& c : m.channels) fill(g, c);
  m.num_channels = static_cast<std::int32_t>(m.channels.size());
  m.served = g.strs(m.num_served);
  m.wanted = g.strs(m.num_wanted);
}
void fill(Gen& g, bridge_status_t& m) {
  m.timestamp_us = g.i64();
  m.name = g.str();
  m.host_id = g.i64();
  m.pid = g.i32();
  m.curve = g.i8();
  m.bad_frames = g.i64();
  m.peers.resize(g.small(2));
  for (auto& p : m.peers) fill(g, p);
  m.num_peers = static_cast<std::int32_t>(m.peers.size());
  m.demand = g.strs(m.num_demand);
  m.zero_copy_sends = g.i64();
  m.copied_sends = g.i64();
  m.lost_local = g.i64();
}

template <class T>
Bytes lcm_encode(const T& m) {
  return lcmx::lcmtypes::encode(m);
}

// Writes a big-endian int32 at `off`.
void put32(Bytes& b, std::size_t off, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) b[off + i] = static_cast<std::byte>(v >> (24 - 8 * i));
}

// Everything this file checks for one type.
template <class T>
void check_type(const char* name) {
  INFO(name);
  Gen g(std::hash<std::string>{}(name));
  for (int round = 0; round < 200; ++round) {
    T m{};
    fill(g, m);
    const Bytes bytes = lcm_encode(m);
    // Round trip: lcm-gen's encoding decodes, and re-encodes to the same bytes.
    auto [ok, allocated] = counted_decode<T>(bytes);
    REQUIRE(ok);
    CHECK(allocated <= bound(bytes.size()));
    T back{};
    REQUIRE(lcmx::lcmtypes::decode(bytes, back));
    REQUIRE(lcm_encode(back) == bytes);
    // lcm-gen's own decode agrees.
    T theirs{};
    REQUIRE(theirs.decode(bytes.data(), 0, static_cast<int>(bytes.size())) == static_cast<int>(bytes.size()));
    REQUIRE(lcm_encode(theirs) == bytes);
    if (round < 20) {
      // Every truncation, and one byte more, are refused.
      for (std::size_t n = 0; n < bytes.size(); ++n) {
        T t{};
        if (lcmx::lcmtypes::decode(std::span(bytes.data(), n), t)) FAIL("a truncation to " << n << " bytes decoded");
      }
      Bytes longer = bytes;
      longer.push_back(std::byte{0});
      T t{};
      CHECK_FALSE(lcmx::lcmtypes::decode(longer, t));
      // Another type's fingerprint.
      Bytes other = bytes;
      other[7] ^= std::byte{1};
      CHECK_FALSE(lcmx::lcmtypes::decode(other, t));
      // Hostile counts and lengths at every offset: never more than the bound allocated.
      for (std::uint32_t v : {0x7fffffffu, 0x80000000u, 0xffffffffu, 50000000u, 0u}) {
        for (std::size_t off = 8; off + 4 <= bytes.size(); ++off) {
          Bytes bad = bytes;
          put32(bad, off, v);
          const auto [bad_ok, bad_allocated] = counted_decode<T>(bad);
          if (bad_allocated > bound(bad.size()))
            FAIL("offset " << off << " value " << v << ": " << bad_allocated << " bytes allocated for "
                           << bad.size());
          if (bad_ok) {  // accepted: it must be an encoding lcm-gen writes
            T again{};
            REQUIRE(lcmx::lcmtypes::decode(bad, again));
            REQUIRE(lcm_encode(again) == bad);
          }
        }
      }
    }
    // Random mutations: refused or canonical, and bounded either way.
    for (int k = 0; k < 20; ++k) {
      Bytes bad = bytes;
      const int flips = 1 + static_cast<int>(g.rng() % 4);
      for (int f = 0; f < flips; ++f) bad[8 + g.rng() % (bad.size() - 8)] = static_cast<std::byte>(g.rng());
      const auto [bad_ok, bad_allocated] = counted_decode<T>(bad);
      CHECK(bad_allocated <= bound(bad.size()));
      if (bad_ok) {
        T again{};
        REQUIRE(lcmx::lcmtypes::decode(bad, again));
        REQUIRE(lcm_encode(again) == bad);
      }
    }
  }
}

}  // namespace

TEST_CASE("envelopes: every lcmx_msgs type round-trips with lcm-gen, refuses every truncation, allocates a bounded amount",
          "[lcmtypes]") {
  check_type<match_t>("match_t");
  check_type<endpoint_t>("endpoint_t");
  check_type<beacon_t>("beacon_t");
  check_type<host_beacon_t>("host_beacon_t");
  check_type<marker_t>("marker_t");
  check_type<records_t>("records_t");
  check_type<records_z_t>("records_z_t");
  check_type<history_message_t>("history_message_t");
  check_type<history_t>("history_t");
  check_type<service_request_t>("service_request_t");
  check_type<service_reply_t>("service_reply_t");
  check_type<action_goal_t>("action_goal_t");
  check_type<action_goal_reply_t>("action_goal_reply_t");
  check_type<action_goal_ref_t>("action_goal_ref_t");
  check_type<action_goal_status_t>("action_goal_status_t");
  check_type<action_result_t>("action_result_t");
  check_type<action_feedback_t>("action_feedback_t");
  check_type<action_status_t>("action_status_t");
  check_type<bridge_link_status_t>("bridge_link_status_t");
  check_type<bridge_channel_status_t>("bridge_channel_status_t");
  check_type<bridge_peer_status_t>("bridge_peer_status_t");
  check_type<bridge_status_t>("bridge_status_t");
}

TEST_CASE("envelopes: the history bomb of issue 34 (70 bytes that say 50,000,000 messages) allocates nothing",
          "[lcmtypes]") {
  history_t h{};
  h.channel = "POSE";
  h.num_messages = 0;
  Bytes bomb = lcm_encode(h);
  put32(bomb, bomb.size() - 4, 50000000u);  // num_messages, the last field
  bomb.resize(70, std::byte{0x41});
  const auto [ok, allocated] = counted_decode<history_t>(bomb);
  CHECK_FALSE(ok);
  CHECK(allocated < 64);  // the channel name fits std::string's own buffer
  // lcm-gen's decode of the same bytes sizes the vector first (50,000,000 x 40 bytes): not run.
}

TEST_CASE("envelopes: an array inside an array element counts only the bytes its later siblings leave",
          "[lcmtypes]") {
  // The fuzz_bridge_status find of 2026-11-29: a bridge_status_t whose num_peers claims all
  // the bytes (35 a peer), and whose first peer's num_served claims them again (5 a string).
  // Each count alone fits; together they sized 12 bytes of vectors per input byte.
  bridge_peer_status_t peer{};
  peer.num_served = 1000;
  peer.served.assign(1000, std::string());
  bridge_status_t status{};
  status.peers.push_back(peer);
  status.num_peers = 1;
  Bytes bytes = lcm_encode(status);
  REQUIRE(counted_decode<bridge_status_t>(bytes).first);  // as lcm-gen wrote it
  // The same bytes, saying as many peers as the bytes could hold alone, and nothing after
  // the first peer's strings (so it ends early whatever happens).
  const std::size_t num_peers_at = 8 + 8 + 5 + 8 + 4 + 1 + 8;
  const std::size_t tail = 4 + 3 * 8;  // num_demand and the three counters after the peers
  bytes.resize(bytes.size() - tail);
  put32(bytes, num_peers_at, static_cast<std::uint32_t>((bytes.size() - num_peers_at - 4) / 35));
  const auto [ok, allocated] = counted_decode<bridge_status_t>(bytes);
  CHECK_FALSE(ok);
  CHECK(allocated <= bound(bytes.size()));

  // The same shape two levels deeper: records_t -> beacon_t (97 bytes at least) ->
  // endpoint_t -> its errors.
  endpoint_t e{};
  e.errors.assign(1000, std::string());
  e.num_errors = 1000;
  beacon_t b{};
  b.endpoints.push_back(e);
  b.num_endpoints = 1;
  records_t r{};
  r.records.push_back(b);
  r.num_records = 1;
  Bytes rb = lcm_encode(r);
  REQUIRE(counted_decode<records_t>(rb).first);
  rb.resize(rb.size() - 4 - 4);  // the beacon's num_carried, then num_state
  const std::size_t num_records_at = 8 + 4 + 8;
  put32(rb, num_records_at, static_cast<std::uint32_t>((rb.size() - num_records_at - 4) / 97));
  const auto [rok, rallocated] = counted_decode<records_t>(rb);
  CHECK_FALSE(rok);
  CHECK(rallocated <= bound(rb.size()));
}

TEST_CASE("envelopes: strings need one NUL, at their end, booleans are 0 or 1", "[lcmtypes]") {
  action_goal_ref_t ref;
  ref.goal_id = "abc";
  const Bytes good = lcm_encode(ref);  // fingerprint, int32 4, 'a' 'b' 'c' NUL
  REQUIRE(good.size() == 8 + 4 + 4);
  action_goal_ref_t out;
  REQUIRE(lcmx::lcmtypes::decode(good, out));
  CHECK(out.goal_id == "abc");
  Bytes bad = good;
  bad[13] = std::byte{0};  // "a\0c\0": an inner NUL
  CHECK_FALSE(lcmx::lcmtypes::decode(bad, out));
  bad = good;
  bad[15] = std::byte{'d'};  // no NUL at the end
  CHECK_FALSE(lcmx::lcmtypes::decode(bad, out));
  for (std::uint32_t len : {0u, 0xffffffffu, 5u}) {  // empty (no room for a NUL), negative, past the end
    bad = good;
    put32(bad, 8, len);
    CHECK_FALSE(lcmx::lcmtypes::decode(bad, out));
  }
  action_goal_reply_t reply{};
  reply.accepted = true;
  Bytes b = lcm_encode(reply);
  action_goal_reply_t r2;
  REQUIRE(lcmx::lcmtypes::decode(b, r2));
  b[8] = std::byte{2};
  CHECK_FALSE(lcmx::lcmtypes::decode(b, r2));
}

TEST_CASE("envelopes: service headers are views in place, and encode as lcm-gen does", "[lcmtypes]") {
  service_reply_t r{};
  r.client_id = 7;
  r.request_id = 9;
  r.server_participant = -3;
  r.request_type = "pose_t";
  r.response_type = "bench_t";
  r.status = service_reply_t::HANDLER_FAILED;
  r.error = "it threw";
  r.payload = {1, 2, 3, 4, 5};
  r.size = 5;
  const Bytes bytes = lcm_encode(r);
  lcmx::lcmtypes::ServiceReplyHeader h;
  std::span<const std::byte> payload;
  REQUIRE(lcmx::lcmtypes::decode(bytes, h, payload));
  CHECK(h.client_id == 7);
  CHECK(h.request_id == 9);
  CHECK(h.server_participant == -3);
  CHECK(h.request_type == "pose_t");
  CHECK(h.error == "it threw");
  CHECK(h.status == service_reply_t::HANDLER_FAILED);
  CHECK(payload.data() == bytes.data() + bytes.size() - 5);  // where it lies: no copy
  CHECK(payload.size() == 5);
  CHECK(h.error.data() > reinterpret_cast<const char*>(bytes.data()));
  // The header writer and a payload after it give lcm-gen's bytes.
  Bytes mine(lcmx::lcmtypes::header_size(h) + 5);
  REQUIRE(lcmx::lcmtypes::encode_header(h, 5, mine));
  std::memcpy(mine.data() + lcmx::lcmtypes::header_size(h), r.payload.data(), 5);
  CHECK(mine == bytes);
  // Too short an output is refused, never overrun.
  Bytes small(lcmx::lcmtypes::header_size(h) - 1);
  CHECK_FALSE(lcmx::lcmtypes::encode_header(h, 5, small));

  service_request_t q{};
  q.client_id = 1;
  q.request_id = 2;
  q.server_participant = 3;
  q.server_id = 4;
  q.reply_channel = "svc/rp/0000000000000001";
  q.payload = {9};
  q.size = 1;
  const Bytes qb = lcm_encode(q);
  lcmx::lcmtypes::ServiceRequestHeader qh;
  REQUIRE(lcmx::lcmtypes::decode(qb, qh, payload));
  CHECK(qh.reply_channel == "svc/rp/0000000000000001");
  Bytes qm(lcmx::lcmtypes::header_size(qh) + 1);
  REQUIRE(lcmx::lcmtypes::encode_header(qh, 1, qm));
  qm.back() = std::byte{9};
  CHECK(qm == qb);
  // The target sits where a client patches it on fail-over.
  std::int64_t target = 0;
  for (int i = 0; i < 8; ++i)
    target = (target << 8) | std::to_integer<std::int64_t>(qb[lcmx::lcmtypes::kServiceRequestTargetOffset + i]);
  CHECK(target == 3);
  // A string with an inner NUL is written up to it, as lcm-gen writes it.
  qh.reply_channel = std::string_view("ab\0cd", 5);
  Bytes nul(lcmx::lcmtypes::header_size(qh));
  REQUIRE(lcmx::lcmtypes::encode_header(qh, 0, nul));
  lcmx::lcmtypes::ServiceRequestHeader back;
  REQUIRE(lcmx::lcmtypes::decode(nul, back, payload));
  CHECK(back.reply_channel == "ab");
}
