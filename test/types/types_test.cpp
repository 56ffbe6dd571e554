// lcmx::types: parser, fingerprints against lcm-gen's getHash(), registry, parse errors.
#include <catch2/catch.hpp>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <unistd.h>

#include "corpus_a/arrays_t.hpp"
#include "corpus_a/empty_t.hpp"
#include "corpus_a/path_t.hpp"
#include "corpus_a/point_t.hpp"
#include "corpus_a/primitives_t.hpp"
#include "corpus_b/level1_t.hpp"
#include "corpus_b/level2_t.hpp"
#include "corpus_b/level3_t.hpp"
#include "corpus_b/scene_t.hpp"
#include "corpus_b/stamp_t.hpp"
#include "corpus_b/tree_t.hpp"
#include "lcmx/types/types.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "lcmx_examples/header_t.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pointcloud_t.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "lcmx_msgs/beacon_t.hpp"
#include "lcmx_msgs/bridge_status_t.hpp"
#include "plain_t.hpp"

namespace fs = std::filesystem;
using namespace lcmx::types;

namespace {

const TypeRegistry& lcm_corpus() {
  static const TypeRegistry r = TypeRegistry::load({LCMX_TYPES_CORPUS});
  return r;
}

template <class T>
void check_hash(const TypeRegistry& r, const std::string& name) {
  INFO(name);
  const StructType* t = r.find(name);
  REQUIRE(t != nullptr);
  CHECK(t->fingerprint == static_cast<std::uint64_t>(T::getHash()));
  CHECK(r.find(t->fingerprint) != nullptr);
}

// A scratch directory removed at the end of the test.
struct TempDir {
  fs::path path;
  explicit TempDir(const std::string& name)
      : path(fs::temp_directory_path() / ("lcmx_types_" + name + "_" + std::to_string(::getpid()))) {
    fs::remove_all(path);
    fs::create_directories(path);
  }
  ~TempDir() { fs::remove_all(path); }
  fs::path write(const std::string& rel, const std::string& text) const {
    const fs::path p = path / rel;
    fs::create_directories(p.parent_path());
    std::ofstream(p) << text;
    return p;
  }
};

// The ParseError thrown by parsing `text` (fails the test when none is).
ParseError parse_error_of(const std::string& text) {
  try {
    parse(text, "bad.lcm");
  } catch (const ParseError& e) {
    return e;
  }
  FAIL("no ParseError for:\n" << text);
  throw std::logic_error("unreachable");
}

}  // namespace

TEST_CASE("every corpus type's fingerprint equals lcm-gen's getHash()", "[unit]") {
  const TypeRegistry& r = lcm_corpus();
  CHECK(r.size() == 12);
  check_hash<corpus_a::primitives_t>(r, "corpus_a.primitives_t");
  check_hash<corpus_a::empty_t>(r, "corpus_a.empty_t");
  check_hash<corpus_a::arrays_t>(r, "corpus_a.arrays_t");
  check_hash<corpus_a::point_t>(r, "corpus_a.point_t");
  check_hash<corpus_a::path_t>(r, "corpus_a.path_t");
  check_hash<corpus_b::stamp_t>(r, "corpus_b.stamp_t");
  check_hash<corpus_b::scene_t>(r, "corpus_b.scene_t");
  check_hash<corpus_b::level1_t>(r, "corpus_b.level1_t");
  check_hash<corpus_b::level2_t>(r, "corpus_b.level2_t");
  check_hash<corpus_b::level3_t>(r, "corpus_b.level3_t");
  check_hash<corpus_b::tree_t>(r, "corpus_b.tree_t");
  check_hash<plain_t>(r, "plain_t");
}

