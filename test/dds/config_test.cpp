// The DDS gateway's config: defaults, and every bad config refused with a message naming the key.
#include <catch2/catch.hpp>
#include <sched.h>

#include <fstream>
#include <string>
#include <thread>

#include "lcmx/dds/config.hpp"

using lcmx::dds::ConfigError;
using lcmx::dds::parse_config;

namespace {

// The error of parsing `text` (FAIL if it parses).
std::string error_of(const std::string& text) {
  try {
    parse_config(text, "gw.toml");
  } catch (const ConfigError& e) {
    return e.what();
  }
  FAIL("parsed: " << text);
  return {};
}

const std::string kTypes = "types = [\"" LCMX_DDS_TEST_LCM "\"]\n";

}  // namespace

TEST_CASE("dds config: defaults, ROS 2 naming and Cyclone's network config", "[dds][config]") {
  const auto cfg = parse_config("name = \"gw\"\n" + kTypes +
                                    "[[map]]\nchannel = \"POSE\"\ndirection = \"to_dds\"\n"
                                    "[[map]]\nchannel = \"CMD\"\ndirection = \"both\"\nmode = \"typed\"\n"
                                    "type = \"lcmx_ddstest.sample_t\"\nros2 = true\nreliability = \"best_effort\"\n"
                                    "history = 3\ndurability = \"transient_local\"\npartition = \"p1\"\n",
                                "gw.toml");
  REQUIRE(cfg.mappings.size() == 2);
  CHECK(cfg.domain == 0);
  CHECK(cfg.cyclone_xml().empty());  // no interface: Cyclone's default / CYCLONEDDS_URI
  const auto& a = cfg.mappings[0];
  CHECK(a.topic == "POSE");
  CHECK(a.mode == lcmx::dds::Mode::opaque);
  CHECK(a.reliability == lcmx::dds::Reliability::reliable);
  CHECK(a.history == 16);
  CHECK(a.durability == lcmx::dds::Durability::volatile_);
  CHECK(a.exports());
  CHECK_FALSE(a.imports());
  const auto& b = cfg.mappings[1];
  CHECK(b.topic == "rt/CMD");
  REQUIRE(b.lcm_type != nullptr);
  CHECK(b.lcm_type->full_name() == "lcmx_ddstest.sample_t");
  CHECK(b.history == 3);
  CHECK(b.partition == "p1");
  CHECK(b.exports());
  CHECK(b.imports());
  CHECK(cfg.spin == std::chrono::microseconds(0));
  CHECK_FALSE(cfg.slice.has_value());  // not set: default_slice() when the gateway starts

  const auto net = parse_config("name = \"gw\"\ndomain = 7\ninterface = \"127.0.0.1\"\nallow_multicast = false\n"
                                "peers = [\"127.0.0.1\"]\n[[map]]\nchannel = \"X\"\ndirection = \"from_dds\"\n",
                                "gw.toml");
  const auto xml = net.cyclone_xml();
  CHECK(xml.find("<NetworkInterface address=\"127.0.0.1\"/>") != std::string::npos);
  CHECK(xml.find("<AllowMulticast>false</AllowMulticast>") != std::string::npos);
  CHECK(xml.find("<Peer address=\"127.0.0.1\"/>") != std::string::npos);
  // Large imports: a receive buffer above Cyclone's 1 MiB by default; 0 leaves Cyclone's.
  CHECK(net.receive_buffer_kb == 4096);
  CHECK(xml.find("<Internal><SocketReceiveBufferSize max=\"4096KiB\"/></Internal>") != std::string::npos);
  const auto own = parse_config("name = \"gw\"\ninterface = \"127.0.0.1\"\nreceive_buffer_kb = 0\n[[map]]\nchannel = \"X\"\n"
                                "direction = \"both\"\n", "gw.toml");
  CHECK(own.cyclone_xml().find("SocketReceiveBufferSize") == std::string::npos);
  const auto byname = parse_config("name = \"gw\"\ninterface = \"veth0\"\n[[map]]\nchannel = \"X\"\ndirection = \"both\"\n",
                                   "gw.toml");
  CHECK(byname.cyclone_xml().find("<NetworkInterface name=\"veth0\"/>") != std::string::npos);
}

