// Discovery: beacon codec against hostile input, and two participants on a test group
// (join, update, goodbye, lease expiry, observer query).
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <climits>
#include <catch2/catch.hpp>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <set>
#include <span>
#include <mutex>
#include <random>
#include <thread>

#include <zlib.h>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "lcmx/discovery/identity.hpp"

using namespace std::chrono_literals;
using lcmx_msgs::beacon_t;

namespace {

beacon_t sample_beacon(std::int64_t id) {
  beacon_t b{};
  b.version = lcmx::discovery::kBeaconVersion;
  b.participant_id = id;
  b.host_id = 7;
  b.pid = 1234;
  b.process_name = "proc";
  b.nodes = {"a", "b"};
  b.num_nodes = 2;
  lcmx_msgs::endpoint_t e{};
  e.id = 1;
  e.kind = lcmx_msgs::endpoint_t::KIND_SUBSCRIBER;
  e.node = "a";
  e.topic = "POSE";
  e.type_name = "pose_t";
  lcmx_msgs::match_t m{};
  m.path = "shm";
  e.matches = {m};
  e.num_matches = 1;
  e.errors = {"x"};
  e.num_errors = 1;
  b.endpoints = {e, e};
  b.num_endpoints = 2;
  return b;
}

lcmx::udpm::GroupConfig test_group(int salt) {
  const int id = static_cast<int>(::getpid()) * 8 + salt;
  lcmx::udpm::GroupConfig g;
  g.address = "239.253." + std::to_string((id >> 8) & 0xff) + "." + std::to_string(id & 0xff);
  g.port = static_cast<std::uint16_t>(20000 + id % 40000);
  g.interface = "lo";  // the root namespace: never join on the machine's real interface
  return g;
}

template <class Pred>
bool eventually(Pred pred, std::chrono::milliseconds deadline = 5000ms) {
  const auto end = std::chrono::steady_clock::now() + deadline;
  while (!pred()) {
    if (std::chrono::steady_clock::now() > end) return false;
    std::this_thread::sleep_for(1ms);  // polling a condition with a deadline
  }
  return true;
}

}  // namespace

TEST_CASE("beacons round-trip through the codec", "[discovery][codec]") {
  const auto b = sample_beacon(42);
  const auto bytes = lcmx::discovery::encode_beacon(b);
  auto back = lcmx::discovery::decode_beacon(bytes);
  REQUIRE(back);
  CHECK(back->participant_id == 42);
  CHECK(back->endpoints.size() == 2);
  CHECK(back->endpoints[1].matches[0].path == "shm");
}

