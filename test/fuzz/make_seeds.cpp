// Writes the seed corpora of the fuzz targets: make_seeds <dir> creates <dir>/beacon/*.bin
// (beacons from encode_beacon, so they follow beacon.lcm and its fingerprint as it changes),
// <dir>/udpm_datagram/*.bin (inputs in the layout of udpm_input.hpp) and
// <dir>/regressions/beacon/*.bin (kept reproducers that depend on beacon.lcm). Exit status 0,
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

#include "lcmx/discovery/beacon_codec.hpp"
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
  return ok ? 0 : 1;
}
