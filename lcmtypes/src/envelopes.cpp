// Checked decoders of lcmx's own envelopes (lcmx/lcmtypes/envelope.hpp): each struct's fields
// in the order of its .lcm file (lcmtypes/*.lcm), read with a Reader; every array's count is
// checked against the bytes left before the array is sized. A nested struct's fields follow
// in place (no fingerprint of its own inside its parent), as lcm-gen lays them out.
#include "lcmx/lcmtypes/envelope.hpp"

#include <climits>

namespace lcmx::lcmtypes {
namespace {

using namespace lcmx_msgs;

// The smallest encodings, for counts: an LCM string is an int32 length and its NUL.
constexpr std::size_t kString = 4 + 1;
constexpr std::size_t kMatch = 8 + 8 + kString + 8 + 8;
constexpr std::size_t kEndpoint = 8 + 1 + 3 * kString + 8 + kString + 1 + 8 + 4 + 8 + 8 + 8 + 4 + 4;
// The smallest beacon_t without its fingerprint: fixed fields and empty strings and arrays.
constexpr std::size_t kBeacon = 4 + 8 + 8 + 4 + 8 + 8 + kString + 8 + 8 + 1 + 4 + 8 + 1 + 2 * kString + 4 + 4 + 4;
// The smallest host_beacon_t without its fingerprint: fixed fields and empty arrays.
constexpr std::size_t kHostBeacon = 4 + 1 + 1 + 8 + 8 + 8 + 8 + 4 + 8 + 4 + 4 + 8 + 4;
constexpr std::size_t kHistoryMessage = 1 + 4 + 4;
constexpr std::size_t kGoalStatus = kString + 1 + kString + 4;
constexpr std::size_t kLinkStatus = 2 * kString + 1 + 1 + 8 + 8 + 8 + 4;
constexpr std::size_t kChannelStatus = kString + 8 + 8 + 8 + 4 + 8 + 8 + 8;
constexpr std::size_t kPeerStatus = kString + 1 + kString + 8 + 4 + 4 + 4 + 4;

void str(Reader& r, std::string& out) {
  const auto v = r.string();
  out.assign(v.data(), v.size());
}

// A size member followed by a byte array of that size.
void byte_array(Reader& r, std::int32_t& size, std::vector<std::uint8_t>& out) {
  size = r.i32();
  const auto n = r.count(size, 1);
  const auto b = r.bytes(n);
  const auto* p = reinterpret_cast<const std::uint8_t*>(b.data());
  out.assign(p, p + b.size());
}

// An int32 count member followed by `count` strings.
void string_array(Reader& r, std::int32_t& count, std::vector<std::string>& out) {
  count = r.i32();
  out.resize(r.count(count, kString));
  for (auto& s : out) {
    if (!r.ok()) return;
    str(r, s);
  }
}

// An int32 count member followed by `count` structs, each read by `fields`.
template <class T, class F>
void struct_array(Reader& r, std::int32_t& count, std::size_t min_size, std::vector<T>& out, F fields) {
  count = r.i32();
  out.resize(r.count(count, min_size));
  for (std::size_t i = 0; i < out.size() && r.ok(); ++i) {
    const Reader::Hold later(r, (out.size() - 1 - i) * min_size);
    fields(r, out[i]);
  }
}

// --- discovery (beacon.lcm) ---

void fields(Reader& r, match_t& m) {
  m.publisher_participant = r.i64();
  m.publisher_endpoint = r.i64();
  str(r, m.path);
  m.received = r.i64();
  m.drops = r.i64();
}

void fields(Reader& r, endpoint_t& e) {
  e.id = r.i64();
  e.kind = r.i8();
  str(r, e.node);
  str(r, e.topic);
  str(r, e.type_name);
  e.fingerprint = r.i64();
  str(r, e.shm_segment);
  e.large = r.i8();
  e.max_message_size = r.i64();
  e.history = r.i32();
  e.messages = r.i64();
  e.drops = r.i64();
  e.rate_hz = r.f64();
  struct_array(r, e.num_matches, kMatch, e.matches, [](Reader& rr, match_t& m) { fields(rr, m); });
  string_array(r, e.num_errors, e.errors);
}

void fields(Reader& r, beacon_t& b) {
  b.version = r.i32();
  b.participant_id = r.i64();
  b.host_id = r.i64();
  b.pid = r.i32();
  b.start_time = r.i64();
  b.pid_namespace = r.i64();
  str(r, b.process_name);
  b.sequence = r.i64();
  b.revision = r.i64();
  b.flags = r.i8();
  b.lease_ms = r.i32();
  b.timestamp_us = r.i64();
  b.scope = r.i8();
  str(r, b.local_source);
  str(r, b.vehicle_source);
  string_array(r, b.num_nodes, b.nodes);
  struct_array(r, b.num_endpoints, kEndpoint, b.endpoints, [](Reader& rr, endpoint_t& e) { fields(rr, e); });
  string_array(r, b.num_carried, b.carried);
}

void fields(Reader& r, records_z_t& b) {
  b.version = r.i32();
  b.host_id = r.i64();
  b.base_participant = r.i64();
  b.base_revision = r.i64();
  b.raw_size = r.i32();
  byte_array(r, b.num_bytes, b.deflated);
}

// An int64 array whose count member was read before (host_beacon_t: two arrays share one).
void i64_array(Reader& r, std::int32_t count, std::vector<std::int64_t>& out) {
  out.resize(r.count(count, 8));
  for (auto& v : out) v = r.i64();
}

void fields(Reader& r, host_beacon_t& h) {
  h.version = r.i32();
  h.kind = r.i8();
  h.scope = r.i8();
  h.host_id = r.i64();
  h.registry_id = r.i64();
  h.speaker = r.i64();
  h.sequence = r.i64();
  h.lease_ms = r.i32();
  h.digest = r.i64();
  h.count = r.i32();
  h.num_entries = r.i32();
  // Both arrays are sized by num_entries: check it against both before sizing either.
  r.count(h.num_entries, 16);
  if (!r.ok()) return;
  i64_array(r, h.num_entries, h.participants);
  i64_array(r, h.num_entries, h.revisions);
  h.target_host = r.i64();
  h.num_wanted = r.i32();
  i64_array(r, h.num_wanted, h.wanted);
}

void fields(Reader& r, marker_t& m) {
  m.version = r.i32();
  m.participant_id = r.i64();
  m.host_id = r.i64();
  str(r, m.channel);
  m.count = r.i64();
}

void fields(Reader& r, records_t& b) {
  b.version = r.i32();
  b.host_id = r.i64();
  struct_array(r, b.num_records, kBeacon, b.records, [](Reader& rr, beacon_t& x) { fields(rr, x); });
  struct_array(r, b.num_state, kHostBeacon, b.state, [](Reader& rr, host_beacon_t& x) { fields(rr, x); });
}

// --- keep last N (history.lcm) ---

void fields(Reader& r, history_message_t& m) {
  m.sent = r.i8();
  m.sequence = r.i32();
  byte_array(r, m.size, m.data);
}

void fields(Reader& r, history_t& h) {
  h.publisher_participant = r.i64();
  h.publisher_endpoint = r.i64();
  h.subscriber_participant = r.i64();
  h.subscriber_endpoint = r.i64();
  str(r, h.channel);
  struct_array(r, h.num_messages, kHistoryMessage, h.messages,
               [](Reader& rr, history_message_t& m) { fields(rr, m); });
}

// --- services (service.lcm) ---

void fields(Reader& r, ServiceRequestHeader& h) {
  h.client_id = r.i64();
  h.request_id = r.i64();
  h.server_participant = r.i64();
  h.server_id = r.i64();
  h.client_participant = r.i64();
  h.request_fingerprint = r.i64();
  h.response_fingerprint = r.i64();
  h.reply_channel = r.string();
}

void fields(Reader& r, ServiceReplyHeader& h) {
  h.client_id = r.i64();
  h.request_id = r.i64();
  h.server_participant = r.i64();
  h.server_id = r.i64();
  h.reply_endpoint = r.i64();
  h.request_fingerprint = r.i64();
  h.response_fingerprint = r.i64();
  h.request_type = r.string();
  h.response_type = r.string();
  h.status = r.i8();
  h.error = r.string();
}

std::span<const std::byte> payload_of(Reader& r) {
  const std::int32_t size = r.i32();
  return r.bytes(r.count(size, 1));
}

// --- actions (action.lcm) ---

void fields(Reader& r, action_goal_t& m) {
  str(r, m.goal_id);
  m.client_id = r.i64();
  m.goal_fingerprint = r.i64();
  m.feedback_fingerprint = r.i64();
  m.result_fingerprint = r.i64();
  byte_array(r, m.size, m.goal);
}

void fields(Reader& r, action_goal_reply_t& m) {
  m.accepted = r.boolean();
  m.types_ok = r.boolean();
  str(r, m.message);
  m.cancel_server_id = r.i64();
  m.result_server_id = r.i64();
  str(r, m.goal_type);
  str(r, m.feedback_type);
  str(r, m.result_type);
}

void fields(Reader& r, action_goal_ref_t& m) { str(r, m.goal_id); }

void fields(Reader& r, action_goal_status_t& m) {
  str(r, m.goal_id);
  m.state = r.i8();
  str(r, m.message);
  m.feedback_count = r.i32();
}

void fields(Reader& r, action_result_t& m) {
  fields(r, m.status);
  byte_array(r, m.size, m.result);
}

void fields(Reader& r, action_feedback_t& m) {
  str(r, m.goal_id);
  byte_array(r, m.size, m.feedback);
}

void fields(Reader& r, action_status_t& m) {
  m.server_participant = r.i64();
  m.goal_server_id = r.i64();
  m.cancel_server_id = r.i64();
  m.result_server_id = r.i64();
  str(r, m.goal_type);
  str(r, m.feedback_type);
  str(r, m.result_type);
  m.goal_fingerprint = r.i64();
  m.feedback_fingerprint = r.i64();
  m.result_fingerprint = r.i64();
  struct_array(r, m.num_goals, kGoalStatus, m.goals, [](Reader& rr, action_goal_status_t& g) { fields(rr, g); });
}

// --- bridge status (bridge.lcm) ---

void fields(Reader& r, bridge_link_status_t& m) {
  str(r, m.name);
  str(r, m.address);
  m.up = r.i8();
  m.active = r.i8();
  m.bytes_sent = r.i64();
  m.bytes_received = r.i64();
  m.heartbeat_age_ms = r.i64();
  m.rtt_us = r.i32();
}

void fields(Reader& r, bridge_channel_status_t& m) {
  str(r, m.name);
  m.messages_sent = r.i64();
  m.bytes_sent = r.i64();
  m.drops = r.i64();
  m.queued = r.i32();
  m.messages_received = r.i64();
  m.bytes_received = r.i64();
  m.lost = r.i64();
}

void fields(Reader& r, bridge_peer_status_t& m) {
  str(r, m.name);
  m.up = r.i8();
  str(r, m.active_link);
  m.failovers = r.i64();
  struct_array(r, m.num_links, kLinkStatus, m.links, [](Reader& rr, bridge_link_status_t& l) { fields(rr, l); });
  struct_array(r, m.num_channels, kChannelStatus, m.channels,
               [](Reader& rr, bridge_channel_status_t& c) { fields(rr, c); });
  string_array(r, m.num_served, m.served);
  string_array(r, m.num_wanted, m.wanted);
}

void fields(Reader& r, bridge_status_t& m) {
  m.timestamp_us = r.i64();
  str(r, m.name);
  m.host_id = r.i64();
  m.pid = r.i32();
  m.curve = r.i8();
  m.bad_frames = r.i64();
  struct_array(r, m.num_peers, kPeerStatus, m.peers, [](Reader& rr, bridge_peer_status_t& p) { fields(rr, p); });
  string_array(r, m.num_demand, m.demand);
  m.zero_copy_sends = r.i64();
  m.copied_sends = r.i64();
  m.lost_local = r.i64();
}

// One whole message: the fingerprint, the fields, nothing after them.
template <class T>
bool whole(std::span<const std::byte> bytes, T& out) {
  Reader r(bytes);
  if (!r.fingerprint(T::getHash())) return false;
  fields(r, out);
  return r.done();
}

}  // namespace

bool decode(std::span<const std::byte> b, beacon_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, host_beacon_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, marker_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, records_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, records_z_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, endpoint_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, match_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, history_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, history_message_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, action_goal_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, action_goal_reply_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, action_goal_ref_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, action_goal_status_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, action_result_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, action_feedback_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, action_status_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, bridge_status_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, bridge_peer_status_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, bridge_link_status_t& out) { return whole(b, out); }
bool decode(std::span<const std::byte> b, bridge_channel_status_t& out) { return whole(b, out); }

bool decode(std::span<const std::byte> bytes, ServiceRequestHeader& h, std::span<const std::byte>& payload) noexcept {
  Reader r(bytes);
  if (!r.fingerprint(service_request_t::getHash())) return false;
  fields(r, h);
  payload = payload_of(r);
  return r.done();
}

bool decode(std::span<const std::byte> bytes, ServiceReplyHeader& h, std::span<const std::byte>& payload) noexcept {
  Reader r(bytes);
  if (!r.fingerprint(service_reply_t::getHash())) return false;
  fields(r, h);
  payload = payload_of(r);
  return r.done();
}

bool decode(std::span<const std::byte> bytes, service_request_t& out) {
  ServiceRequestHeader h;
  std::span<const std::byte> payload;
  if (!decode(bytes, h, payload)) return false;
  out.client_id = h.client_id;
  out.request_id = h.request_id;
  out.server_participant = h.server_participant;
  out.server_id = h.server_id;
  out.client_participant = h.client_participant;
  out.request_fingerprint = h.request_fingerprint;
  out.response_fingerprint = h.response_fingerprint;
  out.reply_channel.assign(h.reply_channel);
  out.size = static_cast<std::int32_t>(payload.size());
  const auto* p = reinterpret_cast<const std::uint8_t*>(payload.data());
  out.payload.assign(p, p + payload.size());
  return true;
}

bool decode(std::span<const std::byte> bytes, service_reply_t& out) {
  ServiceReplyHeader h;
  std::span<const std::byte> payload;
  if (!decode(bytes, h, payload)) return false;
  out.client_id = h.client_id;
  out.request_id = h.request_id;
  out.server_participant = h.server_participant;
  out.server_id = h.server_id;
  out.reply_endpoint = h.reply_endpoint;
  out.request_fingerprint = h.request_fingerprint;
  out.response_fingerprint = h.response_fingerprint;
  out.request_type.assign(h.request_type);
  out.response_type.assign(h.response_type);
  out.status = h.status;
  out.error.assign(h.error);
  out.size = static_cast<std::int32_t>(payload.size());
  const auto* p = reinterpret_cast<const std::uint8_t*>(payload.data());
  out.payload.assign(p, p + payload.size());
  return true;
}

std::size_t header_size(const ServiceRequestHeader& h) noexcept {
  return 8 + 7 * 8 + encoded_string_size(h.reply_channel) + 4;
}

std::size_t header_size(const ServiceReplyHeader& h) noexcept {
  return 8 + 7 * 8 + encoded_string_size(h.request_type) + encoded_string_size(h.response_type) + 1 +
         encoded_string_size(h.error) + 4;
}

bool encode_header(const ServiceRequestHeader& h, std::size_t payload_size, std::span<std::byte> out) noexcept {
  if (payload_size > static_cast<std::size_t>(INT32_MAX)) return false;
  Writer w(out);
  w.i64(service_request_t::getHash());
  w.i64(h.client_id);
  w.i64(h.request_id);
  w.i64(h.server_participant);
  w.i64(h.server_id);
  w.i64(h.client_participant);
  w.i64(h.request_fingerprint);
  w.i64(h.response_fingerprint);
  w.string(h.reply_channel);
  w.i32(static_cast<std::int32_t>(payload_size));
  return w.ok();
}

bool encode_header(const ServiceReplyHeader& h, std::size_t payload_size, std::span<std::byte> out) noexcept {
  if (payload_size > static_cast<std::size_t>(INT32_MAX)) return false;
  Writer w(out);
  w.i64(service_reply_t::getHash());
  w.i64(h.client_id);
  w.i64(h.request_id);
  w.i64(h.server_participant);
  w.i64(h.server_id);
  w.i64(h.reply_endpoint);
  w.i64(h.request_fingerprint);
  w.i64(h.response_fingerprint);
  w.string(h.request_type);
  w.string(h.response_type);
  w.i8(h.status);
  w.string(h.error);
  w.i32(static_cast<std::int32_t>(payload_size));
  return w.ok();
}

}  // namespace lcmx::lcmtypes