TEST_CASE("a batch of records (records_t) is lcm-gen's encoding, checked like a beacon", "[discovery][codec]") {
  const std::vector<std::vector<std::byte>> three = {lcmx::discovery::encode_beacon(sample_beacon(1)),
                                                     lcmx::discovery::encode_beacon(sample_beacon(2)),
                                                     lcmx::discovery::encode_beacon(sample_beacon(3))};
  const auto bytes = lcmx::discovery::encode_records(7, three);
  // What lcm-gen's own decoder reads (stock LCM tools see a valid message).
  lcmx_msgs::records_t plain;
  REQUIRE(plain.decode(bytes.data(), 0, static_cast<int>(bytes.size())) == static_cast<int>(bytes.size()));
  CHECK(plain.host_id == 7);
  REQUIRE(plain.records.size() == 3);
  CHECK(plain.records[2].participant_id == 3);
  CHECK(plain.records[1].endpoints[1].matches[0].path == "shm");
  auto back = lcmx::discovery::decode_records(bytes);
  REQUIRE(back);
  CHECK(back->records.size() == 3);
  auto any = lcmx::discovery::decode_any_records(bytes);
  REQUIRE(any);
  CHECK(any->size() == 3);
  auto one = lcmx::discovery::decode_any_records(three[0]);
  REQUIRE(one);
  CHECK(one->size() == 1);
  std::string why;
  SECTION("every truncation") {
    for (std::size_t n = 0; n < bytes.size(); ++n) CHECK_FALSE(lcmx::discovery::decode_records({bytes.data(), n}, &why));
  }
  SECTION("a record of another host than the batch's") {
    auto other = sample_beacon(4);
    other.host_id = 8;
    const std::vector<std::vector<std::byte>> mixed = {three[0], lcmx::discovery::encode_beacon(other)};
    CHECK_FALSE(lcmx::discovery::decode_records(lcmx::discovery::encode_records(7, mixed), &why));
    CHECK_THAT(why, Catch::Contains("another host"));
  }
  SECTION("a count larger than the bytes") {
    auto bad = bytes;
    bad[20] = std::byte{0x7f};  // num_records, after fingerprint, version and host id
    CHECK_FALSE(lcmx::discovery::decode_records(bad, &why));
    CHECK_THAT(why, Catch::Contains("malformed"));
  }
  SECTION("the speaker's heartbeat after the records: one, a heartbeat, of the same host") {
    lcmx_msgs::host_beacon_t heartbeat{};
    heartbeat.version = lcmx::discovery::kHostBeaconVersion;
    heartbeat.kind = lcmx_msgs::host_beacon_t::KIND_HEARTBEAT;
    heartbeat.host_id = 7;
    heartbeat.digest = 0x1234;
    heartbeat.count = 3;
    const auto with = lcmx::discovery::encode_records(7, three, lcmx::discovery::encode_host_beacon(heartbeat));
    lcmx_msgs::records_t read;  // lcm-gen's decoder
    REQUIRE(read.decode(with.data(), 0, static_cast<int>(with.size())) == static_cast<int>(with.size()));
    REQUIRE(read.state.size() == 1);
    CHECK(read.state[0].digest == 0x1234);
    auto ok = lcmx::discovery::decode_batch(lcmx::discovery::encode_batch(7, three, lcmx::discovery::encode_host_beacon(heartbeat)));
    REQUIRE(ok);
    REQUIRE(ok->state.size() == 1);
    CHECK(ok->state[0].count == 3);
    // With a heartbeat, even one record goes in a batch.
    const std::vector<std::vector<std::byte>> one = {three[0]};
    const auto single = lcmx::discovery::decode_batch(lcmx::discovery::encode_batch(7, one, lcmx::discovery::encode_host_beacon(heartbeat)));
    REQUIRE(single);
    CHECK(single->state.size() == 1);
    // Refused: two heartbeats, an index, another host's heartbeat.
    auto encode = [](lcmx_msgs::records_t r) {
      std::vector<std::byte> out(static_cast<std::size_t>(r.getEncodedSize()));
      r.encode(out.data(), 0, static_cast<int>(out.size()));
      return out;
    };
    auto two = read;
    two.state = {heartbeat, heartbeat};
    two.num_state = 2;
    CHECK_FALSE(lcmx::discovery::decode_records(encode(two), &why));
    CHECK_THAT(why, Catch::Contains("more than one heartbeat"));
    auto index = read;
    index.state[0].kind = lcmx_msgs::host_beacon_t::KIND_INDEX;
    CHECK_FALSE(lcmx::discovery::decode_records(encode(index), &why));
    CHECK_THAT(why, Catch::Contains("not its host's heartbeat"));
    auto other = read;
    other.state[0].host_id = 8;
    CHECK_FALSE(lcmx::discovery::decode_records(encode(other), &why));
    CHECK_THAT(why, Catch::Contains("not its host's heartbeat"));
    CHECK(lcmx::discovery::decode_records(encode(read)));
  }
}

