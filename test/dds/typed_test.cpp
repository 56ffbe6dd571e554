// Typed mode: the IDL `lcmx idl` writes compiles with idlc; the run-time descriptor lays samples
// out as idlc's C does (same size, alignment and opcodes) and converts both ways.
#include <catch2/catch.hpp>
#include <sys/wait.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <fstream>

#include "dds_test.h"  // idlc's C for the IDL of dds_test.lcm (built by test/dds/CMakeLists.txt)
#include "lcmx/dds/idl.hpp"
#include "lcmx/dds/typed.hpp"
#include "lcmx_ddstest/sample_t.hpp"

namespace {

const lcmx::types::TypeRegistry& registry() {
  static const auto reg = lcmx::types::TypeRegistry::load({LCMX_DDS_TEST_LCM});
  return reg;
}

int run(const std::string& cmd) {
  const int rc = std::system(cmd.c_str());
  return WIFEXITED(rc) ? WEXITSTATUS(rc) : -1;
}

lcmx_ddstest::sample_t make() {
  lcmx_ddstest::sample_t s{};
  s.seq = 77;
  s.i8 = -7;
  s.i16 = -1234;
  s.i32 = 123456;
  s.f = 1.5f;
  s.d = -0.125;
  s.flag = 1;
  s.b = 255;
  s.name = "name";
  s.fixed3[2] = 9.5;
  s.grid[1][2] = 12;
  s.grid[0][1] = 1;
  s.origin.x = 2;
  s.origin.label = "o";
  s.corners[1].label = "c1";
  s.n = 2;
  s.values = {4.0, 5.0};
  s.blob = {1, 250};
  s.m = 1;
  s.points.resize(1);
  s.points[0].x = 3;
  s.points[0].label = "p";
  s.tags = {"tag"};
  return s;
}

}  // namespace

TEST_CASE("lcmx idl: the IDL of every construct compiles with idlc, plain and ROS 2 naming", "[dds][idl]") {
  const auto dir = std::filesystem::temp_directory_path() / ("lcmx_dds_idl_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const auto* t = registry().find("lcmx_ddstest.sample_t");
  REQUIRE(t != nullptr);
  for (bool ros2 : {false, true}) {
    const std::string idl = lcmx::dds::to_idl({t}, ros2);
    CHECK(idl.find("sequence<double> values;") != std::string::npos);
    CHECK(idl.find("long grid[2][3];") != std::string::npos);
    CHECK(idl.find("int8 i8;") != std::string::npos);
    const auto file = dir / (ros2 ? "ros.idl" : "plain.idl");
    std::ofstream(file) << idl;
    INFO(idl);
    CHECK(run(std::string(LCMX_IDLC) + " -o " + dir.string() + " " + file.string() + " > /dev/null 2>&1") == 0);
  }
  CHECK(lcmx::dds::dds_type_name(*t, false) == "lcmx_ddstest::sample_t");
  CHECK(lcmx::dds::dds_type_name(*t, true) == "lcmx_ddstest::msg::dds_::sample_t_");
  // Member names that are IDL keywords are escaped.
  const auto kw = lcmx::types::TypeRegistry::load_texts(
      {{"kw.lcm", "package kw;\nstruct t { int32_t module; double fixed[2]; }\n"}});
  const std::string idl = lcmx::dds::to_idl({&kw.at("kw.t")}, false);
  CHECK(idl.find("long _module;") != std::string::npos);
  CHECK(idl.find("double _fixed[2];") != std::string::npos);
  std::ofstream(dir / "kw.idl") << idl;
  CHECK(run(std::string(LCMX_IDLC) + " -o " + dir.string() + " " + (dir / "kw.idl").string() + " > /dev/null 2>&1") == 0);
  std::filesystem::remove_all(dir);
}

TEST_CASE("typed mode: the run-time descriptor matches idlc's (size, alignment, opcodes)", "[dds][typed]") {
  const auto tt = lcmx::dds::TypedType::create(registry().at("lcmx_ddstest.sample_t"), false);
  const dds_topic_descriptor_t& mine = *tt->descriptor();
  const dds_topic_descriptor_t& idlc = lcmx_ddstest_sample_t_desc;
  CHECK(mine.m_size == idlc.m_size);
  CHECK(mine.m_align == idlc.m_align);
  CHECK(std::string(mine.m_typename) == idlc.m_typename);
  CHECK(mine.m_nops == idlc.m_nops);
  // Same opcodes word for word (idlc's array is at least as long: nothing follows it).
  const auto ops = tt->ops();
  const std::vector<std::uint32_t> a(ops.begin(), ops.end()), b(idlc.m_ops, idlc.m_ops + ops.size());
  CHECK(a == b);
}

TEST_CASE("typed mode: LCM encoding to an idlc-layout sample and back", "[dds][typed]") {
  const auto tt = lcmx::dds::TypedType::create(registry().at("lcmx_ddstest.sample_t"), false);
  const auto msg = make();
  std::vector<std::uint8_t> lcm(static_cast<std::size_t>(msg.getEncodedSize()));
  msg.encode(lcm.data(), 0, static_cast<int>(lcm.size()));
  const auto sample = tt->from_lcm(std::as_bytes(std::span(lcm)));
  const auto* c = static_cast<const lcmx_ddstest_sample_t*>(sample.data());
  CHECK(c->seq == 77);
  CHECK(c->i8 == -7);
  CHECK(c->i16 == -1234);
  CHECK(c->i32 == 123456);
  CHECK(c->f == 1.5f);
  CHECK(c->d == -0.125);
  CHECK(c->flag);
  CHECK(c->b == 255);
  CHECK(std::string(c->name) == "name");
  CHECK(c->fixed3[2] == 9.5);
  CHECK(c->grid[1][2] == 12);
  CHECK(c->grid[0][1] == 1);
  CHECK(c->origin.x == 2);
  CHECK(std::string(c->origin.label) == "o");
  CHECK(std::string(c->corners[1].label) == "c1");
  CHECK(c->n == 2);
  REQUIRE(c->values._length == 2);
  CHECK(c->values._buffer[1] == 5.0);
  REQUIRE(c->blob._length == 2);
  CHECK(c->blob._buffer[1] == 250);
  REQUIRE(c->points._length == 1);
  CHECK(std::string(c->points._buffer[0].label) == "p");
  REQUIRE(c->tags._length == 1);
  CHECK(std::string(c->tags._buffer[0]) == "tag");

  // Back: the same bytes lcm-gen wrote.
  CHECK(tt->to_lcm(sample.data()) == lcm);

  // A sample whose size member disagrees with its sequences: the size member follows them.
  lcmx_ddstest_sample_t s = *c;
  s.n = 40;
  const auto fixed = tt->to_lcm(&s);
  lcmx_ddstest::sample_t back;
  REQUIRE(back.decode(fixed.data(), 0, static_cast<int>(fixed.size())) > 0);
  CHECK(back.n == 2);
  // Two sequences sharing one size member with different lengths: an error, not a crash.
  s.blob._length = 1;
  CHECK_THROWS_WITH(tt->to_lcm(&s), Catch::Contains("share the size member n"));
  // Bytes of another type: an error naming the fingerprint.
  lcm[0] ^= 0xff;
  CHECK_THROWS_AS(tt->from_lcm(std::as_bytes(std::span(lcm))), lcmx::types::Error);
}
