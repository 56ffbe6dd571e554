// The DDS gateway across emulated hosts (network namespaces joined by a bridge, link "eth"):
// the gateway and the lcmx programs on host 0, a plain Cyclone DDS program on host 1. Cyclone
// runs on the namespaces' "eth" with unicast discovery to the other host's address: every packet
// stays inside the test's namespaces.
#include "dds_support.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;
using namespace lcmx::ddstest;

TEST_CASE("dds gateway typed across emulated hosts - lcmx to a DDS reader and a DDS writer to lcmx",
          "[dds][multihost]") {
  Hosts h(2, 1, 60000ms);
  const int domain = unique_domain(1);
  auto& emu = h.emu();
  const std::string a0 = emu.address(0, "eth"), a1 = emu.address(1, "eth");
  TempDir dir("mh");
  const std::string ch_out = lcmx::it::unique_channel("DDS_MH_OUT", 1), ch_in = lcmx::it::unique_channel("DDS_MH_IN", 1);
  const auto cfg = dir.write(
      "gw.toml", gateway_head("gwmh", domain, emu.interface(0, "eth"), a1) +
                     mapping(ch_out, "to_dds", "typed", "lcmx_ddstest.sample_t", "topic = \"MH_OUT\"\n") +
                     mapping(ch_in, "from_dds", "typed", "lcmx_ddstest.sample_t", "topic = \"MH_IN\"\n"));
  auto& gw = h.spawn(0, {LCMX_TOOL, "dds-gateway", "--config", cfg}, h.lcmx_env(), true);
  REQUIRE(gw.expect("dds-gateway gwmh: ready", 15000ms));
  const auto env1 = peer_env(domain, emu.interface(1, "eth"), {a0});

  // lcmx (host 0) -> gateway -> DDS reader (host 1).
  auto& rd = h.spawn(1, {LCMX_DDS_PEER, "read-typed", "MH_OUT", "2"}, env1);
  REQUIRE(rd.expect("ready", 10000ms));
  auto& pub = h.spawn(0, {LCMX_DDS_LCMX_PEER, "pub", ch_out, "2"}, h.lcmx_env());
  REQUIRE(pub.expect("published 2", 20000ms));
  const auto got = rd.expect("sample seq=0 ", 20000ms);
  REQUIRE(got);
  CHECK_THAT(*got, Catch::Contains("name=from-lcmx") && Catch::Contains("values=3:1,2,3") &&
                       Catch::Contains("points=2:5/a,6/b tags=2:t1,t2"));
  CHECK(rd.expect("sample seq=1 ", 10000ms));
  CHECK(rd.wait(10000ms) == 0);

  // DDS writer (host 1) -> gateway -> typed lcmx subscriber (host 0).
  auto& sub = h.spawn(0, {LCMX_DDS_LCMX_PEER, "sub", ch_in, "2"}, h.lcmx_env());
  REQUIRE(sub.expect("ready", 10000ms));
  auto& wr = h.spawn(1, {LCMX_DDS_PEER, "write-typed", "MH_IN", "2"}, env1);
  REQUIRE(wr.expect("written 2", 20000ms));
  const auto in = sub.expect("sample seq=1000 ", 20000ms);
  REQUIRE(in);
  CHECK_THAT(*in, Catch::Contains("name=from-dds") && Catch::Contains("n=3 values=0.5,1.5,2.5") &&
                      Catch::Contains("tags=alpha,beta"));
  CHECK(sub.expect("sample seq=1001 ", 10000ms));
  CHECK(sub.wait(10000ms) == 0);
}
