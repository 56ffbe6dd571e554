// The DDS gateway with real processes on one host: `lcmx dds-gateway`, a plain Cyclone DDS C
// program (dds_peer, built from `lcmx idl` + idlc), lcmx publishers/subscribers (lcmx_peer).
// Cyclone runs on loopback only (dds_support.hpp); every test has its own DDS domain and lcmx
// discovery group.
#include "dds_support.hpp"
#include "lcmx_examples/image_t.hpp"
#include "support.hpp"

using namespace lcmx::it;
using namespace lcmx::ddstest;

namespace {

const char* const kFromLcmx0 =
    "sample seq=0 i8=-5 i16=-300 i32=70000 f=0.5 d=3.25 flag=1 b=250 name=from-lcmx fixed3=0.25,0.5,0.75 grid12=42 "
    "origin=1.5/origin corner1=-4/corner n=3 values=3:1,2,3 blob=3:24 m=2 points=2:5/a,6/b tags=2:t1,t2";
const char* const kFromDds1000 =
    "sample seq=1000 i8=-8 i16=-1600 i32=320000 f=1.25 d=-2.5 flag=1 b=200 name=from-dds fixed3=1,2,3 grid12=12 "
    "origin=7.5/o corner1=9/c1 n=3 values=0.5,1.5,2.5 blob=1,2,3 m=2 points=10/p0,11/p1 tags=alpha,beta";

// `lcmx dds-gateway status --json`: the JSON line (empty if no gateway answered).
std::string status_json(Session& s) {
  auto& c = s.spawn({LCMX_TOOL, "dds-gateway", "status", "--json", "--wait", "3000"});
  c.wait(10000ms);
  return json_line(c.text());
}

// Polls the status of gateway `name` until `pred` holds for it (returns that JSON) or 20 s pass
// (returns the last one).
std::string status_until(Session& s, const std::string& name, const std::function<bool(const std::string&)>& pred) {
  std::string last;
  wait_until(
      [&] {
        last = gateway_json(status_json(s), name);
        return !last.empty() && pred(last);
      },
      20000ms, 50ms);
  return last;
}

Child& start_gateway(Session& s, const std::string& config, int domain) {
  auto& gw = s.spawn({LCMX_TOOL, "dds-gateway", "--config", config}, {"SPDLOG_LEVEL=info"}, true);
  (void)domain;
  REQUIRE(gw.expect("dds-gateway ", 15000ms));
  return gw;
}

}  // namespace

TEST_CASE("dds gateway typed - an lcmx publisher's messages reach a plain DDS reader, field by field, on demand",
          "[dds][it]") {
  Session s(1, 60000ms);
  const int domain = unique_domain(1);
  TempDir dir("typed_out");
  const std::string ch = unique_channel("DDS_OUT", 1);
  const auto cfg = dir.write("gw.toml", gateway_head("gw1", domain) +
                                            mapping(ch, "to_dds", "typed", "lcmx_ddstest.sample_t", "topic = \"T1\"\n"));
  start_gateway(s, cfg, domain);
  // No DDS reader yet: the gateway does not subscribe to the channel.
  const auto idle = status_until(s, "gw1", [](const std::string& j) { return field(j, "dds_readers") == 0; });
  CHECK(idle.find("\"exporting\":false") != std::string::npos);
  CHECK(idle.find("\"dds_type\":\"lcmx_ddstest::sample_t\"") != std::string::npos);

  auto& rd = s.spawn({LCMX_DDS_PEER, "read-typed", "T1", "3"}, peer_env(domain));
  REQUIRE(rd.expect("ready", 10000ms));
  auto& pub = s.spawn({LCMX_DDS_LCMX_PEER, "pub", ch, "3"});
  REQUIRE(pub.expect("published 3", 20000ms));
  const auto first = rd.expect("sample seq=0 ", 20000ms);
  REQUIRE(first);
  CHECK(*first == kFromLcmx0);
  CHECK(rd.expect("sample seq=1 ", 10000ms));
  CHECK(rd.expect("sample seq=2 ", 10000ms));
  CHECK(rd.wait(10000ms) == 0);
  // The reader is gone: the export stops again, with the counters of what went out.
  const auto after = status_until(s, "gw1", [](const std::string& j) { return field(j, "dds_readers") == 0; });
  CHECK(field(after, "exported") == 3);
  CHECK(field(after, "export_drops") == 0);
  CHECK(after.find("\"exporting\":false") != std::string::npos);
}