namespace {

// A records_z_t around whatever deflated bytes and declared size a test wants (lcm-gen's encoder).
std::vector<std::byte> records_z(std::int64_t host, std::int32_t raw_size, std::vector<std::uint8_t> deflated) {
  lcmx_msgs::records_z_t z{};
  z.version = lcmx::discovery::kBeaconVersion;
  z.host_id = host;
  z.raw_size = raw_size;
  z.num_bytes = static_cast<std::int32_t>(deflated.size());
  z.deflated = std::move(deflated);
  std::vector<std::byte> out(static_cast<std::size_t>(z.getEncodedSize()));
  z.encode(out.data(), 0, static_cast<int>(out.size()));
  return out;
}

std::vector<std::uint8_t> deflate(std::span<const std::byte> raw) {
  uLongf n = compressBound(static_cast<uLong>(raw.size()));
  std::vector<std::uint8_t> z(n);
  REQUIRE(compress2(z.data(), &n, reinterpret_cast<const Bytef*>(raw.data()), static_cast<uLong>(raw.size()), 6) == Z_OK);
  z.resize(n);
  return z;
}

}  // namespace

TEST_CASE("a compressed batch (records_z_t) is smaller, inflates to the records_t, and is inflated only within its bounds",
          "[discovery][codec]") {
  std::vector<std::vector<std::byte>> records;
  for (int k = 1; k <= 6; ++k) records.push_back(lcmx::discovery::encode_beacon(sample_beacon(k)));
  const auto plain = lcmx::discovery::encode_records(7, records);
  const auto sent = lcmx::discovery::encode_batch(7, records);
  REQUIRE(lcmx::discovery::fingerprint_of(sent) == lcmx_msgs::records_z_t::getHash());
  INFO("records_t " << plain.size() << " B, compressed " << sent.size() << " B");
  CHECK(2 * sent.size() < plain.size());  // six alike records: well under half
  // lcm-gen's own decoder reads it, and zlib's own inflate gives back exactly the records_t.
  lcmx_msgs::records_z_t z;
  REQUIRE(z.decode(sent.data(), 0, static_cast<int>(sent.size())) == static_cast<int>(sent.size()));
  CHECK(z.host_id == 7);
  REQUIRE(z.raw_size == static_cast<std::int32_t>(plain.size()));
  std::vector<std::byte> inflated(plain.size());
  uLongf n = static_cast<uLongf>(inflated.size());
  REQUIRE(uncompress(reinterpret_cast<Bytef*>(inflated.data()), &n, z.deflated.data(), static_cast<uLong>(z.deflated.size())) == Z_OK);
  CHECK(inflated == plain);
  auto back = lcmx::discovery::decode_batch(sent);
  REQUIRE(back);
  REQUIRE(back->records.size() == 6);
  CHECK(back->records[5].participant_id == 6);
  CHECK(back->records[2].endpoints[1].matches[0].path == "shm");
  auto any = lcmx::discovery::decode_any_records(sent);
  REQUIRE(any);
  CHECK(any->size() == 6);
  // A plain records_t still decodes through decode_batch; a small record with little to
  // compress (random fields) is sent alone, as it is; a compressible one is sent deflated.
  CHECK(lcmx::discovery::decode_batch(plain));
  std::mt19937_64 rng(7);
  beacon_t tiny{};
  tiny.version = lcmx::discovery::kBeaconVersion;
  tiny.host_id = 7;
  for (auto* f : {&tiny.participant_id, &tiny.start_time, &tiny.pid_namespace, &tiny.sequence, &tiny.revision, &tiny.timestamp_us})
    *f = static_cast<std::int64_t>(rng());
  for (int k = 0; k < 24; ++k) tiny.process_name += static_cast<char>('!' + rng() % 90);
  const std::vector<std::vector<std::byte>> one = {lcmx::discovery::encode_beacon(tiny)};
  CHECK(lcmx::discovery::encode_batch(7, one) == one.front());
  const std::vector<std::vector<std::byte>> alike = {lcmx::discovery::encode_beacon(sample_beacon(1))};
  const auto single = lcmx::discovery::encode_batch(7, alike);
  CHECK(lcmx::discovery::fingerprint_of(single) == lcmx_msgs::records_z_t::getHash());
  CHECK(single.size() < alike.front().size());

  std::string why;
  SECTION("every truncation") {
    for (std::size_t k = 0; k < sent.size(); ++k) CHECK_FALSE(lcmx::discovery::decode_batch({sent.data(), k}, &why));
  }
  SECTION("a declared size that is not what the stream inflates to, either way") {
    const auto d = deflate(plain);
    const auto size = static_cast<std::int32_t>(plain.size());
    CHECK(lcmx::discovery::decode_batch(records_z(7, size, d), &why));
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(7, size + 1, d), &why));
    CHECK_THAT(why, Catch::Contains("do not inflate"));
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(7, size - 1, d), &why));
    CHECK_THAT(why, Catch::Contains("do not inflate"));
  }
  SECTION("bytes after the stream, a broken checksum") {
    auto d = deflate(plain);
    auto longer = d;
    longer.push_back(0);
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(7, static_cast<std::int32_t>(plain.size()), longer), &why));
    CHECK_THAT(why, Catch::Contains("do not inflate"));
    d.back() ^= 1;  // the Adler-32 at the end of the stream
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(7, static_cast<std::int32_t>(plain.size()), d), &why));
  }
  SECTION("a size no receiver inflates: above the bound, or above deflate's ratio for its bytes") {
    // 8 MiB of zeros deflates to about 8 KB: a real stream, refused before anything is allocated.
    const std::vector<std::byte> zeros(8u << 20);
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(7, static_cast<std::int32_t>(zeros.size()), deflate(zeros)), &why));
    CHECK_THAT(why, Catch::Contains("impossible size"));
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(7, 1 << 20, {1, 2, 3}), &why));
    CHECK_THAT(why, Catch::Contains("impossible size"));
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(7, -5, deflate(plain)), &why));
    CHECK_THAT(why, Catch::Contains("impossible size"));
  }
  SECTION("a stream that is not a batch, or a batch of another host") {
    const auto beacon = lcmx::discovery::encode_beacon(sample_beacon(1));
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(7, static_cast<std::int32_t>(beacon.size()), deflate(beacon)), &why));
    CHECK_THAT(why, Catch::Contains("records_t"));
    CHECK_FALSE(lcmx::discovery::decode_batch(records_z(8, static_cast<std::int32_t>(plain.size()), deflate(plain)), &why));
    CHECK_THAT(why, Catch::Contains("another host"));
  }
}

