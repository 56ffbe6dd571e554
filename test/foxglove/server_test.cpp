// `lcmx foxglove` seen by the real Foxglove client (@foxglove/ws-protocol's FoxgloveClient over
// `ws`, test/foxglove/client/fg_client.js, run by Node.js): both subprotocols, schemas checked
// by an independent validator (schema_check.py, python3-jsonschema), typed messages from shm
// publishers, an image as foxglove.RawImage, clientPublish to a typed C++ subscriber, an lcmx
// service, the connection graph, a slow client that neither delays another client nor grows
// without bound, a type in no .lcm file (lcmx.unknown), `lcmx play` with the `time` capability,
// and wss:// with a throwaway certificate. Every process is a real one (lcmx, lcmx_test_peer,
// lcmx_service_peer, lcmx_fg_raw_peer, node, openssl); the server listens on 127.0.0.1, port 0
// (read back from its ready line). Other hosts and stock LCM senders: multihost_test.cpp.
#include <cstdlib>
#include <catch2/catch.hpp>

#include <fstream>
#include <regex>

#include "lcmx/log/eventlog.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "support.hpp"

using namespace lcmx::it;

namespace {

const std::string kClientDir = LCMX_FOXGLOVE_CLIENT_DIR;

void require_client() {
  INFO("the npm client is installed by scripts/setup.sh (npm ci in " << kClientDir << ")");
  REQUIRE(::access((kClientDir + "/node_modules/@foxglove/ws-protocol/package.json").c_str(), R_OK) == 0);
  REQUIRE(::access(LCMX_NODE, X_OK) == 0);
}

// Starts `lcmx foxglove --port 0 --json` with `args`; returns its port from the ready line.
int start_server(Session& s, std::vector<std::string> args, Child** out = nullptr) {
  std::vector<std::string> argv{LCMX_TOOL, "foxglove", "--port", "0", "--json", "--types", LCMX_LCMTYPES_DIR};
  for (auto& a : args) argv.push_back(std::move(a));
  Child& c = s.spawn(argv);
  if (out) *out = &c;
  const auto line = c.expect("{\"ready\":true", 15000ms);
  REQUIRE(line);
  return static_cast<int>(json_num(*line, "port"));
}

std::string write_plan(const TmpDir& dir, const std::string& name, const std::string& json) {
  const std::string path = dir.path + "/" + name;
  std::ofstream(path) << json;
  return path;
}

Child& client(Session& s, const std::string& plan) { return s.spawn({LCMX_NODE, kClientDir + "/fg_client.js", plan}); }

// Lines of the client until its {"done":...} line; every line printed for the listing.
std::vector<std::string> run_client(Child& c, ms timeout) {
  std::vector<std::string> lines;
  const auto deadline = Clock::now() + timeout;
  while (auto l = c.read_line(std::chrono::duration_cast<ms>(deadline - Clock::now()))) {
    lines.push_back(*l);
    if (l->rfind("{\"done\":", 0) == 0) break;
  }
  return lines;
}
bool any_line(const std::vector<std::string>& lines, std::initializer_list<const char*> words) {
  for (const auto& l : lines) {
    bool all = true;
    for (const char* w : words) all = all && contains(l, w);
    if (all) return true;
  }
  return false;
}
std::string joined(const std::vector<std::string>& lines) {
  std::string s;
  for (const auto& l : lines) s += l + "\n";
  return s;
}

}  // namespace

