// lcmx::types codec: round trips against lcm-gen's encoders/decoders, hostile messages,
// encode errors, renderings.
#include <catch2/catch.hpp>

#include <chrono>
#include <random>

#include "corpus_a/arrays_t.hpp"
#include "corpus_a/path_t.hpp"
#include "corpus_a/primitives_t.hpp"
#include "corpus_b/scene_t.hpp"
#include "corpus_b/tree_t.hpp"
#include "lcmx/types/types.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pointcloud_t.hpp"
#include "lcmx_msgs/beacon_t.hpp"
#include "plain_t.hpp"
#include "samples.hpp"

using namespace lcmx::types;
using Catch::Contains;

using namespace samples;

TEST_CASE("lcm-gen-encoded messages decode and re-encode to the same bytes", "[unit]") {
  const TypeRegistry& r = corpus();
  round_trip(r, make_primitives());
  round_trip(r, make_arrays());
  round_trip(r, make_path(3));

  const Value scene = round_trip(r, make_scene());
  const Struct& s = scene.as<Struct>();
  CHECK(s.type == r.find("corpus_b.scene_t"));
  CHECK(s.find("stamp")->as<Struct>().find("frame")->as<std::string>() == "map");
  const Struct& prims = s.find("prims")->as<Struct>();
  CHECK(prims.find("i8")->as<std::int64_t>() == -128);
  CHECK(prims.find("octet")->as<std::int64_t>() == 0xfe);
  CHECK(prims.find("flag")->as<bool>());
  CHECK(prims.find("f32")->as<float>() == -3.25e-7f);
  CHECK(prims.find("i64")->as<std::int64_t>() == static_cast<std::int64_t>(0x8000000000000001ULL));
  const Struct& arrays = s.find("arrays")->as<Struct>();
  CHECK(arrays.find("blob")->as<Bytes>() == Bytes{0, 1, 0x7f, 0x80, 0xff});
  CHECK(arrays.find("image")->as<Array>().size() == 3);
  CHECK(arrays.find("image")->as<Array>()[2].as<Bytes>() == Bytes{204, 205});
  CHECK(arrays.find("cube")->as<Array>()[3].as<Array>()[2].as<Array>()[1].as<std::int64_t>() == 321);
  CHECK(arrays.find("mixed2")->as<Array>().size() == 4);

  corpus_b::tree_t tree;
  tree.value = 1;
  tree.num_children = 2;
  tree.children.resize(2);
  tree.children[1].num_children = 1;
  tree.children[1].children.resize(1);
  tree.children[1].children[0].value = 99;
  tree.children[1].children[0].stamp.frame = "leaf";
  round_trip(r, tree);

  plain_t plain;
  plain.count = 2;
  plain.stamps.resize(2);
  plain.stamps[1].frame = "second";
  plain.label = "plain";
  round_trip(r, plain);
}

TEST_CASE("random trees encode as lcm-gen does - every corpus type", "[unit]") {
  const TypeRegistry& r = corpus();
  random_round_trips<corpus_a::primitives_t>(r, "corpus_a.primitives_t");
  random_round_trips<corpus_a::arrays_t>(r, "corpus_a.arrays_t");
  random_round_trips<corpus_a::path_t>(r, "corpus_a.path_t");
  random_round_trips<corpus_b::scene_t>(r, "corpus_b.scene_t");
  random_round_trips<corpus_b::tree_t>(r, "corpus_b.tree_t");
  random_round_trips<plain_t>(r, "plain_t");
}

TEST_CASE("lcmx's own messages decode: a beacon and a large image", "[unit]") {
  const TypeRegistry r = TypeRegistry::load({LCMX_LCMTYPES_DIR});
  lcmx_msgs::beacon_t b{};
  b.version = 3;
  b.process_name = "proc";
  b.num_nodes = 1;
  b.nodes = {"node"};
  b.num_endpoints = 1;
  b.endpoints.resize(1);
  b.endpoints[0].topic = "POSE";
  b.endpoints[0].num_matches = 1;
  b.endpoints[0].matches.resize(1);
  b.endpoints[0].matches[0].path = "shm";
  b.num_carried = 0;
  const Value v = round_trip(r, b);
  CHECK(v.as<Struct>().find("endpoints")->as<Array>()[0].as<Struct>().find("topic")->as<std::string>() == "POSE");

  lcmx_examples::image_t img{};
  img.width = 1920;
  img.height = 1080;
  img.size = 1920 * 1080 * 3;
  img.data.resize(static_cast<std::size_t>(img.size));
  for (std::size_t i = 0; i < img.data.size(); ++i) img.data[i] = static_cast<uint8_t>(i * 7);
  round_trip(r, img);

  lcmx_examples::pointcloud_t pc{};
  pc.num_fields = 2;
  pc.fields = {"x", "y"};
  pc.point_step = 8;
  pc.num_points = 3;
  pc.size = 24;
  pc.data.assign(24, 0xab);
  round_trip(r, pc);
}