TEST_CASE("a batch compressed against a base record is smaller still, and decodes only with that record's bytes",
          "[discovery][codec]") {
  // The previous revision of a record: what changed is one match.
  auto before = sample_beacon(3);
  before.revision = 4;
  auto after = before;
  after.revision = 5;
  after.endpoints[0].matches[0].path = "udp";
  after.endpoints[0].matches[0].publisher_participant = 99;
  const auto base_bytes = lcmx::discovery::encode_beacon(before);
  const std::vector<std::vector<std::byte>> records = {lcmx::discovery::encode_beacon(after)};
  const auto plain = lcmx::discovery::encode_batch(7, records);
  const lcmx::discovery::BatchBase base{3, 4, base_bytes};
  const auto against = lcmx::discovery::encode_batch(7, records, {}, &base);
  INFO("alone or deflated " << plain.size() << " B, against its previous revision " << against.size() << " B");
  REQUIRE(lcmx::discovery::fingerprint_of(against) == lcmx_msgs::records_z_t::getHash());
  CHECK(against.size() + 20 < plain.size());
  CHECK(lcmx::discovery::batch_base(against) == std::make_pair(std::int64_t{3}, std::int64_t{4}));
  CHECK(lcmx::discovery::batch_base(plain) == std::make_pair(std::int64_t{0}, std::int64_t{0}));
  std::string why;
  // Without the base, or with other bytes (another revision), nothing comes out.
  CHECK_FALSE(lcmx::discovery::decode_batch(against, &why));
  CHECK_THAT(why, Catch::Contains("not given"));
  auto other = before;
  other.revision = 3;
  CHECK_FALSE(lcmx::discovery::decode_batch(against, &why, lcmx::discovery::encode_beacon(other)));
  CHECK_THAT(why, Catch::Contains("another base"));
  // With it: the record as sent.
  auto back = lcmx::discovery::decode_batch(against, &why, base_bytes);
  REQUIRE(back);
  REQUIRE(back->records.size() == 1);
  CHECK(lcmx::discovery::encode_beacon(back->records[0]) == records[0]);
  // lcm-gen's decoder reads the header; zlib's own inflate wants the dictionary it names.
  lcmx_msgs::records_z_t z;
  REQUIRE(z.decode(against.data(), 0, static_cast<int>(against.size())) == static_cast<int>(against.size()));
  std::vector<std::byte> out(static_cast<std::size_t>(z.raw_size));
  uLongf n = static_cast<uLongf>(out.size());
  CHECK(uncompress(reinterpret_cast<Bytef*>(out.data()), &n, z.deflated.data(), static_cast<uLong>(z.deflated.size())) ==
        Z_DATA_ERROR);  // (zlib's uncompress reports Z_NEED_DICT as a data error)
  // Every truncation is refused, with the base too.
  for (std::size_t k = 0; k < against.size(); ++k)
    CHECK_FALSE(lcmx::discovery::decode_batch({against.data(), k}, &why, base_bytes));
}