TEST_CASE("lcmx foxglove: both subprotocols, valid schemas, typed messages, an image, publish, a service, the graph",
          "[foxglove]") {
  require_client();
  Session s(0, 90000ms);
  TmpDir dir;
  const std::string pose_ch = unique_channel("FG_POSE", 0), cam_ch = unique_channel("FG_CAM", 0),
                    cmd_ch = unique_channel("FG_CMD", 0), svc = unique_channel("FG_SVC", 0);
  Child& pose = s.peer({"pub", "--channel", pose_ch, "--type", "pose", "--count", "0", "--rate", "50", "--id", "shm"});
  Child& cam = s.peer({"pub", "--channel", cam_ch, "--type", "image", "--count", "0", "--rate", "5", "--width", "64",
                       "--height", "48", "--id", "cam"});
  Child& sub = s.peer({"sub", "--channel", cmd_ch, "--type", "pose", "--expect", "3"});
  Child& server = s.spawn({LCMX_SERVICE_PEER, "server", "--name", svc, "--timeout-ms", "80000"});
  REQUIRE(pose.expect("READY"));
  REQUIRE(cam.expect("READY"));
  REQUIRE(sub.expect("READY"));
  REQUIRE(server.expect("READY"));
  const int port = start_server(s, {"--publish-allow", ".*FG_CMD.*"});

  for (const std::string proto : {"foxglove.websocket.v1", "foxglove.sdk.v1"}) {
    DYNAMIC_SECTION("subprotocol " << proto) {
      const bool full = proto == "foxglove.websocket.v1";
      const std::string dump = dir.path + "/dump_" + proto + ".json";
      std::string plan = "{\"url\":\"ws://127.0.0.1:" + std::to_string(port) + "\",\"subprotocol\":\"" + proto +
                         "\",\"timeout_ms\":40000,\"dump\":\"" + dump + "\",\"subscribe\":[{\"topic\":\"" + pose_ch +
                         "\",\"count\":3},{\"topic\":\"" + cam_ch + "\",\"count\":2},{\"topic\":\"" + cam_ch +
                         "/image\",\"count\":2}]";
      if (full) {
        plan += ",\"publish\":[{\"topic\":\"" + cmd_ch +
                "\",\"schemaName\":\"lcmx_examples.pose_t\",\"period_ms\":100,\"messages\":["
                "{\"header\":{\"seq\":1},\"position\":[1,0,0],\"orientation\":[0,0,0,1]},"
                "{\"header\":{\"seq\":2},\"position\":[2,0,0],\"orientation\":[0,0,0,1]},"
                "{\"header\":{\"seq\":3},\"position\":[3,0,0],\"orientation\":[0,0,0,1]},"
                "{\"header\":{\"seq\":4},\"position\":[4,0,0],\"orientation\":[0,0,0,1]},"
                "{\"header\":{\"seq\":5},\"position\":[5,0,0],\"orientation\":[0,0,0,1]}]}]";
        plan += ",\"call\":[{\"service\":\"" + svc + "\",\"request\":{\"position\":[7,16,0]}}]";
        plan += ",\"graph_topic\":\"" + pose_ch + "\"";
      }
      plan += "}";
      Child& c = client(s, write_plan(dir, "plan.json", plan));
      const auto lines = run_client(c, 60000ms);
      const std::string all = joined(lines);
      std::printf("---- what the client sees (%s) ----\n%s", proto.c_str(), all.c_str());
      REQUIRE(any_line(lines, {"\"done\":true"}));
      CHECK(any_line(lines, {"serverInfo", ("\"subprotocol\":\"" + proto + "\"").c_str()}));
      CHECK(any_line(lines, {"\"advertised\"", ("\"topic\":\"" + pose_ch + "\"").c_str(), "lcmx_examples.pose_t",
                             "\"encoding\":\"json\"", "jsonschema"}));
      CHECK(any_line(lines, {"\"advertised\"", ("\"topic\":\"" + cam_ch + "/image\"").c_str(), "foxglove.RawImage"}));
      CHECK(any_line(lines, {"\"message\"", ("\"topic\":\"" + pose_ch + "\"").c_str(), "\"frame_id\":\"shm\""}));
      CHECK(any_line(lines, {"\"message\"", "foxglove.RawImage", "\"width\":64", "\"height\":48", "\"encoding\":\"rgb8\"",
                             "\"step\":192"}));
      // Every schema valid and within Foxglove's reader; the messages received match them.
      const auto check = s.run({LCMX_PYTHON3, LCMX_SCHEMA_CHECK, dump});
      std::printf("%s", check.out.c_str());
      CHECK(check.rc == 0);
      CHECK(contains(check.out, " 0 failed"));
      if (full) {
        CHECK(any_line(lines, {"\"published\"", cmd_ch.c_str()}));
        // The typed C++ subscriber got the published poses (its own content check passed).
        const auto summary = sub.expect("SUMMARY", 20000ms);
        REQUIRE(summary);
        const auto kv = parse_kv(*summary);
        CHECK(std::stoll(kv.at("received")) >= 3);
        CHECK(kv.at("bad_content") == "0");
        CHECK(any_line(lines, {"\"service\"", svc.c_str(), "lcmx_examples.pose_t", "lcmx_examples.bench_t"}));
        // service_peer answers a bench_t: seq = position[0], size = position[1] bytes.
        CHECK(any_line(lines, {"\"called\"", "\"ok\":true", "\"seq\":7", "\"size\":16"}));
        CHECK(any_line(lines, {"\"graph\"", pose_ch.c_str(), "lcmx_test_peer"}));
      }
    }
  }
}

