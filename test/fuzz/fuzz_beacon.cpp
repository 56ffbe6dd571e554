// libFuzzer target: lcmx::discovery::decode_beacon and decode_batch (a speaker's batch, plain
// or compressed, chosen by the input's fingerprint) on hostile bytes.
//
// Checks:
//  - a rejection says why;
//  - an accepted beacon has the supported version and occupies no more than the input
//    (getEncodedSize() <= input size: decoding allocates at most what was received);
//  - it survives a round trip: encode_beacon, decode_beacon again, and the key fields (every
//    field this target names; fields added later are covered by comparing the re-encodings)
//    are equal, strings byte for byte;
//  - a batch (records_t) that decodes is re-encoded by encode_records from its records'
//    encode_beacon bytes to exactly the input, and each record survives the round trip above;
//  - a compressed batch (records_z_t; inflated within its bounds, beacon_codec.hpp) that decodes
//    holds records that survive the same round trip, and encode_batch of them decodes to them.
// A failed check prints what failed and aborts, which libFuzzer reports as a crash.

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "batch_base.hpp"
#include "lcmx/discovery/beacon_codec.hpp"

namespace {

#define FUZZ_CHECK(cond)                                                                  \
  do {                                                                                    \
    if (!(cond)) {                                                                        \
      std::fprintf(stderr, "fuzz_beacon: check failed: %s (%s:%d)\n", #cond, __FILE__,   \
                   __LINE__);                                                             \
      std::abort();                                                                       \
    }                                                                                     \
  } while (0)

bool same_bits(double a, double b) { return std::memcmp(&a, &b, sizeof a) == 0; }

void check_string(const std::string& a, const std::string& b, const char* what) {
  if (a == b) return;
  std::fprintf(stderr,
               "fuzz_beacon: %s differs after encode_beacon + decode_beacon: %zu bytes before, "
               "%zu after (NUL inside the decoded string: %s)\n",
               what, a.size(), b.size(), a.find('\0') != std::string::npos ? "yes" : "no");
  std::abort();
}

void check_same(const lcmx_msgs::endpoint_t& a, const lcmx_msgs::endpoint_t& b) {
  FUZZ_CHECK(a.id == b.id);
  FUZZ_CHECK(a.kind == b.kind);
  check_string(a.node, b.node, "endpoint node");
  check_string(a.topic, b.topic, "endpoint topic");
  check_string(a.type_name, b.type_name, "endpoint type_name");
  FUZZ_CHECK(a.fingerprint == b.fingerprint);
  check_string(a.shm_segment, b.shm_segment, "endpoint shm_segment");
  FUZZ_CHECK(a.max_message_size == b.max_message_size);
  FUZZ_CHECK(a.messages == b.messages);
  FUZZ_CHECK(a.drops == b.drops);
  FUZZ_CHECK(same_bits(a.rate_hz, b.rate_hz));
  FUZZ_CHECK(a.num_matches == b.num_matches);
  FUZZ_CHECK(a.matches.size() == static_cast<std::size_t>(a.num_matches));
  FUZZ_CHECK(b.matches.size() == a.matches.size());
  for (std::size_t i = 0; i < a.matches.size(); ++i) {
    FUZZ_CHECK(a.matches[i].publisher_participant == b.matches[i].publisher_participant);
    FUZZ_CHECK(a.matches[i].publisher_endpoint == b.matches[i].publisher_endpoint);
    check_string(a.matches[i].path, b.matches[i].path, "match path");
    FUZZ_CHECK(a.matches[i].received == b.matches[i].received);
    FUZZ_CHECK(a.matches[i].drops == b.matches[i].drops);
  }
  FUZZ_CHECK(a.num_errors == b.num_errors);
  FUZZ_CHECK(a.errors.size() == static_cast<std::size_t>(a.num_errors));
  FUZZ_CHECK(b.errors.size() == a.errors.size());
  for (std::size_t i = 0; i < a.errors.size(); ++i) check_string(a.errors[i], b.errors[i], "error");
}

void check_same(const lcmx_msgs::beacon_t& a, const lcmx_msgs::beacon_t& b) {
  FUZZ_CHECK(a.version == b.version);
  FUZZ_CHECK(a.participant_id == b.participant_id);
  FUZZ_CHECK(a.host_id == b.host_id);
  FUZZ_CHECK(a.pid == b.pid);
  check_string(a.process_name, b.process_name, "process_name");
  FUZZ_CHECK(a.sequence == b.sequence);
  FUZZ_CHECK(a.revision == b.revision);
  FUZZ_CHECK(a.flags == b.flags);
  FUZZ_CHECK(a.lease_ms == b.lease_ms);
  FUZZ_CHECK(a.timestamp_us == b.timestamp_us);
  FUZZ_CHECK(a.num_nodes == b.num_nodes);
  FUZZ_CHECK(a.nodes.size() == static_cast<std::size_t>(a.num_nodes));
  FUZZ_CHECK(b.nodes.size() == a.nodes.size());
  for (std::size_t i = 0; i < a.nodes.size(); ++i) check_string(a.nodes[i], b.nodes[i], "node");
  FUZZ_CHECK(a.num_endpoints == b.num_endpoints);
  FUZZ_CHECK(a.endpoints.size() == static_cast<std::size_t>(a.num_endpoints));
  FUZZ_CHECK(b.endpoints.size() == a.endpoints.size());
  for (std::size_t i = 0; i < a.endpoints.size(); ++i) check_same(a.endpoints[i], b.endpoints[i]);
  FUZZ_CHECK(a.num_carried == b.num_carried);
  FUZZ_CHECK(a.carried.size() == static_cast<std::size_t>(a.num_carried));
  FUZZ_CHECK(b.carried.size() == a.carried.size());
  for (std::size_t i = 0; i < a.carried.size(); ++i) check_string(a.carried[i], b.carried[i], "carried");
}


int check_batch(std::span<const std::byte> input) {
  std::string why;
  const bool compressed = lcmx::discovery::fingerprint_of(input) == lcmx_msgs::records_z_t::getHash();
  // Deflated against a base: the fuzz inputs' one (batch_base.hpp), whatever the batch names.
  const auto named = lcmx::discovery::batch_base(input);
  const auto base_bytes = lcmx::discovery::encode_beacon(lcmx::fuzz::batch_base_record());
  const lcmx::discovery::BatchBase base{named.first, named.second, base_bytes};
  const auto batch = lcmx::discovery::decode_batch(input, &why, named.first != 0 ? std::span(base_bytes) : std::span<const std::byte>{});
  if (!batch) {
    FUZZ_CHECK(!why.empty());
    return 0;
  }
  FUZZ_CHECK(batch->version == lcmx::discovery::kBeaconVersion);
  FUZZ_CHECK(batch->records.size() == static_cast<std::size_t>(batch->num_records));
  std::vector<std::vector<std::byte>> each;
  for (const auto& r : batch->records) {
    FUZZ_CHECK(r.version == lcmx::discovery::kBeaconVersion && r.host_id == batch->host_id);
    each.push_back(lcmx::discovery::encode_beacon(r));
    const auto again = lcmx::discovery::decode_beacon(each.back(), &why);
    FUZZ_CHECK(again.has_value());
    check_same(r, *again);
  }
  const auto host = static_cast<std::uint64_t>(batch->host_id);
  FUZZ_CHECK(batch->state.size() <= 1);
  std::vector<std::byte> heartbeat;  // the speaker's heartbeat after the records, if the batch has one
  for (const auto& h : batch->state) {
    FUZZ_CHECK(h.kind == lcmx_msgs::host_beacon_t::KIND_HEARTBEAT && h.host_id == batch->host_id);
    heartbeat = lcmx::discovery::encode_host_beacon(h);
  }
  if (!compressed) {
    const auto encoded = lcmx::discovery::encode_records(host, each, heartbeat);
    FUZZ_CHECK(encoded.size() == input.size() && std::equal(encoded.begin(), encoded.end(), input.begin()));
    return 0;
  }
  // A compressed batch need not deflate to the same bytes again (another zlib, another level),
  // but what the speaker would send for its records must decode to them.
  if (each.empty()) return 0;
  const auto again = lcmx::discovery::decode_any_records(lcmx::discovery::encode_batch(host, each, heartbeat), &why);
  FUZZ_CHECK(again.has_value() && again->size() == batch->records.size());
  for (std::size_t i = 0; i < again->size(); ++i) check_same(batch->records[i], (*again)[i]);
  if (named.first != 0) {  // and against the same base: what decodes with it gives them back
    const auto sent = lcmx::discovery::encode_batch(host, each, heartbeat, &base);
    std::optional<std::vector<lcmx_msgs::beacon_t>> got;
    if (lcmx::discovery::batch_base(sent).first != 0) {
      auto r = lcmx::discovery::decode_batch(sent, &why, base_bytes);
      if (r) got = std::move(r->records);
    } else {
      got = lcmx::discovery::decode_any_records(sent, &why);
    }
    FUZZ_CHECK(got.has_value() && got->size() == batch->records.size());
    for (std::size_t i = 0; i < got->size(); ++i) check_same(batch->records[i], (*got)[i]);
  }
  return 0;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::span<const std::byte> input(reinterpret_cast<const std::byte*>(data), size);
  const auto fp = lcmx::discovery::fingerprint_of(input);
  if (fp == lcmx_msgs::records_t::getHash() || fp == lcmx_msgs::records_z_t::getHash()) return check_batch(input);
  std::string why;
  const auto first = lcmx::discovery::decode_beacon(input, &why);
  if (!first) {
    FUZZ_CHECK(!why.empty());
    return 0;
  }
  FUZZ_CHECK(first->version == lcmx::discovery::kBeaconVersion);
  FUZZ_CHECK(first->getEncodedSize() >= 0);
  FUZZ_CHECK(static_cast<std::size_t>(first->getEncodedSize()) <= size);

  const std::vector<std::byte> encoded = lcmx::discovery::encode_beacon(*first);
  FUZZ_CHECK(!encoded.empty());
  std::string why_again;
  const auto second = lcmx::discovery::decode_beacon(encoded, &why_again);
  if (!second) {
    std::fprintf(stderr, "fuzz_beacon: re-encoded beacon rejected: %s\n", why_again.c_str());
    std::abort();
  }
  check_same(*first, *second);
  FUZZ_CHECK(lcmx::discovery::encode_beacon(*second) == encoded);
  return 0;
}