TEST_CASE("malformed beacons are rejected without crashing or allocating", "[discovery][codec]") {
  const auto good = lcmx::discovery::encode_beacon(sample_beacon(1));
  std::string why;
  SECTION("every truncation") {
    for (std::size_t n = 0; n < good.size(); ++n)
      CHECK_FALSE(lcmx::discovery::decode_beacon({good.data(), n}, &why));
  }
  SECTION("wrong fingerprint") {
    auto bad = good;
    bad[0] ^= std::byte{0xff};
    CHECK_FALSE(lcmx::discovery::decode_beacon(bad, &why));
    CHECK_THAT(why, Catch::Contains("fingerprint"));
  }
  SECTION("huge and negative counts") {
    // num_nodes sits right after the fixed header fields; find it by its value (2).
    int refused = 0;
    for (std::uint32_t v : {0x7fffffffu, 0x80000000u, 0xffffffffu, 100000u}) {
      for (std::size_t off = 8; off + 4 <= good.size(); ++off) {
        auto bad = good;
        bad[off] = std::byte(v >> 24);
        bad[off + 1] = std::byte(v >> 16);
        bad[off + 2] = std::byte(v >> 8);
        bad[off + 3] = std::byte(v);
        // Never a crash or a huge allocation: refused with a reason, or decoded with every
        // count matching what was read (a count the bytes cannot hold is refused).
        why.clear();
        const auto r = lcmx::discovery::decode_beacon(bad, &why);
        if (r) {
          CHECK(r->nodes.size() == static_cast<std::size_t>(r->num_nodes));
          CHECK(r->endpoints.size() == static_cast<std::size_t>(r->num_endpoints));
          CHECK(r->nodes.size() + r->endpoints.size() <= bad.size());
        } else {
          CHECK_FALSE(why.empty());
          ++refused;
        }
      }
    }
    CHECK(refused > 0);  // at num_nodes' offset at least
  }
  SECTION("random mutations") {
    std::mt19937 rng(1234);
    for (int i = 0; i < 20000; ++i) {
      auto bad = good;
      const int flips = 1 + static_cast<int>(rng() % 4);
      for (int k = 0; k < flips; ++k) bad[rng() % bad.size()] = std::byte(rng());
      auto r = lcmx::discovery::decode_beacon(bad, &why);
      if (r) CHECK(r->endpoints.size() == static_cast<std::size_t>(r->num_endpoints));
    }
  }
  SECTION("unsupported version") {
    auto b = sample_beacon(1);
    b.version = 99;
    CHECK_FALSE(lcmx::discovery::decode_beacon(lcmx::discovery::encode_beacon(b), &why));
    CHECK_THAT(why, Catch::Contains("version"));
  }
}