TEST_CASE("lcmx foxglove: a slow client does not delay another client, and its queue stays bounded", "[foxglove]") {
  require_client();
#if defined(__SANITIZE_ADDRESS__)
  {  // the server inherits it: a small quarantine, so its RSS shows its queues, not ASan's
    const char* cur = std::getenv("ASAN_OPTIONS");
    const std::string opts = std::string(cur ? cur : "") + (cur && *cur ? ":" : "") + "quarantine_size_mb=16";
    ::setenv("ASAN_OPTIONS", opts.c_str(), 1);
  }
#endif
  Session s(1, 90000ms);
  TmpDir dir;
  const std::string small = unique_channel("FG_SMALL", 1), cam = unique_channel("FG_BIG", 1);
  Child& p1 = s.peer({"pub", "--channel", small, "--type", "pose", "--count", "0", "--rate", "100", "--id", "s"});
  Child& p2 = s.peer({"pub", "--channel", cam, "--type", "image", "--count", "0", "--rate", "20", "--width", "640",
                      "--height", "480", "--id", "c"});
  REQUIRE(p1.expect("READY"));
  REQUIRE(p2.expect("READY"));
  Child* server = nullptr;
  // A 4 MiB queue: the slow client's bound is a few images.
  const int port = start_server(s, {"--queue-mb", "4", "--stats", "0.5"}, &server);
  const std::string url = "ws://127.0.0.1:" + std::to_string(port);
  Child& slow = client(s, write_plan(dir, "slow.json",
                                     "{\"url\":\"" + url + "\",\"timeout_ms\":60000,\"subscribe_all\":true,\"slow\":true,"
                                     "\"expect_topics\":[\"" + small + "\",\"" + cam + "\"],\"run_ms\":30000}"));
  REQUIRE(slow.expect("{\"event\":\"paused\"", 20000ms));
  // Let the slow client's queue fill: the server must drop from it (counted).
  REQUIRE(wait_until(
      [&] {
        auto l = server->read_line(1000ms);
        return l && json_num(*l, "dropped") > 20;
      },
      30000ms));
  // A second client, reading, still gets both channels at their rate while the slow one is stuck.
  Child& fast = client(s, write_plan(dir, "fast.json",
                                     "{\"url\":\"" + url + "\",\"timeout_ms\":40000,\"count_only\":true,\"subscribe\":["
                                     "{\"topic\":\"" + small + "\",\"count\":1},{\"topic\":\"" + cam + "\",\"count\":1}],"
                                     "\"run_ms\":3000,\"stats_every_ms\":3000}"));
  const auto lines = run_client(fast, 45000ms);
  std::printf("---- the reading client beside a stuck one ----\n%s", joined(lines).c_str());
  REQUIRE(any_line(lines, {"\"done\":true"}));
  std::string stats;
  for (const auto& l : lines)
    if (contains(l, "\"stats\"")) stats = l;
  REQUIRE(!stats.empty());
  // ~100 Hz and ~20 Hz (generous: 2 shared CPUs).
  const std::regex rate_re("\"" + small + "\":\\{\"rate\":([0-9.]+)");
  std::smatch m;
  REQUIRE(std::regex_search(stats, m, rate_re));
  CHECK(std::stod(m[1]) > 60);
  const std::regex cam_re("\"" + cam + "\":\\{\"rate\":([0-9.]+)");
  REQUIRE(std::regex_search(stats, m, cam_re));
  CHECK(std::stod(m[1]) > 10);
  // The publishers were never slowed: both still publish at their rates (their own counters).
  // The server's memory stays bounded: its resident set is far below what the stuck client
  // would have queued unbounded (20 images/s of 0.9 MB for 20 s = 370 MB).
  std::ifstream st("/proc/" + std::to_string(server->pid()) + "/status");
  std::string line;
  long rss_kb = 0;
  while (std::getline(st, line))
    if (line.rfind("VmRSS:", 0) == 0) rss_kb = std::atol(line.c_str() + 6);
  std::printf("server VmRSS %ld kB\n", rss_kb);
  CHECK(rss_kb > 0);
#if defined(__SANITIZE_ADDRESS__)
  // AddressSanitizer keeps freed memory in its quarantine (16 MiB for the server, set at the
  // top of this test) and shadow memory besides: 100 MiB more, still below an unbounded queue.
  constexpr long kBoundKb = 300 * 1024;
#else
  constexpr long kBoundKb = 200 * 1024;
#endif
  CHECK(rss_kb < kBoundKb);
  slow.signal(SIGTERM);
}