TEST_CASE("lcmx's own lcmtypes fingerprints equal their generated getHash()", "[unit]") {
  const TypeRegistry r = TypeRegistry::load({LCMX_LCMTYPES_DIR});
  check_hash<lcmx_msgs::match_t>(r, "lcmx_msgs.match_t");
  check_hash<lcmx_msgs::endpoint_t>(r, "lcmx_msgs.endpoint_t");
  check_hash<lcmx_msgs::beacon_t>(r, "lcmx_msgs.beacon_t");
  check_hash<lcmx_msgs::bridge_link_status_t>(r, "lcmx_msgs.bridge_link_status_t");
  check_hash<lcmx_msgs::bridge_channel_status_t>(r, "lcmx_msgs.bridge_channel_status_t");
  check_hash<lcmx_msgs::bridge_peer_status_t>(r, "lcmx_msgs.bridge_peer_status_t");
  check_hash<lcmx_msgs::bridge_status_t>(r, "lcmx_msgs.bridge_status_t");
  check_hash<lcmx_examples::header_t>(r, "lcmx_examples.header_t");
  check_hash<lcmx_examples::image_t>(r, "lcmx_examples.image_t");
  check_hash<lcmx_examples::pointcloud_t>(r, "lcmx_examples.pointcloud_t");
  check_hash<lcmx_examples::pose_t>(r, "lcmx_examples.pose_t");
  check_hash<lcmx_examples::bench_t>(r, "lcmx_examples.bench_t");
}

TEST_CASE("the parser keeps members and dimensions and constants as declared", "[unit]") {
  const TypeRegistry& r = lcm_corpus();
  const StructType& p = r.at("corpus_a.primitives_t");
  CHECK(p.file.find("primitives.lcm") != std::string::npos);
  REQUIRE(p.members.size() == 12);
  CHECK(p.members[2].name == "i32");
  CHECK(p.members[8].primitive == Primitive::byte);
  CHECK(p.members[11].name == "c");
  REQUIRE(p.constants.size() == 8);
  CHECK(p.constants[0].name == "I8_MIN");
  CHECK(p.constants[0].integer == -128);
  CHECK(p.constants[1].integer == 0x7f);
  CHECK(p.constants[1].text == "0x7f");
  CHECK(p.constants[2].integer == 0x7fff);
  CHECK(p.constants[3].integer == -16);
  CHECK(p.constants[4].integer == 15);  // 017, octal as in C
  CHECK(p.constants[5].integer == 0x7fffffffffffffff);
  CHECK(p.constants[6].floating == 1500.0);
  CHECK(p.constants[7].type == Primitive::float64);
  CHECK(p.constants[7].floating == -2.25);

  const StructType& a = r.at("corpus_a.arrays_t");
  const Member* cube = a.find_member("cube");
  REQUIRE(cube != nullptr);
  REQUIRE(cube->dims.size() == 3);
  CHECK(cube->dims[0].variable);
  CHECK(a.members[cube->dims[0].size_member].name == "n32");
  CHECK(cube->dims[1].variable);
  CHECK(!cube->dims[2].variable);
  CHECK(cube->dims[2].fixed == 2);
  CHECK(a.find_member("hexsized")->dims[0].fixed == 4);

  const StructType& scene = r.at("corpus_b.scene_t");
  CHECK(scene.find_member("stamp")->nested == &r.at("corpus_b.stamp_t"));          // relative
  CHECK(scene.find_member("landmarks")->nested == &r.at("corpus_a.point_t"));      // qualified
  CHECK(r.at("corpus_b.tree_t").find_member("children")->nested == &r.at("corpus_b.tree_t"));
  CHECK(r.at("plain_t").package.empty());
}

TEST_CASE("a constant as array size is a fixed dimension hashed as the constant's text", "[unit]") {
  // Newer lcm-gen (not Debian's 1.3.1) accepts `a[N]` for a constant N: hashed like `a[4]`.
  const auto by_const = parse("struct s { const int32_t N = 4; int32_t a[N]; }", "c.lcm");
  const auto literal = parse("struct s { int32_t a[4]; }", "l.lcm");
  REQUIRE(by_const.size() == 1);
  CHECK(by_const[0].members[0].dims[0].fixed == 4);
  CHECK(by_const[0].base_hash == literal[0].base_hash);
  // ...and the hash depends on the size as written.
  CHECK(parse("struct s { int32_t a[0x4]; }", "h.lcm")[0].base_hash != literal[0].base_hash);
}

TEST_CASE("a struct name may carry its package as lcm-gen allows", "[unit]") {
  const auto types = parse("package p;\nstruct q.r.s_t { t_t x; }", "q.lcm");
  REQUIRE(types.size() == 1);
  CHECK(types[0].package == "q.r");
  CHECK(types[0].name == "s_t");
  CHECK(types[0].members[0].type_name == "p.t_t");  // members: the file's package
}