TEST_CASE("host id: stable, overridable, bad override refused", "[discovery][identity]") {
  ::unsetenv("LCMX_HOST_ID");
  const auto a = lcmx::discovery::host_id();
  CHECK(a == lcmx::discovery::host_id());
  ::setenv("LCMX_HOST_ID", "0x1234", 1);
  CHECK(lcmx::discovery::host_id() == 0x1234);
  ::setenv("LCMX_HOST_ID", "banana", 1);
  CHECK_THROWS_AS(lcmx::discovery::host_id(), std::invalid_argument);
  ::setenv("LCMX_HOST_ID", "0", 1);
  CHECK_THROWS_AS(lcmx::discovery::host_id(), std::invalid_argument);
  ::unsetenv("LCMX_HOST_ID");
}

TEST_CASE("participants find each other, see updates, goodbyes and lease expiry", "[discovery]") {
  lcmx::discovery::Options o;
  o.group = test_group(1);
  o.period = 50ms;
  o.lease = 400ms;

  std::atomic<int> rev_b{0};
  auto beacon_b = [&] {  // a structural change (a node more): the registry revision grows
    auto b = sample_beacon(2);
    if (rev_b.load()) b.nodes.push_back("c"), b.num_nodes = 3;
    return b;
  };
  std::mutex mu;
  std::vector<std::pair<lcmx::discovery::Change, std::int64_t>> seen;
  lcmx::discovery::Discovery a(o, [] { return sample_beacon(1); },
                               [&](lcmx::discovery::Change c, const lcmx::discovery::Participant& p) {
                                 std::lock_guard lock(mu);
                                 seen.push_back({c, p.beacon.participant_id});
                               });
  auto count = [&](lcmx::discovery::Change c) {
    std::lock_guard lock(mu);
    return std::count_if(seen.begin(), seen.end(), [&](auto& s) { return s.first == c && s.second == 2; });
  };
  {
    lcmx::discovery::Discovery b(o, beacon_b, nullptr);
    REQUIRE(eventually([&] { return count(lcmx::discovery::Change::joined) == 1; }));
    REQUIRE(eventually([&] { return a.participants().size() == 1; }));
    const auto rev0 = a.participants()[0].beacon.revision;
    rev_b = 5;
    b.announce_now();
    REQUIRE(eventually([&] {
      auto ps = a.participants();
      return ps.size() == 1 && ps[0].beacon.revision > rev0 && ps[0].beacon.num_nodes == 3;
    }));
    // An observer sees both participants and is not listed by them.
    lcmx::discovery::Options ob = o;
    ob.observer = true;
    lcmx::discovery::Discovery observer(ob, nullptr, nullptr);
    observer.query();
    REQUIRE(eventually([&] { return observer.participants().size() == 2; }));
    CHECK(a.participants().size() == 1);
  }  // b says goodbye
  REQUIRE(eventually([&] { return count(lcmx::discovery::Change::left) == 1; }, 300ms));
  CHECK(a.counters().goodbyes == 1);

  // A participant that stops beaconing without goodbye: gone after its lease.
  lcmx::discovery::Options quiet = o;
  quiet.period = 10s;  // beacons once, then stays silent for longer than the lease
  {
    lcmx::discovery::Discovery c(quiet, [] { return sample_beacon(3); }, nullptr);
    REQUIRE(eventually([&] { return a.participants().size() == 1; }));
    const auto t0 = std::chrono::steady_clock::now();
    REQUIRE(eventually([&] { return a.participants().empty(); }, 3000ms));
    CHECK(std::chrono::steady_clock::now() - t0 >= 200ms);
    CHECK(a.counters().leases_expired == 1);
  }
}