TEST_CASE("lcmx foxglove: a type in no .lcm file is advertised as lcmx.unknown, its messages as base64",
          "[foxglove]") {
  require_client();
  Session s(2, 60000ms);
  TmpDir dir;
  // Two raw publishers of a made-up type: one announces no type (the server learns the
  // fingerprint from a message), one announces it ("lcmx_test.mystery_t"): neither is dropped.
  const std::string ch = unique_channel("FG_RAW", 2);
  Child& raw = s.spawn({LCMX_FG_RAW_PEER, ch, "50"});
  REQUIRE(raw.expect("READY"));
  const int port = start_server(s, {});
  const std::string dump = dir.path + "/dump.json";
  Child& c = client(s, write_plan(dir, "plan.json",
                                  "{\"url\":\"ws://127.0.0.1:" + std::to_string(port) +
                                      "\",\"timeout_ms\":30000,\"dump\":\"" + dump + "\",\"subscribe\":[{\"topic\":\"" +
                                      ch + "\",\"count\":3},{\"topic\":\"" + ch + "_T\",\"count\":3}]}"));
  const auto lines = run_client(c, 40000ms);
  std::printf("---- what the client sees ----\n%s", joined(lines).c_str());
  REQUIRE(any_line(lines, {"\"done\":true"}));
  for (const std::string& topic : {ch, ch + "_T"}) {
    INFO("topic " << topic);
    CHECK(any_line(lines, {"\"advertised\"", ("\"topic\":\"" + topic + "\"").c_str(), "\"schemaName\":\"lcmx.unknown\"",
                           "\"encoding\":\"json\""}));
    // The whole LCM encoding, base64: fingerprint 0123456789abcdef + "unknown payload!".
    CHECK(any_line(lines, {"\"message\"", ("\"topic\":\"" + topic + "\"").c_str(),
                           "\"fingerprint\":\"0x0123456789abcdef\"", "\"size\":24",
                           "\"data\":\"ASNFZ4mrze91bmtub3duIHBheWxvYWQh\""}));
  }
  const auto check = s.run({LCMX_PYTHON3, LCMX_SCHEMA_CHECK, dump});
  std::printf("%s", check.out.c_str());
  CHECK(check.rc == 0);
  raw.send("quit");
  CHECK(raw.wait() == 0);
}