TEST_CASE("truncated - mismatched - hostile messages are errors", "[unit]") {
  const TypeRegistry& r = corpus();
  const std::vector<std::uint8_t> good = lcm_encode(make_scene());
  const StructType& scene = r.at("corpus_b.scene_t");

  SECTION("every truncation") {
    for (std::size_t n = 0; n < good.size(); ++n) {
      INFO(n);
      CHECK_THROWS_AS(decode(scene, good.data(), n), Error);
    }
    CHECK_THAT(error_of([&] { decode(scene, good.data(), good.size() - 1); }), Contains("truncated"));
  }
  SECTION("trailing bytes") {
    std::vector<std::uint8_t> longer = good;
    longer.push_back(0);
    CHECK_THAT(error_of([&] { decode(scene, longer.data(), longer.size()); }), Contains("1 trailing bytes"));
  }
  SECTION("another type's fingerprint, an unknown one") {
    CHECK_THAT(error_of([&] { decode(r.at("corpus_a.point_t"), good.data(), good.size()); }),
               Contains("is not corpus_a.point_t's"));
    std::vector<std::uint8_t> unknown = good;
    unknown[0] ^= 0x55;
    CHECK_THAT(error_of([&] { decode(r, unknown.data(), unknown.size()); }), Contains("unknown fingerprint 0x"));
  }
  SECTION("huge and negative sizes fail before allocating") {
    // arrays_t: n8 n16 n32 n64 first. n64 = 2^62 bytes of blob, n32 = 2^31-1 doubles.
    corpus_a::arrays_t a = make_arrays();
    std::vector<std::uint8_t> bytes = lcm_encode(a);
    const StructType& t = r.at("corpus_a.arrays_t");
    std::vector<std::uint8_t> huge = bytes;
    for (int i = 0; i < 4; ++i) huge[8 + 3 + i] = i == 0 ? 0x7f : 0xff;  // n32
    const auto start = std::chrono::steady_clock::now();
    CHECK_THAT(error_of([&] { decode(t, huge.data(), huge.size()); }),
               Contains("var: message truncated: 2147483647 elements need at least 8 bytes each"));
    std::vector<std::uint8_t> negative = bytes;
    negative[8 + 1] = 0x80;  // n16 < 0
    CHECK_THAT(error_of([&] { decode(t, negative.data(), negative.size()); }), Contains("negative array size"));
    CHECK(std::chrono::steady_clock::now() - start < std::chrono::seconds(1));
  }
  SECTION("zero-size elements cannot make millions of nodes") {
    const TypeRegistry z = TypeRegistry::load_texts(
        {{"z.lcm", "struct e { }\nstruct z { int32_t n; e many[n]; }"}});
    const StructType& t = z.at("z");
    std::vector<std::uint8_t> msg(12);
    for (int i = 0; i < 8; ++i) msg[static_cast<std::size_t>(i)] = static_cast<std::uint8_t>(t.fingerprint >> (56 - 8 * i));
    msg[8] = 0x7f, msg[9] = 0xff, msg[10] = 0xff, msg[11] = 0xff;
    CHECK_THAT(error_of([&] { decode(t, msg.data(), msg.size()); }), Contains("more elements than a message"));
    msg[8] = 0, msg[9] = 0, msg[10] = 0, msg[11] = 100;  // a few are fine
    CHECK(decode(t, msg.data(), msg.size()).as<Struct>().find("many")->as<Array>().size() == 100);
  }
  SECTION("a bad string length names the field") {
    corpus_b::stamp_t st;
    st.frame = "abc";
    std::vector<std::uint8_t> bytes = lcm_encode(st);
    bytes[16] = 0, bytes[17] = 0, bytes[18] = 0, bytes[19] = 0;  // length 0 (needs >= 1)
    CHECK_THAT(error_of([&] { decode(r, bytes.data(), bytes.size()); }), Contains("frame: string length 0"));
  }
  SECTION("random corruption never crashes") {
    std::mt19937 rng(7);
    int decoded = 0;
    for (int i = 0; i < 3000; ++i) {
      std::vector<std::uint8_t> bad = good;
      for (int k = 0; k < 4; ++k) bad[8 + rng() % (bad.size() - 8)] = static_cast<std::uint8_t>(rng());
      try {
        decode(scene, bad.data(), bad.size());
        ++decoded;
      } catch (const Error&) {
      }
    }
    CHECK(decoded > 0);  // some corruptions only change values
  }
}