TEST_CASE("deep type graphs hash in linear time", "[unit]") {
  // 60 types, each with two members of the next: 2^60 paths, hashed once each type.
  std::string text = "package deep;\nstruct t60 { int32_t leaf; }\n";
  for (int i = 59; i >= 0; --i)
    text += "struct t" + std::to_string(i) + " { t" + std::to_string(i + 1) + " a; t" +
            std::to_string(i + 1) + " b; }\n";
  const auto start = std::chrono::steady_clock::now();
  const TypeRegistry r = TypeRegistry::load_texts({{"deep.lcm", text}});
  CHECK(std::chrono::steady_clock::now() - start < std::chrono::seconds(2));
  // Each level: rotl1(base + 2 * hash(next)).
  std::uint64_t expect = 0;
  for (int i = 60; i >= 0; --i) {
    const StructType& t = r.at("deep.t" + std::to_string(i));
    const std::uint64_t h = static_cast<std::uint64_t>(t.base_hash) + 2 * expect;
    expect = (h << 1) | (h >> 63);
    CHECK(t.fingerprint == expect);
  }
  CHECK(r.at("deep.t0").min_encoded_size == (std::size_t{1} << 48));  // 4 * 2^60, saturated
  CHECK_THROWS_WITH(zero_value(r.at("deep.t0")), Catch::Contains("more than 2^24 elements"));
  CHECK(zero_value(r.at("deep.t50")).as<Struct>().fields.size() == 2);
}

TEST_CASE("bad .lcm files are errors with file:line:col", "[unit]") {
  struct Case {
    const char* text;
    int line, column;
    const char* message;
  };
  const Case cases[] = {
      {"struct s {\n  int32_t x\n}\n", 3, 1, "expected ';', found '}'"},
      {"struct s {\n  int32_t a[n];\n}", 2, 13, "unknown array size 'n'"},
      {"struct s {\n  double n;\n  int32_t a[n];\n}", 3, 13, "must be an integer member"},
      {"struct s {\n  byte n;\n  int32_t a[n];\n}", 3, 13, "must be an integer member"},
      {"struct s {\n  int32_t n[2];\n  int32_t a[n];\n}", 3, 13, "must not be an array"},
      {"struct s {\n  int32_t a[0];\n}", 2, 13, "must be > 0"},
      {"struct s {\n  int32_t x;\n  double x;\n}", 3, 10, "duplicate member name 'x'"},
      {"struct s {\n  const int8_t X = 0x80;\n}", 2, 20, "out of range for int8_t"},
      {"struct s {\n  const int32_t X = 12abc;\n}", 2, 21, "expected an integer value"},
      {"struct s {\n  const string X = 1;\n}", 2, 9, "invalid type 'string' for a constant"},
      {"struct s {\n  int32_t 9x;\n}", 2, 11, "invalid member name '9x'"},
      {"package p;\n\nstruct s {\n  int32_t x;\n", 5, 1, "end of file inside struct 's'"},
      {"/* never\n closed", 1, 1, "comment '/*' is never closed"},
      {"message s { }", 1, 1, "expected 'package' or 'struct'"},
      {"enum e { A, B }", 1, 1, "'enum' is not supported"},
      {"struct s { int32_t x; }\nstruct s { int32_t y; }", 2, 1, "declared twice"},
      {"struct s {\n  int32_t x; @\n}", 2, 14, "unexpected character '@'"},
      {"struct s {\n  struct t { }\n}", 2, 3, "nested 'struct' declarations"},
  };
  for (const Case& c : cases) {
    INFO(c.text);
    const ParseError e = parse_error_of(c.text);
    CHECK(e.file() == "bad.lcm");
    CHECK(e.line() == c.line);
    CHECK(e.column() == c.column);
    CHECK_THAT(e.message(), Catch::Contains(c.message));
    CHECK_THAT(std::string(e.what()),
               Catch::StartsWith("bad.lcm:" + std::to_string(c.line) + ":" + std::to_string(c.column) + ": "));
  }
}