TEST_CASE("lcmx foxglove: lcmx play's channels appear, and time follows the log's clock while it plays", "[foxglove]") {
  require_client();
  Session s(3, 90000ms);
  TmpDir dir;
  const std::string pose_ch = unique_channel("FG_LOG_POSE", 3), cam_ch = unique_channel("FG_LOG_CAM", 3);
  // A log of 20 s starting 2001-09-09T01:46:40Z (far from now: a receive-time stamp would show):
  // poses at 50 Hz, a 32x24 image at 5 Hz.
  constexpr std::int64_t t0_us = 1'000'000'000'000'000;
  constexpr std::int64_t span_us = 20'000'000;
  const std::string log = dir.path + "/play.lcmlog";
  {
    auto w = lcmx::eventlog::Writer::open(log, lcmx::eventlog::OpenMode::create);
    for (std::int64_t k = 0; k * 20'000 <= span_us; ++k) {
      const std::int64_t t = t0_us + k * 20'000;
      lcmx_examples::pose_t p{};
      p.header.seq = k;
      p.header.frame_id = "log";
      p.position[0] = static_cast<double>(k);
      p.orientation[3] = 1;
      std::vector<std::byte> buf(static_cast<std::size_t>(p.getEncodedSize()));
      REQUIRE(p.encode(buf.data(), 0, static_cast<int>(buf.size())) == static_cast<int>(buf.size()));
      w.write(t, pose_ch, buf);
      if (k % 10 == 0) {
        lcmx_examples::image_t img{};
        img.header.seq = k;
        img.width = 32;
        img.height = 24;
        img.stride = 96;
        img.encoding = "rgb8";
        img.size = 96 * 24;
        img.data.assign(96 * 24, static_cast<std::uint8_t>(k));
        std::vector<std::byte> ib(static_cast<std::size_t>(img.getEncodedSize()));
        REQUIRE(img.encode(ib.data(), 0, static_cast<int>(ib.size())) == static_cast<int>(ib.size()));
        w.write(t, cam_ch, ib);
      }
    }
    w.close();
  }
  Child* server = nullptr;
  const int port = start_server(s, {"--stats", "0.2"}, &server);
  Child& play = s.spawn({LCMX_TOOL, "play", log, "--delay", "0", "--json"});
  const std::string dump = dir.path + "/dump.json";
  Child& c = client(s, write_plan(dir, "plan.json",
                                  "{\"url\":\"ws://127.0.0.1:" + std::to_string(port) +
                                      "\",\"timeout_ms\":40000,\"expect_capability\":\"time\",\"dump\":\"" + dump +
                                      "\",\"subscribe\":[{\"topic\":\"" + pose_ch + "\",\"count\":20},{\"topic\":\"" +
                                      cam_ch + "/image\",\"count\":2}],\"time_count\":20,\"report_timestamps\":true}"));
  const auto lines = run_client(c, 50000ms);
  std::printf("---- what the client sees ----\n%s", joined(lines).c_str());
  REQUIRE(any_line(lines, {"\"done\":true"}));
  CHECK(any_line(lines, {"serverInfo", "\"time\""}));
  CHECK(any_line(lines, {"\"advertised\"", ("\"topic\":\"" + pose_ch + "\"").c_str(), "lcmx_examples.pose_t"}));
  CHECK(any_line(lines, {"\"advertised\"", ("\"topic\":\"" + cam_ch + "/image\"").c_str(), "foxglove.RawImage"}));
  CHECK(any_line(lines, {"\"message\"", ("\"topic\":\"" + pose_ch + "\"").c_str(), "\"frame_id\":\"log\""}));
  CHECK_FALSE(any_line(lines, {"LCMX_PLAY_CLOCK"}));  // the clock is the `time`, not a channel
  // `time` follows the log: within its span, never backwards.
  const std::int64_t lo_ns = t0_us * 1000, hi_ns = (t0_us + span_us + 1'000'000) * 1000;
  auto field = [](const std::string& line, const std::string& key) {
    const std::regex re("\"" + key + "\":\"?([0-9]+)");
    std::smatch m;
    REQUIRE(std::regex_search(line, m, re));
    return std::stoll(m[1]);
  };
  bool saw_time = false;
  for (const auto& l : lines) {
    if (contains(l, "\"event\":\"time\"")) {
      saw_time = true;
      CHECK(field(l, "min") >= lo_ns);
      CHECK(field(l, "max") <= hi_ns);
      CHECK(field(l, "decreasing") == 0);
    }
    // Message timestamps on the same clock (pose_t has no utime: the log's time at receipt).
    if (contains(l, "\"event\":\"timestamps\"") && contains(l, pose_ch)) {
      CHECK(field(l, "min") >= lo_ns);
      CHECK(field(l, "max") <= hi_ns);
    }
  }
  CHECK(saw_time);
  const auto check = s.run({LCMX_PYTHON3, LCMX_SCHEMA_CHECK, dump});
  std::printf("%s", check.out.c_str());
  CHECK(check.rc == 0);
  // When play stops, the server stops following its clock.
  play.send("quit");
  CHECK(play.wait(15000ms) == 0);
  CHECK(json_until(*server, [](const std::string& l) { return contains(l, "\"time\":false"); }, 10000ms));
}

