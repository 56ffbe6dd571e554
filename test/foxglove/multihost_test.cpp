// `lcmx foxglove` with channels from beyond its process's host: lcmx publishers on another
// emulated host reaching it over UDP on the vehicle group, and a stock liblcm sender on the
// host-local group (lcmx::test::Emulation: network namespaces joined by a bridge; every packet
// stays inside them). The server and the real npm client (node) run inside host A's namespace,
// the server on 127.0.0.1 there. Schemas and messages are checked as in server_test.cpp.
#include <fstream>

#include "lcmx/test/catch_netns.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;

namespace {

const std::string kClientDir = LCMX_FOXGLOVE_CLIENT_DIR;

bool client_installed() {
  return ::access((kClientDir + "/node_modules/@foxglove/ws-protocol/package.json").c_str(), R_OK) == 0;
}

// `lcmx foxglove` inside `host`; its port from the ready line.
int start_server(Hosts& h, int host) {
  Child& c = h.spawn(host, {LCMX_TOOL, "foxglove", "--port", "0", "--json", "--types", LCMX_LCMTYPES_DIR},
                     h.lcmx_env({"SPDLOG_LEVEL=warn"}));
  const auto line = c.expect("{\"ready\":true", 15000ms);
  REQUIRE(line);
  return static_cast<int>(json_num(*line, "port"));
}

// Runs the npm client inside `host` with the plan; its lines up to {"done":...}.
std::vector<std::string> run_client(Hosts& h, int host, const std::string& plan_path, ms timeout) {
  Child& c = h.spawn(host, {LCMX_NODE, kClientDir + "/fg_client.js", plan_path});
  std::vector<std::string> lines;
  const auto deadline = Clock::now() + timeout;
  while (auto l = c.read_line(std::chrono::duration_cast<ms>(deadline - Clock::now()))) {
    lines.push_back(*l);
    if (l->rfind("{\"done\":", 0) == 0) break;
  }
  std::string all;
  for (const auto& l : lines) all += l + "\n";
  std::printf("---- what the client sees ----\n%s", all.c_str());
  return lines;
}

bool any_line(const std::vector<std::string>& lines, std::initializer_list<std::string> words) {
  for (const auto& l : lines) {
    bool all = true;
    for (const auto& w : words) all = all && contains(l, w);
    if (all) return true;
  }
  return false;
}

void check_schemas(Hosts& h, const std::string& dump) {
  const auto r = h.run(0, {LCMX_PYTHON3, LCMX_SCHEMA_CHECK, dump});
  std::printf("%s", r.out.c_str());
  CHECK(r.rc == 0);
  CHECK(contains(r.out, " 0 failed"));
}

}  // namespace

TEST_CASE("lcmx foxglove: publishers on another host reach the client over UDP (vehicle group)",
          "[multihost][foxglove]") {
  LCMX_REQUIRE_NETNS();
  REQUIRE(client_installed());
  Hosts h(2, 40);
  lcmx::it::TmpDir dir;
  const auto pose_ch = h.channel("FG_POSE"), cam_ch = h.channel("FG_CAM");
  // On host B: a pose at 50 Hz and a 64x48 rgb8 image (9 KB, a small topic: UDP) at 5 Hz.
  auto& pose = h.peer(1, {"pub", "--channel", pose_ch, "--type", "pose", "--count", "0", "--rate", "50", "--id", "B"});
  auto& cam = h.peer(1, {"pub", "--channel", cam_ch, "--type", "image", "--count", "0", "--rate", "5", "--width", "64",
                         "--height", "48", "--id", "Bcam"});
  REQUIRE(pose.expect("READY"));
  REQUIRE(cam.expect("READY"));
  const int port = start_server(h, 0);
  const std::string dump = dir.path + "/dump.json", plan = dir.path + "/plan.json";
  std::ofstream(plan) << "{\"url\":\"ws://127.0.0.1:" << port << "\",\"timeout_ms\":30000,\"dump\":\"" << dump
                      << "\",\"subscribe\":[{\"topic\":\"" << pose_ch << "\",\"count\":5},{\"topic\":\"" << cam_ch
                      << "\",\"count\":2},{\"topic\":\"" << cam_ch << "/image\",\"count\":2}],\"graph_topic\":\""
                      << pose_ch << "\"}";
  const auto lines = run_client(h, 0, plan, 40000ms);
  REQUIRE(any_line(lines, {"\"done\":true"}));
  CHECK(any_line(lines, {"\"advertised\"", "\"topic\":\"" + pose_ch + "\"", "lcmx_examples.pose_t", "jsonschema"}));
  CHECK(any_line(lines, {"\"message\"", "\"topic\":\"" + pose_ch + "\"", "\"frame_id\":\"B\""}));
  CHECK(any_line(lines, {"\"message\"", "\"topic\":\"" + cam_ch + "\"", "lcmx_examples.image_t", "\"width\":64"}));
  CHECK(any_line(lines, {"\"message\"", "foxglove.RawImage", "\"width\":64", "\"height\":48", "\"encoding\":\"rgb8\""}));
  // The connection graph names the publisher on host B.
  CHECK(any_line(lines, {"\"graph\"", pose_ch, "lcmx_test_peer"}));
  check_schemas(h, dump);
}

TEST_CASE("lcmx foxglove: a stock liblcm sender on the host-local group is advertised with its type",
          "[multihost][foxglove][interop]") {
  LCMX_REQUIRE_NETNS();
  REQUIRE(client_installed());
  Hosts h(1, 41);
  h.route_local_group_to_lo();
  lcmx::it::TmpDir dir;
  const auto ch = h.channel("FG_STOCK");
  const int port = start_server(h, 0);
  // liblcm (no discovery: the server learns the channel from its datagrams, the type from the
  // first message) sending bench_t, 200 bytes, at 50 Hz until told to quit.
  auto& lcm = h.lcm_peer(0, {"pub", h.discovery_url, ch, "100000", "50", "200", "L"});
  REQUIRE(lcm.expect("ready"));
  const std::string dump = dir.path + "/dump.json", plan = dir.path + "/plan.json";
  std::ofstream(plan) << "{\"url\":\"ws://127.0.0.1:" << port << "\",\"timeout_ms\":30000,\"dump\":\"" << dump
                      << "\",\"subscribe\":[{\"topic\":\"" << ch << "\",\"count\":5}]}";
  const auto lines = run_client(h, 0, plan, 40000ms);
  REQUIRE(any_line(lines, {"\"done\":true"}));
  CHECK(any_line(lines, {"\"advertised\"", "\"topic\":\"" + ch + "\"", "lcmx_examples.bench_t"}));
  // bench_t's data (200 bytes) as base64: 268 characters, shortened in the listing.
  CHECK(any_line(lines, {"\"message\"", "\"topic\":\"" + ch + "\"", "\"size\":200", "(268 chars)"}));
  check_schemas(h, dump);
  lcm.send("quit");
}
