// Writes the seed corpora of the fuzz targets: make_seeds <dir> creates <dir>/beacon/*.bin
// (beacons from encode_beacon, so they follow beacon.lcm and its fingerprint as it changes),
// <dir>/{history,service_envelope,action_envelope,bridge_status}/*.bin (a selector byte and an
// lcm-gen encoding, so they follow the .lcm files too),
// <dir>/udpm_datagram/*.bin (inputs in the layout of udpm_input.hpp) and
// <dir>/regressions/{beacon,bridge_status}/*.bin (kept reproducers that depend on the .lcm files). Exit status 0,
// or 1 with a message when a file cannot be written.

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "batch_base.hpp"
#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/lcmtypes/envelope.hpp"
#include "lcmx/udpm/wire.hpp"
#include "udpm_input.hpp"

namespace {

using Bytes = std::vector<std::byte>;

void put32(Bytes& b, std::uint32_t v) {
  for (int s = 24; s >= 0; s -= 8) b.push_back(std::byte(static_cast<std::uint8_t>(v >> s)));
}
void put16(Bytes& b, std::uint16_t v) {
  b.push_back(std::byte(static_cast<std::uint8_t>(v >> 8)));
  b.push_back(std::byte(static_cast<std::uint8_t>(v)));
}
void put_channel(Bytes& b, std::string_view channel) {
  for (char c : channel) b.push_back(std::byte(static_cast<unsigned char>(c)));
  b.push_back(std::byte{0});
}
Bytes pattern(std::size_t n, std::uint8_t seed) {
  Bytes b(n);
  for (std::size_t i = 0; i < n; ++i) b[i] = std::byte(static_cast<std::uint8_t>(seed + i * 7));
  return b;
}

Bytes lc02(std::uint32_t seq, std::string_view channel, std::span<const std::byte> payload) {
  Bytes b;
  put32(b, lcmx::udpm::kMagicShort);
  put32(b, seq);
  put_channel(b, channel);
  b.insert(b.end(), payload.begin(), payload.end());
  return b;
}

// LC03 fragments of `payload`, each carrying at most `chunk` payload bytes (small, so that seeds
// stay small; the wire format allows any split).
std::vector<Bytes> lc03(std::uint32_t seq, std::string_view channel,
                        std::span<const std::byte> payload, std::size_t chunk) {
  const std::size_t count = (payload.size() + chunk - 1) / chunk;
  std::vector<Bytes> out;
  for (std::size_t i = 0; i < count; ++i) {
    Bytes b;
    put32(b, lcmx::udpm::kMagicLong);
    put32(b, seq);
    put32(b, static_cast<std::uint32_t>(payload.size()));
    put32(b, static_cast<std::uint32_t>(i * chunk));
    put16(b, static_cast<std::uint16_t>(i));
    put16(b, static_cast<std::uint16_t>(count));
    if (i == 0) put_channel(b, channel);
    const auto part = payload.subspan(i * chunk, std::min(chunk, payload.size() - i * chunk));
    b.insert(b.end(), part.begin(), part.end());
    out.push_back(std::move(b));
  }
  return out;
}

lcmx_msgs::beacon_t beacon(int endpoints, int nodes) {
  lcmx_msgs::beacon_t b{};  // value-initialised: fields this file does not name are 0 or ""
  b.version = lcmx::discovery::kBeaconVersion;
  b.participant_id = 0x1122334455667788;
  b.host_id = 0x0102030405060708;
  b.pid = 4242;
  b.process_name = "fuzz_seed";
  b.sequence = 7;
  b.revision = 3;
  b.lease_ms = 3000;
  b.timestamp_us = 1700000000000000;
  for (int i = 0; i < nodes; ++i) b.nodes.push_back("node" + std::to_string(i));
  b.num_nodes = static_cast<std::int32_t>(b.nodes.size());
  for (int i = 0; i < endpoints; ++i) {
    lcmx_msgs::endpoint_t e{};
    e.id = i + 1;
    e.kind = i % 2 == 0 ? lcmx_msgs::endpoint_t::KIND_PUBLISHER : lcmx_msgs::endpoint_t::KIND_SUBSCRIBER;
    e.node = "node0";
    e.topic = "CAMERA";
    e.type_name = "lcmx_examples.image_t";
    e.fingerprint = 0x0badc0de;
    e.shm_segment = i % 2 == 0 ? "/lcmx_seed" : "";
    e.max_message_size = 1 << 20;
    e.messages = 100;
    e.rate_hz = 30.0;
    if (e.kind == lcmx_msgs::endpoint_t::KIND_SUBSCRIBER) {
      lcmx_msgs::match_t m{};
      m.publisher_participant = b.participant_id;
      m.publisher_endpoint = 1;
      m.path = "shm";
      m.received = 99;
      m.drops = 1;
      e.matches.push_back(m);
      e.errors.push_back("type mismatch");
    }
    e.num_matches = static_cast<std::int32_t>(e.matches.size());
    e.num_errors = static_cast<std::int32_t>(e.errors.size());
    b.endpoints.push_back(e);
  }
  b.num_endpoints = static_cast<std::int32_t>(b.endpoints.size());
  if (endpoints > 0) b.carried = {"MAP_*", "CMD"};
  b.num_carried = static_cast<std::int32_t>(b.carried.size());
  return b;
}

bool write(const std::filesystem::path& path, std::span<const std::byte> bytes) {
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  if (!f) {
    std::fprintf(stderr, "make_seeds: cannot write %s\n", path.c_str());
    return false;
  }
  return true;
}

}  // namespace