// default_slice() reads the calling thread's CPU affinity: run it on a thread of its own with
// the mask given (empty: the process's own).
std::chrono::microseconds default_slice_on(const cpu_set_t* mask) {
  std::chrono::microseconds got{-1};
  std::thread t([&] {
    if (mask != nullptr && ::sched_setaffinity(0, sizeof *mask, mask) != 0) return;
    got = lcmx::dds::default_slice();
  });
  t.join();
  return got;
}

TEST_CASE("dds config: without slice_us the gateway asks for 100 us on two CPUs or more, the kernel's slice on one",
          "[dds][config]") {
  cpu_set_t all;
  CPU_ZERO(&all);
  REQUIRE(::sched_getaffinity(0, sizeof all, &all) == 0);
  int first = -1;
  for (int c = 0; c < CPU_SETSIZE && first < 0; ++c)
    if (CPU_ISSET(c, &all)) first = c;
  REQUIRE(first >= 0);
  cpu_set_t one;
  CPU_ZERO(&one);
  CPU_SET(first, &one);
  CHECK(default_slice_on(&one) == std::chrono::microseconds(0));
  if (CPU_COUNT(&all) >= 2)
    CHECK(default_slice_on(&all) == std::chrono::microseconds(100));
  else
    WARN("this process may run on one CPU only: the two-CPU case is not checked here");
}

