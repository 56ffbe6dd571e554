#include <catch2/catch.hpp>

#include "lcmx/udpm/udpm.hpp"

using namespace lcmx::udpm;

namespace {
Error::Code code_of(std::string_view url) {
  try {
    parse_url(url);
  } catch (const Error& e) {
    return e.code();
  }
  FAIL("no exception for " << url);
  return Error::Code::system;
}
std::string message_of(std::string_view url) {
  try {
    parse_url(url);
  } catch (const Error& e) {
    return e.what();
  }
  return {};
}
}  // namespace

TEST_CASE("parse_url reads LCM URLs and lcmx's options", "[unit][url]") {
  SECTION("full URL") {
    const auto c = parse_url("udpm://239.255.76.68:7668?ttl=1&iface=eth0&recv_buf_size=2097152&multicast_loop=false");
    CHECK(c.address == "239.255.76.68");
    CHECK(c.port == 7668);
    CHECK(c.ttl == 1);
    CHECK(c.interface == "eth0");
    CHECK(c.recv_buffer_bytes == 2097152);
    CHECK_FALSE(c.multicast_loop);
  }
  SECTION("LCM's default URL") {
    const auto c = parse_url("udpm://239.255.76.67:7667?ttl=0");
    const GroupConfig d;
    CHECK(c.address == d.address);
    CHECK(c.port == d.port);
    CHECK(c.ttl == 0);
    CHECK(c.interface.empty());  // host-local mode: lo and where the kernel routes the group
    CHECK(c.recv_buffer_bytes == d.recv_buffer_bytes);
    CHECK(c.multicast_loop);
  }
  SECTION("missing parts take the defaults") {
    CHECK(parse_url("udpm://").address == "239.255.76.67");
    CHECK(parse_url("udpm://").port == 7667);
    CHECK(parse_url("udpm://239.1.2.3").port == 7667);
    CHECK(parse_url("udpm://239.1.2.3").address == "239.1.2.3");
    CHECK(parse_url("udpm://:9000").address == "239.255.76.67");
    CHECK(parse_url("udpm://:9000").port == 9000);
    CHECK(parse_url("udpm://?ttl=3&").ttl == 3);
    CHECK(parse_url("udpm://239.1.2.3:1?multicast_loop=1").multicast_loop);
  }
  SECTION("to_url round-trips") {
    GroupConfig c;
    c.address = "239.9.8.7";
    c.port = 40001;
    c.ttl = 4;
    c.interface = "veth0";
    c.recv_buffer_bytes = 123456;
    c.multicast_loop = false;
    const auto back = parse_url(to_url(c));
    CHECK(back.address == c.address);
    CHECK(back.port == c.port);
    CHECK(back.ttl == c.ttl);
    CHECK(back.interface == c.interface);
    CHECK(back.recv_buffer_bytes == c.recv_buffer_bytes);
    CHECK(back.multicast_loop == c.multicast_loop);
    CHECK(to_url(GroupConfig{}) == "udpm://239.255.76.67:7667?ttl=0&recv_buf_size=4194304");
    CHECK(parse_url(to_url(GroupConfig{})).interface.empty());
  }
}

TEST_CASE("parse_url rejects bad URLs, naming the bad part", "[unit][url]") {
  for (const char* url : {
           "udp://239.1.2.3:7667", "239.1.2.3:7667", "", "udpm:/239.1.2.3",        // scheme
           "udpm://239.1.2.3:0", "udpm://239.1.2.3:65536", "udpm://239.1.2.3:x",  // port
           "udpm://239.1.2.3:", "udpm://239.1.2.3:-1", "udpm://239.1.2.3:80a",
           "udpm://10.0.0.1:7667", "udpm://127.0.0.1:7667", "udpm://239.1.2:7667",  // address
           "udpm://239.1.2.3.4:7667", "udpm://host:7667", "udpm://240.0.0.1:7667",
           "udpm://?ttl=256", "udpm://?ttl=-1", "udpm://?ttl=", "udpm://?ttl=1x",     // options
           "udpm://?iface=", "udpm://?iface=abcdefghijklmnopq", "udpm://?recv_buf_size=-5",
           "udpm://?recv_buf_size=99999999999", "udpm://?multicast_loop=yes", "udpm://?bogus=1",
           "udpm://?ttl", "udpm://?ttl=1&ttl=2",
       }) {
    INFO(url);
    CHECK(code_of(url) == Error::Code::invalid_config);
  }
  CHECK_THAT(message_of("udpm://239.1.2.3:70000"), Catch::Contains("70000"));
  CHECK_THAT(message_of("udpm://10.1.2.3:7667"), Catch::Contains("10.1.2.3") && Catch::Contains("multicast"));
  CHECK_THAT(message_of("udpm://?ttl=300"), Catch::Contains("ttl=300"));
  CHECK_THAT(message_of("udpm://?colour=red"), Catch::Contains("colour"));
  CHECK_THAT(message_of("udpm://?ttl=1&ttl=1"), Catch::Contains("twice"));
}