TEST_CASE("lcmx foxglove: wss:// with a throwaway self-signed certificate", "[foxglove]") {
  require_client();
  Session s(4, 60000ms);
  TmpDir dir;
  const std::string cert = dir.path + "/cert.pem", key = dir.path + "/key.pem";
  const auto gen = s.run({LCMX_OPENSSL, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
                          "-nodes", "-keyout", key, "-out", cert, "-days", "1", "-subj", "/CN=127.0.0.1", "-addext",
                          "subjectAltName=IP:127.0.0.1"});
  INFO(gen.out);
  REQUIRE(gen.rc == 0);
  const std::string ch = unique_channel("FG_TLS", 4);
  Child& pose = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "50", "--id", "tls"});
  REQUIRE(pose.expect("READY"));
  std::vector<std::string> argv{LCMX_TOOL, "foxglove", "--port",     "0",  "--json",     "--types",
                                LCMX_LCMTYPES_DIR, "--tls-cert", cert, "--tls-key", key};
  Child& server = s.spawn(argv);
  const auto ready = server.expect("{\"ready\":true", 15000ms);
  REQUIRE(ready);
  CHECK(contains(*ready, "\"url\":\"wss://127.0.0.1:"));
  const std::string port = std::to_string(static_cast<int>(json_num(*ready, "port")));
  // The client trusts exactly this certificate (and checks it names 127.0.0.1).
  Child& c = client(s, write_plan(dir, "tls.json",
                                  "{\"url\":\"wss://127.0.0.1:" + port + "\",\"ca\":\"" + cert +
                                      "\",\"timeout_ms\":30000,\"subscribe\":[{\"topic\":\"" + ch + "\",\"count\":3}]}"));
  const auto lines = run_client(c, 40000ms);
  std::printf("---- over wss:// ----\n%s", joined(lines).c_str());
  REQUIRE(any_line(lines, {"\"done\":true"}));
  CHECK(any_line(lines, {"serverInfo", "foxglove.websocket.v1"}));
  CHECK(any_line(lines, {"\"message\"", ("\"topic\":\"" + ch + "\"").c_str(), "\"frame_id\":\"tls\""}));
  // Plain ws:// to the TLS port gets no WebSocket.
  Child& plain = client(s, write_plan(dir, "plain.json", "{\"url\":\"ws://127.0.0.1:" + port + "\",\"timeout_ms\":5000}"));
  const auto plain_lines = run_client(plain, 15000ms);
  std::printf("---- plain ws:// to it ----\n%s", joined(plain_lines).c_str());
  CHECK(any_line(plain_lines, {"\"done\":false"}));
  CHECK_FALSE(any_line(plain_lines, {"\"event\":\"serverInfo\""}));
}