TEST_CASE("dds config: bad configs are refused naming the key", "[dds][config]") {
  const std::string head = "name = \"gw\"\n";
  const std::string map = "[[map]]\nchannel = \"X\"\ndirection = \"to_dds\"\n";
  CHECK_THAT(error_of(map), Catch::Contains("name: missing (required)"));
  CHECK_THAT(error_of("name = \"a b\"\n" + map), Catch::Contains("name: must be 1 to 32 characters"));
  CHECK_THAT(error_of(head), Catch::Contains("map: must list at least one mapping"));
  CHECK_THAT(error_of(head + "domain = 231\n" + map), Catch::Contains("domain: must be an integer from 0 to 230"));
  CHECK_THAT(error_of(head + "domian = 1\n" + map), Catch::Contains("domian: unknown key"));
  CHECK_THAT(error_of(head + "interface = \"not an iface\"\n" + map), Catch::Contains("interface: must be"));
  CHECK_THAT(error_of(head + "peers = [\"127.0.0.1\"]\n" + map), Catch::Contains("peers: needs interface"));
  CHECK_THAT(error_of(head + "receive_buffer_kb = 8192\n" + map), Catch::Contains("receive_buffer_kb: needs interface"));
  CHECK_THAT(error_of(head + "interface = \"lo\"\nreceive_buffer_kb = -1\n" + map),
             Catch::Contains("receive_buffer_kb: must be an integer from 0 to 1048576"));
  CHECK_THAT(error_of(head + "interface = \"lo\"\npeers = [\"x\"]\n" + map), Catch::Contains("peers[0]: not an IPv4"));
  CHECK_THAT(error_of(head + "interface = \"lo\"\nallow_multicast = false\n" + map),
             Catch::Contains("needs at least one peer"));
  CHECK_THAT(error_of(head + "slice_us = 50\n" + map), Catch::Contains("slice_us: must be 0 (the kernel's default) or 100"));
  CHECK_THAT(error_of(head + "slice_us = 100001\n" + map), Catch::Contains("slice_us: must be an integer from 0 to 100000"));
  CHECK(parse_config(head + "slice_us = 0\n" + map, "gw.toml").slice == std::chrono::microseconds(0));
  CHECK(parse_config(head + "slice_us = 100\n" + map, "gw.toml").slice == std::chrono::microseconds(100));
  CHECK_THAT(error_of(head + "[[map]]\ndirection = \"to_dds\"\n"), Catch::Contains("map[0].channel: missing"));
  CHECK_THAT(error_of(head + "[[map]]\nchannel = \"X\"\ndirection = \"up\"\n"),
             Catch::Contains("map[0].direction: must be \"to_dds\", \"from_dds\" or \"both\""));
  CHECK_THAT(error_of(head + map + "mode = \"json\"\n"), Catch::Contains("map[0].mode: must be"));
  CHECK_THAT(error_of(head + map + "mode = \"typed\"\n"), Catch::Contains("map[0].type: missing (required)"));
  CHECK_THAT(error_of(head + kTypes + map + "mode = \"typed\"\ntype = \"nope.t\"\n"),
             Catch::Contains("map[0].type: unknown type \"nope.t\" (types loaded: lcmx_ddstest.point_t"));
  CHECK_THAT(error_of(head + map + "mode = \"typed\"\ntype = \"a.b\"\n"), Catch::Contains("no types loaded"));
  CHECK_THAT(error_of(head + map + "history = 0\n"), Catch::Contains("map[0].history: must be an integer from 1"));
  CHECK_THAT(error_of(head + map + "reliability = \"maybe\"\n"), Catch::Contains("map[0].reliability: must be"));
  CHECK_THAT(error_of(head + map + "durability = \"persistent\"\n"), Catch::Contains("map[0].durability: must be"));
  CHECK_THAT(error_of(head + map + "topic = \"has space\"\n"), Catch::Contains("map[0].topic: must be"));
  CHECK_THAT(error_of(head + map + map), Catch::Contains("map[1].topic: topic \"X\" is already mapped"));
  CHECK_THAT(error_of(head + map + map + "topic = \"Y\"\n"),
             Catch::Contains("map[1].channel: channel \"X\" is already exported"));
  CHECK_THAT(error_of(head + "[[map]]\nchannel = \"" + std::string(64, 'c') + "\"\ndirection = \"both\"\n"),
             Catch::Contains("map[0].channel: must be 1 to 63"));
  CHECK_THAT(error_of(head + "types = [\"/nonexistent/x.lcm\"]\n" + map), Catch::Contains("types: "));
  // The bridge's checks, shared: TOML syntax with its line, and the non-ASCII pre-scan.
  CHECK_THAT(error_of(head + "domain = = 3\n" + map), Catch::Contains("gw.toml: line 2:"));
  CHECK_THAT(error_of(head + "partition = \"\xc3\xa9\"\n" + map), Catch::Contains("line 2: a non-ASCII character"));
  CHECK_THAT(error_of(head + "map = 3\n"), Catch::Contains("map: must be an array of tables"));
}

TEST_CASE("dds config: a typed mapping of a type typed mode cannot map is refused", "[dds][config]") {
  const auto dir = std::filesystem::temp_directory_path() / ("lcmx_dds_cfg_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  {
    std::ofstream f(dir / "bad.lcm");
    f << "package bad;\nstruct t { int32_t n; double m[n][3]; }\n";
  }
  {
    std::ofstream f(dir / "gw.toml");
    f << "name = \"gw\"\ntypes = [\"bad.lcm\"]\n[[map]]\nchannel = \"X\"\ndirection = \"both\"\nmode = \"typed\"\n"
         "type = \"bad.t\"\n";
  }
  std::string err;
  try {
    lcmx::dds::load_config(dir / "gw.toml");
  } catch (const ConfigError& e) {
    err = e.what();
  }
  std::filesystem::remove_all(dir);
  CHECK_THAT(err, Catch::Contains("map[0].type: typed mode: bad.t.m: a variable-size dimension with other"));
  CHECK_THAT(err, Catch::Contains("use mode = \"opaque\""));
  CHECK_THAT([] {
    try {
      lcmx::dds::load_config("/nonexistent/gw.toml");
    } catch (const ConfigError& e) {
      return std::string(e.what());
    }
    return std::string();
  }(), Catch::Contains("cannot read: no such file"));
}