TEST_CASE("malformed datagrams on the beacon channel are counted, not fatal", "[discovery]") {
  lcmx::discovery::Options o;
  o.group = test_group(2);
  o.period = 50ms;
  lcmx::discovery::Discovery a(o, [] { return sample_beacon(1); }, nullptr);
  auto g = lcmx::udpm::Group::open(o.group);
  const std::byte junk[16] = {};
  g.publish(lcmx::discovery::kBeaconChannel, junk);
  auto bad = lcmx::discovery::encode_beacon(sample_beacon(9));
  bad.resize(bad.size() / 2);
  g.publish(lcmx::discovery::kBeaconChannel, bad);
  REQUIRE(eventually([&] { return a.counters().malformed >= 2; }));
  CHECK(a.participants().empty());
}

TEST_CASE("a flood of fake participants is bounded, counted, and does not displace known ones",
          "[discovery][hostile]") {
  // Anyone on the host can send beacons with fresh participant ids (and any lease they like):
  // the table of participants grew without bound, each entry staying for the lease it announced
  // (up to 24 days).
  lcmx::discovery::Options o;
  o.group = test_group(4);
  o.observer = true;  // only what deliver() hands it
  o.max_participants = 8;
  o.max_table_bytes = 1u << 20;
  o.max_lease = 5000ms;
  o.shared_group = std::make_shared<lcmx::udpm::Group>(lcmx::udpm::Group::open(o.group));
  lcmx::discovery::Discovery d(o, nullptr, nullptr);
  auto deliver = [&](const beacon_t& b) {
    const auto bytes = lcmx::discovery::encode_beacon(b);
    d.deliver(lcmx::udpm::Message{lcmx::discovery::kBeaconChannel, bytes, {}, 0, 0, nullptr});
  };
  auto known = sample_beacon(1);
  known.sequence = 1;
  known.lease_ms = 3000;
  deliver(known);
  for (std::int64_t id = 1000; id < 1100; ++id) {
    auto fake = sample_beacon(id);
    fake.sequence = 1;
    fake.lease_ms = INT32_MAX;  // "keep me for 24 days"
    deliver(fake);
  }
  auto ps = d.participants();
  CHECK(ps.size() == 8);
  CHECK(d.counters().refused == 93);
  for (const auto& p : ps) CHECK(p.beacon.lease_ms <= 5000);  // announced leases are cut
  // The participant that was there first still updates.
  known.sequence = 2;
  known.revision = 5;
  deliver(known);
  ps = d.participants();
  const auto it = std::find_if(ps.begin(), ps.end(), [](const auto& p) { return p.beacon.participant_id == 1; });
  REQUIRE(it != ps.end());
  CHECK(it->beacon.revision == 5);
  // A goodbye frees a place for a new participant.
  auto bye = sample_beacon(1000);
  bye.sequence = 2;
  bye.flags = beacon_t::FLAG_GOODBYE;
  deliver(bye);
  auto newcomer = sample_beacon(2000);
  newcomer.sequence = 1;
  deliver(newcomer);
  CHECK(d.participants().size() == 8);
  CHECK(d.counters().refused == 93);

  // The byte bound: a beacon that would take the table over max_table_bytes is refused.
  auto huge = sample_beacon(3000);
  huge.process_name = std::string(2u << 20, 'x');
  deliver(huge);
  CHECK(d.counters().refused == 94);
}

TEST_CASE("committed beacon seeds still decode (refresh test/fuzz/corpus/beacon when beacon.lcm changes)",
          "[discovery][codec]") {
  std::size_t n = 0;
  for (const auto& f : std::filesystem::directory_iterator(LCMX_BEACON_SEEDS)) {
    std::ifstream in(f.path(), std::ios::binary);
    const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::string why;
    INFO(f.path().string());
    CHECK(lcmx::discovery::decode_beacon(std::as_bytes(std::span(text.data(), text.size())), &why));
    INFO(why);
    ++n;
  }
  CHECK(n >= 3);
}