TEST_CASE("parse errors from files name the file", "[unit]") {
  TempDir dir("parse_file");
  const fs::path bad = dir.write("deep/bad.lcm", "package p;\nstruct s {\n  int32_t a[n];\n}\n");
  try {
    TypeRegistry::load({dir.path});
    FAIL("no error");
  } catch (const ParseError& e) {
    CHECK(e.file() == bad.string());
    CHECK(e.line() == 3);
    CHECK_THAT(std::string(e.what()), Catch::StartsWith(bad.string() + ":3:13: "));
  }
}

TEST_CASE("the registry loads files and directories and resolves across them", "[unit]") {
  TempDir dir("registry");
  dir.write("a/one.lcm", "package pa;\nstruct one_t { int32_t x; pb.two_t two; }\n");
  dir.write("b/c/two.lcm", "package pb;\nstruct two_t { string s; }\n");
  dir.write("b/c/ignored.txt", "not a type");
  dir.write("b/copy.lcm", "package pb;\nstruct two_t { string s; }\n");  // identical: kept once

  SECTION("a directory, searched recursively") {
    const TypeRegistry r = TypeRegistry::load({dir.path});
    CHECK(r.size() == 2);
    CHECK(r.at("pa.one_t").find_member("two")->nested == r.find("pb.two_t"));
  }
  SECTION("files listed one by one, the same one twice") {
    const TypeRegistry r = TypeRegistry::load(
        {dir.path / "b/c/two.lcm", dir.path / "a/one.lcm", dir.path / "b/c/two.lcm"});
    CHECK(r.size() == 2);
  }
  SECTION("LCMX_TYPES_PATH, colon-separated, and --types over it") {
    const std::string env = (dir.path / "a").string() + "::" + (dir.path / "b/c").string();
    ::setenv("LCMX_TYPES_PATH", env.c_str(), 1);
    const auto paths = TypeRegistry::paths_or_env({});
    ::unsetenv("LCMX_TYPES_PATH");
    REQUIRE(paths.size() == 2);
    CHECK(TypeRegistry::load(paths).size() == 2);
    const auto given = TypeRegistry::paths_or_env({(dir.path / "b").string()});
    REQUIRE(given.size() == 1);
    CHECK(TypeRegistry::load(given).size() == 1);
  }
  SECTION("a nested type missing from the path is an error naming it") {
    try {
      TypeRegistry::load({dir.path / "a"});
      FAIL("no error");
    } catch (const Error& e) {
      CHECK_THAT(std::string(e.what()), Catch::Contains("unknown type 'pb.two_t'"));
      CHECK_THAT(std::string(e.what()), Catch::Contains("pa.one_t.two"));
      CHECK_THAT(std::string(e.what()), Catch::Contains("one.lcm:2:"));
    }
  }
  SECTION("two different definitions of one name are an error naming both files") {
    dir.write("b/other.lcm", "package pb;\nstruct two_t { int32_t s; }\n");
    try {
      TypeRegistry::load({dir.path});
      FAIL("no error");
    } catch (const Error& e) {
      CHECK_THAT(std::string(e.what()), Catch::Contains("'pb.two_t' is defined differently"));
      CHECK_THAT(std::string(e.what()), Catch::Contains("other.lcm"));
    }
  }
  SECTION("a missing path is an error naming it") {
    CHECK_THROWS_WITH(TypeRegistry::load({dir.path / "nope"}), Catch::Contains("nope does not exist"));
  }
  SECTION("lookups") {
    const TypeRegistry r = TypeRegistry::load({dir.path});
    CHECK(r.find("two_t") == nullptr);  // names are package-qualified
    CHECK_THROWS_WITH(r.at("pb.three_t"), Catch::Contains("unknown type 'pb.three_t'"));
    CHECK(r.find(std::uint64_t{12345}) == nullptr);
    const StructType& two = r.at("pb.two_t");
    CHECK(r.find(two.fingerprint) == &two);
  }
}

TEST_CASE("the fingerprint is read big-endian from the first 8 bytes", "[unit]") {
  const std::uint8_t msg[] = {0x01, 0x23, 0x45, 0x67, 0x89, 0xab, 0xcd, 0xef, 0xff};
  CHECK(message_fingerprint(msg, sizeof msg) == 0x0123456789abcdefULL);
  CHECK(!message_fingerprint(msg, 7));
}
