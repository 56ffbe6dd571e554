// lcmx graph's DOT and JSON (apps/lcmx/graph_model.hpp) from hand-made beacons.
#include <catch2/catch.hpp>

#include <algorithm>

#include "graph_model.hpp"

namespace {

using lcmx::discovery::Participant;
using Endpoint = lcmx_msgs::endpoint_t;

Participant graph_participant(std::int64_t id, std::int64_t host, const std::string& proc, int pid) {
  Participant p;
  p.beacon.participant_id = id;
  p.beacon.host_id = host;
  p.beacon.process_name = proc;
  p.beacon.pid = pid;
  p.beacon.flags = 0;  // lcm-gen leaves members uninitialised
  return p;
}

Endpoint& add(Participant& p, std::int64_t id, std::int8_t kind, const std::string& node, const std::string& topic,
              const std::string& type = "") {
  Endpoint e;
  e.id = id;
  e.kind = kind;
  e.node = node;
  e.topic = topic;
  e.type_name = type;
  e.fingerprint = type.empty() ? 0 : 1;
  p.beacon.endpoints.push_back(e);
  if (std::find(p.beacon.nodes.begin(), p.beacon.nodes.end(), node) == p.beacon.nodes.end())
    p.beacon.nodes.push_back(node);
  return p.beacon.endpoints.back();
}

void match(Endpoint& sub, std::int64_t pp, std::int64_t pe, const std::string& path) {
  lcmx_msgs::match_t m;
  m.publisher_participant = pp;
  m.publisher_endpoint = pe;
  m.path = path;
  sub.matches.push_back(m);
}

std::vector<Participant> system() {
  auto cam = graph_participant(11, 0x1, "camera", 100);
  add(cam, 1, Endpoint::KIND_PUBLISHER, "driver", "IMAGE", "image_t");
  auto viewer = graph_participant(22, 0x1, "viewer", 200);
  auto& s = add(viewer, 1, Endpoint::KIND_SUBSCRIBER, "view", "IMAGE", "image_t");
  match(s, 11, 1, "shm");
  match(s, 0, 999, "udp");  // a stock LCM sender
  auto remote = graph_participant(33, 0x2, "planner", 300);
  auto& r = add(remote, 5, Endpoint::KIND_SUBSCRIBER, "plan", "IMAGE", "image_t");
  match(r, 11, 1, "udp");
  add(remote, 6, Endpoint::KIND_SUBSCRIBER, "plan", "ORPHAN");
  return {remote, viewer, cam};  // unsorted on purpose
}

}  // namespace

TEST_CASE("DOT: a cluster per host and per process, node boxes, topics, one labelled edge per pair", "[graph]") {
  const auto dot = lcmx::cli::graph::to_dot(system());
  INFO(dot);
  CHECK(dot.rfind("digraph lcmx {", 0) == 0);
  CHECK(dot.find("subgraph \"cluster_host_0000000000000001\"") != std::string::npos);
  CHECK(dot.find("subgraph \"cluster_host_0000000000000002\"") != std::string::npos);
  CHECK(dot.find("label=\"camera[100]\"") != std::string::npos);
  CHECK(dot.find("\"n_11_driver\" [shape=box, label=\"driver\"]") != std::string::npos);
  CHECK(dot.find("\"t_IMAGE\" [shape=ellipse") != std::string::npos);
  CHECK(dot.find("label=\"IMAGE\\nimage_t\"") != std::string::npos);
  CHECK(dot.find("\"n_11_driver\" -> \"t_IMAGE\";") != std::string::npos);
  CHECK(dot.find("\"t_IMAGE\" -> \"n_22_view\" [label=\"shm from camera[100]/driver\"]") != std::string::npos);
  CHECK(dot.find("\"t_IMAGE\" -> \"n_33_plan\" [label=\"udp from camera[100]/driver\"]") != std::string::npos);
  CHECK(dot.find("\"stock_lcm\" -> \"t_IMAGE\"") != std::string::npos);
  CHECK(dot.find("\"t_IMAGE\" -> \"n_22_view\" [label=\"udp from LCM sender\"]") != std::string::npos);
  CHECK(dot.find("\"t_ORPHAN\" -> \"n_33_plan\" [style=dotted, label=\"no publisher\"]") != std::string::npos);
  // Host 1 (camera before viewer) comes before host 2 whatever the input order.
  CHECK(dot.find("cluster_p_11") < dot.find("cluster_p_22"));
  CHECK(dot.find("cluster_p_22") < dot.find("cluster_p_33"));
  CHECK(dot.back() == '\n');
}

TEST_CASE("DOT is stable across beacon order and counters, and changes with the structure", "[graph]") {
  auto a = system();
  auto b = system();
  std::reverse(b.begin(), b.end());
  b[0].beacon.endpoints[0].messages = 12345;  // counters are not part of the graph
  b[0].beacon.endpoints[0].rate_hz = 30;
  CHECK(lcmx::cli::graph::to_dot(a) == lcmx::cli::graph::to_dot(b));
  add(b[1], 9, Endpoint::KIND_PUBLISHER, "view", "CMD");
  CHECK(lcmx::cli::graph::to_dot(a) != lcmx::cli::graph::to_dot(b));
  CHECK(lcmx::cli::graph::to_dot({}) == lcmx::cli::graph::to_dot({}));
}

TEST_CASE("JSON: hosts, processes, nodes, publishes, subscribes with pairs, topics", "[graph]") {
  const auto j = lcmx::cli::graph::to_json(system());
  INFO(j);
  CHECK(j.find("{\"host\":\"0000000000000001\",\"processes\":[{\"process\":\"camera\",\"pid\":100,"
               "\"participant\":11,\"bridge\":false,\"nodes\":[{\"node\":\"driver\",\"publishes\":"
               "[{\"topic\":\"IMAGE\",\"type\":\"image_t\"}],\"subscribes\":[]}]}") != std::string::npos);
  CHECK(j.find("\"pairs\":[{\"publisher\":\"LCM sender\",\"path\":\"udp\"},{\"publisher\":\"camera[100]/driver\","
               "\"path\":\"shm\"}]") != std::string::npos);
  CHECK(j.find("{\"topic\":\"IMAGE\",\"types\":[\"image_t\"],\"publishers\":1,\"subscribers\":2}") !=
        std::string::npos);
  CHECK(j.find("{\"topic\":\"ORPHAN\",\"types\":[],\"publishers\":0,\"subscribers\":1}") != std::string::npos);
}

TEST_CASE("DOT flags a topic with two types and says why a subscriber is not matched", "[graph]") {
  auto a = graph_participant(1, 0x1, "a", 10);
  add(a, 1, Endpoint::KIND_PUBLISHER, "n", "T", "image_t");
  auto b = graph_participant(2, 0x1, "b", 20);
  auto& s = add(b, 1, Endpoint::KIND_SUBSCRIBER, "n", "T", "pose_t");
  s.errors.push_back("type mismatch on channel 'T'");
  const auto dot = lcmx::cli::graph::to_dot({a, b});
  INFO(dot);
  CHECK(dot.find("label=\"T\\nimage_t\\npose_t\\nCONFLICT: different types\"") != std::string::npos);
  CHECK(dot.find("[style=dotted, label=\"not matched: type mismatch on channel 'T'\"]") != std::string::npos);
}