TEST_CASE("dds gateway typed - a plain DDS writer's samples reach a typed lcmx subscriber, shown by lcmx topics",
          "[dds][it]") {
  Session s(2, 60000ms);
  const int domain = unique_domain(2);
  TempDir dir("typed_in");
  const std::string ch = unique_channel("DDS_IN", 2);
  const auto cfg = dir.write("gw.toml", gateway_head("gw2", domain) +
                                            mapping(ch, "from_dds", "typed", "lcmx_ddstest.sample_t", "topic = \"T2\"\n"));
  start_gateway(s, cfg, domain);
  auto& sub = s.spawn({LCMX_DDS_LCMX_PEER, "sub", ch, "2"});
  REQUIRE(sub.expect("ready", 10000ms));
  // lcmx topics marks the channel as mapped by the gateway.
  auto& topics = s.spawn({LCMX_TOOL, "topics", "--wait", "600"});
  topics.wait(10000ms);
  INFO(topics.text());
  CHECK(topics.text().find(ch + "  [") != std::string::npos);
  CHECK(topics.text().find("DDS-mapped by lcmx pid") != std::string::npos);

  auto& wr = s.spawn({LCMX_DDS_PEER, "write-typed", "T2", "2"}, peer_env(domain));
  REQUIRE(wr.expect("written 2", 20000ms));
  const auto got = sub.expect("sample seq=1000 ", 20000ms);
  REQUIRE(got);
  CHECK(*got == kFromDds1000);  // n=3: LCM's size member follows the sequences, not the writer's 99
  CHECK(sub.expect("sample seq=1001 ", 10000ms));
  CHECK(sub.wait(10000ms) == 0);
  const auto st = status_until(s, "gw2", [](const std::string& j) { return field(j, "imported") == 2; });
  CHECK(field(st, "imported") == 2);
  CHECK(field(st, "import_drops") == 0);
}

TEST_CASE("dds gateway opaque - a 6 MB lcmx message reaches a DDS reader as one envelope", "[dds][it]") {
  Session s(3, 60000ms);
  const int domain = unique_domain(3);
  TempDir dir("opaque");
  const std::string ch = unique_channel("DDS_BIG", 3);
  const auto cfg = dir.write("gw.toml", gateway_head("gw3", domain) +
                                            mapping(ch, "to_dds", "opaque", "lcmx_examples.image_t", "topic = \"T3\"\n"));
  start_gateway(s, cfg, domain);
  auto& rd = s.spawn({LCMX_DDS_PEER, "read-opaque", "T3", "1"}, peer_env(domain));
  REQUIRE(rd.expect("ready", 10000ms));
  constexpr long kBytes = 6 * 1000 * 1000;
  auto& pub = s.spawn({LCMX_DDS_LCMX_PEER, "image", ch, std::to_string(kBytes)});
  REQUIRE(pub.expect("published 1", 20000ms));
  // What the envelope must carry: the same image's LCM encoding (fingerprint, size, byte sum).
  lcmx_examples::image_t img{};
  img.width = 1;
  img.height = 1;
  img.encoding = "mono8";
  img.size = static_cast<int32_t>(kBytes);
  img.stride = img.size;
  img.data.resize(kBytes);
  for (std::size_t i = 0; i < img.data.size(); ++i) img.data[i] = static_cast<std::uint8_t>(i * 7 % 251);
  std::vector<std::uint8_t> enc(static_cast<std::size_t>(img.getEncodedSize()));
  img.encode(enc.data(), 0, static_cast<int>(enc.size()));
  double sum = 0;
  for (auto b : enc) sum += b;
  char expected[256];
  std::snprintf(expected, sizeof expected, "envelope channel=%s type=lcmx_examples.image_t fingerprint=%lld size=%zu sum=%.0f",
                ch.c_str(), static_cast<long long>(lcmx_examples::image_t::getHash()), enc.size(), sum);
  const auto got = rd.expect("envelope ", 30000ms);
  REQUIRE(got);
  CHECK(*got == expected);
  CHECK(rd.wait(10000ms) == 0);
}

TEST_CASE("dds gateways - two gateways mapping one channel both ways do not loop", "[dds][it]") {
  Session s(4, 80000ms);
  const int domain = unique_domain(4);
  TempDir dir("loop");
  const std::string ch = unique_channel("DDS_LOOP", 4);
  const std::string map = mapping(ch, "both", "typed", "lcmx_ddstest.sample_t", "topic = \"T4\"\n");
  start_gateway(s, dir.write("a.toml", gateway_head("gwa", domain) + map), domain);
  start_gateway(s, dir.write("b.toml", gateway_head("gwb", domain) + map), domain);
  // A native DDS reader (export demand on both gateways) and an lcmx subscriber (import demand).
  auto& rd = s.spawn({LCMX_DDS_PEER, "read-typed", "T4", "4"}, peer_env(domain));
  REQUIRE(rd.expect("ready", 10000ms));
  auto& sub = s.spawn({LCMX_DDS_LCMX_PEER, "sub", ch, "2", "stay"});
  REQUIRE(sub.expect("ready", 10000ms));
  // Each gateway's import reader (there is an lcmx subscriber) has matched the other's writer.
  for (const char* name : {"gwa", "gwb"})
    REQUIRE(field(status_until(s, name, [](const std::string& j) { return field(j, "dds_writers") == 1; }),
                  "dds_writers") == 1);
  // The publisher waits for the lcmx subscriber and both gateways' export subscribers.
  auto& pub = s.spawn({LCMX_DDS_LCMX_PEER, "pub", ch, "2", "3"});
  REQUIRE(pub.expect("published 2", 30000ms));
  CHECK(sub.expect("done", 20000ms));  // its 2 messages, straight from the publisher
  // The DDS reader gets each message from each gateway: 4, and the run ends there.
  CHECK(rd.wait(20000ms) == 0);
  for (const char* name : {"gwa", "gwb"}) {
    const auto st = status_until(s, name, [](const std::string& j) { return field(j, "suppressed") >= 2; });
    INFO(name << ": " << st);
    CHECK(field(st, "exported") == 2);
    CHECK(field(st, "suppressed") == 2);
    CHECK(field(st, "imported") == 0);
  }
  // Nothing more reached the lcmx subscriber (a loop would have brought the messages back).
  CHECK(sub.text().find("sample seq=0") == sub.text().rfind("sample seq=0"));
}