// The envelope targets' seeds: a selector byte (which type), then lcm-gen's encoding of one
// message of that type (fuzz_history, fuzz_service_envelope, fuzz_action_envelope,
// fuzz_bridge_status).
template <class T>
bool envelope_seed(const std::filesystem::path& dir, const char* name, std::uint8_t selector, const T& m) {
  Bytes in{std::byte{selector}};
  const Bytes b = lcmx::lcmtypes::encode(m);
  in.insert(in.end(), b.begin(), b.end());
  return write(dir / name, in);
}

std::vector<std::uint8_t> u8(std::size_t n, std::uint8_t seed) {
  std::vector<std::uint8_t> v(n);
  for (std::size_t i = 0; i < n; ++i) v[i] = static_cast<std::uint8_t>(seed + i * 13);
  return v;
}

bool write_envelope_seeds(const std::filesystem::path& dir) {
  using namespace lcmx_msgs;
  bool ok = true;
  for (const char* d : {"history", "service_envelope", "action_envelope", "bridge_status"})
    std::filesystem::create_directories(dir / d);
  {
    history_t h{};
    h.publisher_participant = 0x1234;
    h.publisher_endpoint = 3;
    h.subscriber_participant = 0x5678;
    h.subscriber_endpoint = 9;
    h.channel = "POSE";
    for (int i = 0; i < 3; ++i) {
      history_message_t m{};
      m.sent = static_cast<std::int8_t>(i % 2);
      m.sequence = 100 + i;
      m.data = u8(static_cast<std::size_t>(8 + 4 * i), static_cast<std::uint8_t>(i));
      m.size = static_cast<std::int32_t>(m.data.size());
      h.messages.push_back(m);
    }
    h.num_messages = 3;
    ok &= envelope_seed(dir / "history", "three.bin", 0, h);
    ok &= envelope_seed(dir / "history", "message.bin", 1, h.messages[1]);
    h.messages.clear();
    h.num_messages = 0;
    ok &= envelope_seed(dir / "history", "empty.bin", 0, h);
  }
  {
    service_request_t q{};
    q.client_id = 0x0123456789abcdef;
    q.request_id = 5;
    q.server_participant = 0x42;
    q.server_id = 7;
    q.client_participant = 0x43;
    q.request_fingerprint = 0x1111;
    q.response_fingerprint = 0x2222;
    q.reply_channel = "plan/rp/0123456789abcdef";
    q.payload = u8(24, 1);
    q.size = 24;
    ok &= envelope_seed(dir / "service_envelope", "request.bin", 0, q);
    q.request_id = 0;
    q.payload.clear();
    q.size = 0;
    ok &= envelope_seed(dir / "service_envelope", "probe.bin", 0, q);
    service_reply_t r{};
    r.client_id = q.client_id;
    r.request_id = 5;
    r.server_participant = 0x42;
    r.server_id = 7;
    r.reply_endpoint = 12;
    r.request_type = "lcmx_examples.pose_t";
    r.response_type = "lcmx_examples.bench_t";
    r.status = service_reply_t::OK;
    r.payload = u8(16, 2);
    r.size = 16;
    ok &= envelope_seed(dir / "service_envelope", "reply.bin", 1, r);
    r.status = service_reply_t::HANDLER_FAILED;
    r.error = "the handler threw";
    r.payload.clear();
    r.size = 0;
    ok &= envelope_seed(dir / "service_envelope", "reply_error.bin", 1, r);
  }
  {
    action_goal_t g{};
    g.goal_id = "0123456789abcdef0123456789abcdef";
    g.client_id = 77;
    g.goal = u8(10, 3);
    g.size = 10;
    ok &= envelope_seed(dir / "action_envelope", "goal.bin", 0, g);
    action_goal_reply_t gr{};
    gr.accepted = true;
    gr.types_ok = true;
    gr.message = "ok";
    gr.cancel_server_id = 4;
    gr.result_server_id = 5;
    gr.goal_type = "pose_t";
    ok &= envelope_seed(dir / "action_envelope", "goal_reply.bin", 1, gr);
    action_goal_ref_t ref{};
    ref.goal_id = g.goal_id;
    ok &= envelope_seed(dir / "action_envelope", "ref.bin", 2, ref);
    action_goal_status_t st{};
    st.goal_id = g.goal_id;
    st.state = action_goal_status_t::EXECUTING;
    st.feedback_count = 3;
    ok &= envelope_seed(dir / "action_envelope", "goal_status.bin", 3, st);
    action_result_t res{};
    res.status = st;
    res.status.state = action_goal_status_t::SUCCEEDED;
    res.result = u8(6, 4);
    res.size = 6;
    ok &= envelope_seed(dir / "action_envelope", "result.bin", 4, res);
    action_feedback_t fb{};
    fb.goal_id = g.goal_id;
    fb.feedback = u8(5, 5);
    fb.size = 5;
    ok &= envelope_seed(dir / "action_envelope", "feedback.bin", 5, fb);
    action_status_t s{};
    s.server_participant = 0x42;
    s.goal_server_id = 1;
    s.cancel_server_id = 2;
    s.result_server_id = 3;
    s.goal_type = "pose_t";
    s.goals = {st, st};
    s.goals[1].state = action_goal_status_t::ABORTED;
    s.goals[1].message = "why";
    s.num_goals = 2;
    ok &= envelope_seed(dir / "action_envelope", "status.bin", 6, s);
  }
  {
    bridge_status_t b{};
    b.name = "a";
    b.host_id = 9;
    b.pid = 100;
    bridge_peer_status_t p{};
    p.name = "b";
    p.up = 1;
    p.active_link = "eth";
    bridge_link_status_t l{};
    l.name = "eth";
    l.address = "10.0.0.2";
    l.up = 1;
    l.active = 1;
    l.rtt_us = 80;
    p.links = {l};
    p.num_links = 1;
    bridge_channel_status_t c{};
    c.name = "images";
    c.messages_sent = 10;
    p.channels = {c};
    p.num_channels = 1;
    p.served = {"CAM"};
    p.num_served = 1;
    p.wanted = {"LIDAR", "POSE"};
    p.num_wanted = 2;
    b.peers = {p};
    b.num_peers = 1;
    b.demand = {"LIDAR"};
    b.num_demand = 1;
    ok &= envelope_seed(dir / "bridge_status", "status.bin", 0, b);
    ok &= envelope_seed(dir / "bridge_status", "peer.bin", 1, p);
    ok &= envelope_seed(dir / "bridge_status", "link.bin", 2, l);
    ok &= envelope_seed(dir / "bridge_status", "channel.bin", 3, c);
  }
  return ok;
}

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: make_seeds <dir>\n");
    return 2;
  }
  const std::filesystem::path dir = argv[1];
  std::filesystem::create_directories(dir / "beacon");
  std::filesystem::create_directories(dir / "udpm_datagram");
  bool ok = true;

  const Bytes small = lcmx::discovery::encode_beacon(beacon(0, 0));
  const Bytes full = lcmx::discovery::encode_beacon(beacon(2, 2));
  ok &= write(dir / "beacon" / "no_endpoints.bin", small);
  ok &= write(dir / "beacon" / "two_endpoints.bin", full);
  auto goodbye = beacon(1, 1);
  goodbye.flags = lcmx_msgs::beacon_t::FLAG_GOODBYE;
  ok &= write(dir / "beacon" / "goodbye.bin", lcmx::discovery::encode_beacon(goodbye));
  // A speaker's batch (records_t): two records and the goodbye, as Discovery sends them.
  const std::vector<Bytes> batch = {small, full, lcmx::discovery::encode_beacon(goodbye)};
  ok &= write(dir / "beacon" / "batch.bin", lcmx::discovery::encode_records(0, batch));
  // The same batch compressed (records_z_t), as a speaker sends it when that is smaller.
  const std::vector<Bytes> many = {full, full, full, small, lcmx::discovery::encode_beacon(goodbye)};
  ok &= write(dir / "beacon" / "batch_z.bin", lcmx::discovery::encode_batch(0, many));
  // Compressed against a base record (batch_base.hpp: fuzz_beacon inflates with it).
  {
    const auto base_record = lcmx::fuzz::batch_base_record();
    const auto base_bytes = lcmx::discovery::encode_beacon(base_record);
    const lcmx::discovery::BatchBase base{base_record.participant_id, base_record.revision, base_bytes};
    ok &= write(dir / "beacon" / "batch_base.bin", lcmx::discovery::encode_batch(0, many, {}, &base));
  }
  // With the speaker's heartbeat after the records, as the last batch of a pass ends.
  lcmx_msgs::host_beacon_t heartbeat{};
  heartbeat.version = lcmx::discovery::kHostBeaconVersion;
  heartbeat.kind = lcmx_msgs::host_beacon_t::KIND_HEARTBEAT;
  heartbeat.digest = 0x5eed;
  heartbeat.count = 2;
  ok &= write(dir / "beacon" / "batch_heartbeat.bin",
              lcmx::discovery::encode_records(0, batch, lcmx::discovery::encode_host_beacon(heartbeat)));

  // Regression (kept, not a seed): a string with a NUL before its terminating NUL. Made here
  // rather than checked in because the bytes carry beacon_t's fingerprint, which follows
  // beacon.lcm. See regressions/README.md.
  {
    auto b = beacon(0, 0);
    b.process_name = "fuzz#seed";
    Bytes bytes = lcmx::discovery::encode_beacon(b);
    const std::string_view marker = "fuzz#seed";
    const std::string_view all(reinterpret_cast<const char*>(bytes.data()), bytes.size());
    const auto at = all.find(marker);
    if (at == std::string_view::npos) {
      std::fprintf(stderr, "make_seeds: process_name not found in the encoded beacon\n");
      return 1;
    }
    bytes[at + 4] = std::byte{0};  // "fuzz\0seed"
    std::filesystem::create_directories(dir / "regressions" / "beacon");
    ok &= write(dir / "regressions" / "beacon" / "nul_inside_string.bin", bytes);
  }

  // Regression (kept, not a seed): nested counts that together claim the bytes twice (a
  // bridge_status_t of as many peers as the bytes hold, whose first peer serves 1000 empty
  // strings, cut after them). Made here because it carries bridge_status_t's fingerprint.
  {
    lcmx_msgs::bridge_peer_status_t peer{};
    peer.served.assign(1000, std::string());
    peer.num_served = 1000;
    lcmx_msgs::bridge_status_t status{};
    status.peers.push_back(peer);
    status.num_peers = 1;
    Bytes bytes{std::byte{0}};  // fuzz_bridge_status's selector: bridge_status_t
    const Bytes encoded = lcmx::lcmtypes::encode(status);
    bytes.insert(bytes.end(), encoded.begin(), encoded.end() - (4 + 3 * 8));  // no demand, no counters
    const std::size_t num_peers_at = 1 + 8 + 8 + 5 + 8 + 4 + 1 + 8;
    const auto peers = static_cast<std::uint32_t>((bytes.size() - num_peers_at - 4) / 35);
    for (int i = 0; i < 4; ++i) bytes[num_peers_at + i] = std::byte(static_cast<std::uint8_t>(peers >> (24 - 8 * i)));
    std::filesystem::create_directories(dir / "regressions" / "bridge_status");
    ok &= write(dir / "regressions" / "bridge_status" / "nested_counts.bin", bytes);
  }

  using lcmx::fuzz::append_record;
  {  // preset 0; one LC02 datagram carrying a beacon
    Bytes in{std::byte{0}};
    append_record(in, 0, lc02(1, lcmx::discovery::kBeaconChannel, small));
    ok &= write(dir / "udpm_datagram" / "lc02_beacon.bin", in);
  }
  {  // preset 0; a beacon in 3 LC03 fragments, out of order, with a duplicate
    Bytes in{std::byte{0}};
    const auto f = lc03(2, lcmx::discovery::kBeaconChannel, full, (full.size() + 2) / 3);
    append_record(in, 0, f[2]);
    append_record(in, 0, f[0]);
    append_record(in, 0, f[0]);
    append_record(in, 1 << lcmx::fuzz::kControlAdvanceShift, f[1]);
    ok &= write(dir / "udpm_datagram" / "lc03_beacon_reordered.bin", in);
  }
  {  // preset 1 (2 partials, 4 KiB); same sequence from two sources interleaved, a third
     // source evicting, an expire in between
    Bytes in{std::byte{1}};
    const Bytes payload = pattern(96, 3);
    const auto f = lc03(9, "CAM", payload, 32);
    append_record(in, 0, f[0]);
    append_record(in, 1, f[0]);
    append_record(in, 0, f[1]);
    append_record(in, 2, f[1]);
    append_record(in, 1, f[1]);
    append_record(in, 0 | lcmx::fuzz::kControlExpire | (2 << lcmx::fuzz::kControlAdvanceShift), f[2]);
    append_record(in, 1, f[2]);
    ok &= write(dir / "udpm_datagram" / "lc03_two_sources.bin", in);
  }
  {  // preset 3; LC02 and a 4-fragment LC03 message, fragments of another sequence expiring
    Bytes in{std::byte{3}};
    append_record(in, 3, lc02(5, "IMU", pattern(40, 9)));
    const auto f = lc03(6, "LIDAR", pattern(200, 1), 50);
    const auto g = lc03(7, "LIDAR", pattern(120, 2), 60);
    append_record(in, 3, f[1]);
    append_record(in, 3, g[0]);
    append_record(in, 3, f[3]);
    append_record(in, 3, f[0]);
    append_record(in, 3 | lcmx::fuzz::kControlExpire | (31 << lcmx::fuzz::kControlAdvanceShift), f[2]);
    ok &= write(dir / "udpm_datagram" / "lc02_lc03_mixed.bin", in);
  }
  ok &= write_envelope_seeds(dir);
  return ok ? 0 : 1;
}