// A peer's process that exits is gone at once: the registry's speaker watches it (pidfd after
// checking its start time, or its liveness lock in another pid namespace): registry_test.cpp
// "a participant killed -9 is gone at every peer of its host within 100 ms - the speaker too".

TEST_CASE("on_change is told in the table's order: an update never lands after the lease expiry of its participant",
          "[discovery][lifecycle]") {
  // The receiving thread tells "updated" outside the table's lock; the discovery thread
  // expired the same participant meanwhile and told "left" first. The owner (the runtime)
  // then kept the participant for good: seen in the soak as a subscriber retrying a dead
  // publisher's segment forever. Here the owner's "updated" callback is slow (it runs until
  // the participant's lease is over, so the discovery thread expires it meanwhile): what the
  // owner knows must still end equal to the table.
  lcmx::discovery::Options o;
  o.group = test_group(6);
  o.observer = true;  // only what deliver() hands it; expiry still runs on its thread
  o.shared_group = std::make_shared<lcmx::udpm::Group>(lcmx::udpm::Group::open(o.group));
  std::mutex mu;
  std::set<std::int64_t> known;  // the owner's view, as the runtime keeps it
  int lefts = 0;
  std::atomic<bool> slow{false};
  const auto lease = 150ms;
  lcmx::discovery::Discovery d(o, nullptr, [&](lcmx::discovery::Change c, const lcmx::discovery::Participant& p) {
    if (c == lcmx::discovery::Change::updated && slow.exchange(false)) {
      // Busy until the lease of what we were told is long over (a deadline on the clock, not
      // a synchronisation: the discovery thread must have had its chance to expire it).
      const auto until = p.last_seen + lease + 300ms;
      while (std::chrono::steady_clock::now() < until) std::this_thread::sleep_for(1ms);
    }
    std::lock_guard lock(mu);
    if (c == lcmx::discovery::Change::left) {
      known.erase(p.beacon.participant_id);
      ++lefts;
    } else {
      known.insert(p.beacon.participant_id);
    }
  });
  auto b = sample_beacon(42);
  b.lease_ms = static_cast<std::int32_t>(lease.count());
  b.sequence = 1;
  auto deliver = [&] {
    const auto bytes = lcmx::discovery::encode_beacon(b);
    d.deliver(lcmx::udpm::Message{lcmx::discovery::kBeaconChannel, bytes, {}, 0, 0, nullptr});
  };
  deliver();  // joined
  slow = true;
  b.sequence = 2;
  b.revision = 1;
  deliver();  // updated, told slowly while the lease runs out
  // The table forgets it (lease); the owner must forget it too, once told everything.
  REQUIRE(eventually([&] {
    std::lock_guard lock(mu);
    return d.participants().empty() && lefts == 1;
  }));
  std::lock_guard lock(mu);
  CHECK(known.empty());
}

TEST_CASE("a newcomer learns of a quiet participant at once, not a period later", "[discovery]") {
  // Both write their state every 10 s: b reads a's from the registry at its first pass.
  lcmx::discovery::Options o;
  o.group = test_group(5);
  o.period = 10s;
  o.lease = 30s;
  lcmx::discovery::Discovery a(o, [] { return sample_beacon(11); }, nullptr);
  REQUIRE(eventually([&] { return a.counters().beacons_sent >= 1; }));
  lcmx::discovery::Discovery b(o, [] { return sample_beacon(12); }, nullptr);
  REQUIRE(eventually([&] { return a.participants().size() == 1; }, 3000ms));
  REQUIRE(eventually([&] { return b.participants().size() == 1; }, 3000ms));
  CHECK(b.participants()[0].beacon.participant_id == 11);
  // Nothing on the group but the speaker's heartbeats: one state write each, no answers.
  CHECK(a.counters().beacons_sent <= 2);
  CHECK(b.counters().beacons_sent == 1);
}