TEST_CASE("dds gateway - a DDS writer of another type on a mapped topic is reported, not crashed on", "[dds][it]") {
  Session s(5, 60000ms);
  const int domain = unique_domain(5);
  TempDir dir("mismatch");
  const std::string ch = unique_channel("DDS_MIS", 5);
  const auto cfg = dir.write("gw.toml", gateway_head("gw5", domain) +
                                            mapping(ch, "both", "typed", "lcmx_ddstest.sample_t", "topic = \"T5\"\n"));
  auto& gw = start_gateway(s, cfg, domain);
  auto& sub = s.spawn({LCMX_DDS_LCMX_PEER, "sub", ch, "1"});
  REQUIRE(sub.expect("ready", 10000ms));
  auto& other = s.spawn({LCMX_DDS_PEER, "write-other", "T5"}, peer_env(domain));
  REQUIRE(other.expect("ready", 10000ms));
  const auto st = status_until(s, "gw5", [](const std::string& j) { return j.find("has type lcmx::dds::Envelope") != std::string::npos; });
  INFO(st);
  CHECK(st.find("a DDS writer on topic 'T5' has type lcmx::dds::Envelope, this mapping's is lcmx_ddstest::sample_t") !=
        std::string::npos);
  CHECK(field(st, "imported") == 0);
  // The gateway still works: a writer of the right type gets through.
  auto& wr = s.spawn({LCMX_DDS_PEER, "write-typed", "T5", "1"}, peer_env(domain));
  REQUIRE(wr.expect("written 1", 20000ms));
  CHECK(sub.expect("sample seq=1000 ", 10000ms));
  gw.signal(SIGTERM);
  CHECK(gw.wait(10000ms) == 0);
}

TEST_CASE("lcmx dds-gateway - bad configs and an unknown interface exit with a clear error", "[dds][it]") {
  Session s(6, 30000ms);
  TempDir dir("cli");
  const auto bad = dir.write("bad.toml", "name = \"gw\"\ndomain = 999\n");
  auto& c1 = s.spawn({LCMX_TOOL, "dds-gateway", "--config", bad}, {}, true);
  CHECK(c1.wait(10000ms) == 2);
  CHECK_THAT(c1.text(), Catch::Contains("bad config: " + bad + ": domain: must be an integer from 0 to 230"));
  auto& c2 = s.spawn({LCMX_TOOL, "dds-gateway", "--config", dir.path().string() + "/missing.toml"}, {}, true);
  CHECK(c2.wait(10000ms) == 2);
  CHECK_THAT(c2.text(), Catch::Contains("cannot read: no such file"));
  const auto good = dir.write("good.toml", gateway_head("gw6", unique_domain(6)) + mapping("X6", "both", "opaque", ""));
  auto& c3 = s.spawn({LCMX_TOOL, "dds-gateway", "--config", good, "--check"}, {}, true);
  CHECK(c3.wait(10000ms) == 0);
  CHECK_THAT(c3.text(), Catch::Contains("ok: dds-gateway gw6"));
  // An interface Cyclone cannot use: exit 1, naming it.
  const auto noif = dir.write("noif.toml", gateway_head("gw6", unique_domain(6), "nosuchif0", "127.0.0.1") +
                                               mapping("X6", "both", "opaque", ""));
  auto& c4 = s.spawn({LCMX_TOOL, "dds-gateway", "--config", noif}, {}, true);
  CHECK(c4.wait(15000ms) == 1);
  CHECK_THAT(c4.text(), Catch::Contains("interface nosuchif0"));
  auto& c5 = s.spawn({LCMX_TOOL, "dds-gateway", "--help"}, {}, true);
  CHECK(c5.wait(10000ms) == 0);
  CHECK_THAT(c5.text(), Catch::Contains("status"));
}