TEST_CASE("encoding a tree that does not fit its type names the field", "[unit]") {
  const TypeRegistry& r = corpus();
  const StructType& t = r.at("corpus_a.path_t");
  const Value good = zero_value(t);
  CHECK(encode(t, good) == lcm_encode(corpus_a::path_t{}));

  Value v = good;
  v.as<Struct>().fields.pop_back();
  CHECK_THAT(error_of([&] { encode(t, v); }), Contains("grid: missing field"));
  v = good;
  v.as<Struct>().fields.push_back({"extra", std::int64_t{1}});
  CHECK_THAT(error_of([&] { encode(t, v); }), Contains("extra: no such field in corpus_a.path_t"));
  v = good;
  v.as<Struct>().find("num_points")->data = std::int64_t{1};
  CHECK_THAT(error_of([&] { encode(t, v); }),
             Contains("points: array has 0 elements but its size member 'num_points' is 1"));
  v = good;
  v.as<Struct>().find("corners")->as<Array>()[2].as<Struct>().find("y")->data = std::string("no");
  CHECK_THAT(error_of([&] { encode(t, v); }), Contains("corners[2].y: expected a number"));

  // A zero value encodes like a value-initialized generated object (recursive tree_t too).
  CHECK(encode(r.at("corpus_b.tree_t"), zero_value(r.at("corpus_b.tree_t"))) == lcm_encode(corpus_b::tree_t{}));
  CHECK(encode(r.at("corpus_b.scene_t"), zero_value(r.at("corpus_b.scene_t"))).size() ==
        static_cast<std::size_t>(corpus_b::scene_t{}.getEncodedSize()));

  const StructType& p = r.at("corpus_a.primitives_t");
  Value q = zero_value(p);
  q.as<Struct>().find("i8")->data = std::int64_t{128};
  CHECK_THAT(error_of([&] { encode(p, q); }), Contains("i8: 128 is out of range for int8_t"));
  q = zero_value(p);
  q.as<Struct>().find("octet")->data = std::int64_t{-1};
  CHECK_THAT(error_of([&] { encode(p, q); }), Contains("octet: -1 is out of range for byte"));
  q = zero_value(p);
  q.as<Struct>().find("f64")->data = std::int64_t{3};  // an integer for a double: fine
  CHECK(decode(p, encode(p, q).data(), encode(p, q).size()).as<Struct>().find("f64")->as<double>() == 3.0);
}

TEST_CASE("JSON rendering is one line in field order and escaped", "[unit]") {
  const TypeRegistry& r = corpus();
  corpus_b::stamp_t st;
  st.utime = -5;
  st.frame = "a\"b\\c\n\x01\xc3\xa9\xff";
  const auto bytes = lcm_encode(st);
  CHECK(to_json(decode(r, bytes.data(), bytes.size())) ==
        R"({"utime":-5,"frame":"a\"b\\c\n\u0001é\u00ff"})");

  corpus_a::path_t p = make_path(1);
  const auto pb = lcm_encode(p);
  CHECK(to_json(decode(r, pb.data(), pb.size())) ==
        R"({"num_points":1,"points":[{"x":0.5,"y":-1.25,"z":5e-301}],"corners":[{"x":0,"y":-0.0,"z":0},)"
        R"({"x":-1,"y":2.5,"z":-1e-300},{"x":-2,"y":5,"z":-2e-300},{"x":-3,"y":7.5,"z":-3e-300}],)"
        R"("origin":{"x":7,"y":-17.5,"z":7e-300},"grid":[[{"x":0,"y":-0.0,"z":0}],[{"x":0,"y":-0.0,"z":0}]]})");

  Value special = Struct{nullptr, {{"nan", std::numeric_limits<double>::quiet_NaN()},
                                   {"f", 0.1f},
                                   {"b", true},
                                   {"bytes", Bytes{1, 2}}}};
  CHECK(to_json(special) == R"({"nan":null,"f":0.1,"b":true,"bytes":[1,2]})");
}

TEST_CASE("text rendering nests structs and abbreviates long arrays", "[unit]") {
  const TypeRegistry& r = corpus();
  corpus_a::path_t p = make_path(12);
  const auto pb = lcm_encode(p);
  const Value v = decode(r, pb.data(), pb.size());
  TextOptions o;
  o.max_array = 2;
  const std::string text = to_text(v, o);
  CHECK_THAT(text, Catch::StartsWith("num_points: 12\npoints: [12]\n  [0]:\n    x: 0.5\n    y: -1.25\n"));
  CHECK_THAT(text, Contains("  ... (10 more)\ncorners: [4]\n"));
  CHECK_THAT(text, Contains("origin:\n  x: 7\n  y: -17.5\n  z: 7e-300\ngrid: [2]\n  [0]: [12]\n    [0]:\n      x: 0\n"));

  const auto ab = lcm_encode(make_arrays());
  const std::string arrays = to_text(decode(r, ab.data(), ab.size()), o);
  CHECK_THAT(arrays, Contains("\nblob: <5 bytes: 00 01 ...>\n"));
  CHECK_THAT(arrays, Contains("\nvar: [0.5, -1, ... (2 more)]\n"));
  CHECK_THAT(arrays, Contains("\ngrid: [[0, 0.14285715, ... (1 more)], [1.4285715, 1.5714285, ... (1 more)]]\n"));
  CHECK_THAT(arrays, Contains("\nnames: [\"\", \"one\", ... (2 more)]\n"));
  CHECK_THAT(arrays, Contains("\nflags: [true, false]\n"));
  CHECK_THAT(to_text(decode(r, ab.data(), ab.size()), TextOptions{0, 2}), Contains("blob: <5 bytes: 00 01 7f 80 ff>"));
}

TEST_CASE("text rendering escapes a string's C0 and C1 controls (a terminal takes U+009B for CSI), JSON keeps C1 "
          "as it is",
          "[unit]") {
  const TypeRegistry& r = corpus();
  corpus_b::stamp_t st;
  st.utime = 1;
  st.frame = "a\x1b[2J\xc2\x9b" "2Jb\xc2\x85\xc3\xa9";  // ESC [ 2 J, CSI (U+009B) 2 J, NEL (U+0085), é
  const auto bytes = lcm_encode(st);
  const Value v = decode(r, bytes.data(), bytes.size());
  const std::string text = to_text(v);
  CHECK_THAT(text, Contains(R"(frame: "a\u001b[2J\u009b2Jb\u0085é")"));
  for (const char c : text) CHECK(static_cast<unsigned char>(c) != 0x1b);
  CHECK(text.find("\xc2\x9b") == std::string::npos);
  CHECK(text.find("\xc2\x85") == std::string::npos);
  CHECK(to_json(v) == "{\"utime\":1,\"frame\":\"a\\u001b[2J\xc2\x9b" "2Jb\xc2\x85\xc3\xa9\"}");
}

TEST_CASE("field paths select parts of a tree and name what is missing", "[unit]") {
  const TypeRegistry& r = corpus();
  const auto bytes = lcm_encode(make_scene());
  const Value v = decode(r, bytes.data(), bytes.size());
  CHECK(to_json(field(v, "stamp.frame")) == R"("map")");
  CHECK(field(v, "paths[0].points[1].x").as<double>() == 1.5);
  CHECK(field(v, "arrays.cube[3][2][1]").as<std::int64_t>() == 321);
  CHECK(field(v, "arrays.blob[4]").as<std::int64_t>() == 0xff);
  CHECK(field(v, "arrays.image[2][1]").as<std::int64_t>() == 205);
  CHECK(field(v, "deep.two.three[1].stamp.utime").as<std::int64_t>() == 33);
  CHECK(to_json(field(v, "")) == to_json(v));
  CHECK(field(v, "paths[0].points").as<Array>().size() == 2);

  CHECK_THAT(error_of([&] { field(v, "stamp.nope"); }), Contains("no field 'nope' in stamp"));
  CHECK_THAT(error_of([&] { field(v, "nope"); }), Contains("no field 'nope' in corpus_b.scene_t"));
  CHECK_THAT(error_of([&] { field(v, "landmarks[3]"); }),
             Contains("index 3 out of range (3 elements) at landmarks[3]"));
  CHECK_THAT(error_of([&] { field(v, "arrays.blob[5]"); }), Contains("out of range (5 elements)"));
  CHECK_THAT(error_of([&] { field(v, "stamp[0]"); }), Contains("stamp is not an array"));
  CHECK_THAT(error_of([&] { field(v, "stamp.utime.x"); }), Contains("stamp.utime is not a struct"));
  CHECK_THAT(error_of([&] { field(v, "landmarks[x]"); }), Contains("bad index 'x'"));
  CHECK_THAT(error_of([&] { field(v, "landmarks[1"); }), Contains("expected [index]"));
  CHECK_THAT(error_of([&] { field(v, "stamp..frame"); }), Contains("empty field name"));
  CHECK_THAT(error_of([&] { field(v, ".stamp"); }), Contains("misplaced '.'"));
}
