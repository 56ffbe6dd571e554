// lcmx::types::from_json: JSON text -> Value, round trips through to_json against lcm-gen's
// encodings, and every error naming what is wrong and where.
#include <catch2/catch.hpp>

#include <cmath>

#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "samples.hpp"

using namespace samples;
using Catch::Contains;

namespace {

const TypeRegistry& examples() {
  static const TypeRegistry r = TypeRegistry::load({LCMX_LCMTYPES_DIR});
  return r;
}

// lcm-gen encodes, we decode and render JSON, parse it back and encode: the same bytes.
template <class T>
void json_round_trip(const TypeRegistry& r, const T& msg) {
  const std::vector<std::uint8_t> theirs = lcm_encode(msg);
  const Value tree = decode(r, theirs.data(), theirs.size());
  const StructType& t = *tree.as<Struct>().type;
  const std::string j = to_json(tree);
  INFO(j);
  CHECK(encode(t, from_json(t, j)) == theirs);
}

std::string from_json_error(const StructType& t, const std::string& j) {
  return error_of([&] { (void)from_json(t, j); });
}

}  // namespace

TEST_CASE("from_json reads back what to_json writes - every corpus type", "[unit]") {
  const TypeRegistry& r = corpus();
  json_round_trip(r, make_primitives());
  json_round_trip(r, make_arrays());
  json_round_trip(r, make_path(3));
  json_round_trip(r, make_scene());
  // Random trees of every type, through JSON.
  std::mt19937 rng(777);
  for (const char* name : {"corpus_a.primitives_t", "corpus_a.arrays_t", "corpus_a.path_t", "corpus_b.scene_t",
                           "corpus_b.tree_t", "plain_t"}) {
    INFO(name);
    const StructType& t = r.at(name);
    for (int i = 0; i < 10; ++i) {
      const Value tree = random_tree(t, rng, 0);
      CHECK(encode(t, from_json(t, to_json(tree))) == encode(t, tree));
    }
  }
}

TEST_CASE("from_json: fields not given are zero, in nested structs too", "[unit]") {
  const TypeRegistry& r = corpus();
  for (const char* name : {"corpus_a.arrays_t", "corpus_b.scene_t", "plain_t"}) {
    const StructType& t = r.at(name);
    CHECK(encode(t, from_json(t, "{}")) == encode(t, zero_value(t)));
  }
  const StructType& pose = examples().at("lcmx_examples.pose_t");
  const Value v = from_json(pose, R"({"header": {"frame_id": "map"}, "position": [1, 2.5, -3]})");
  const Struct& s = v.as<Struct>();
  CHECK(s.find("header")->as<Struct>().find("frame_id")->as<std::string>() == "map");
  CHECK(s.find("header")->as<Struct>().find("seq")->as<std::int64_t>() == 0);
  CHECK(s.find("position")->as<Array>()[1].as<double>() == 2.5);
  CHECK(s.find("position")->as<Array>()[2].as<double>() == -3.0);
  CHECK(s.find("orientation")->as<Array>().size() == 4);
  // lcm-gen decodes what we encode.
  const auto bytes = encode(pose, v);
  lcmx_examples::pose_t p;
  REQUIRE(p.decode(bytes.data(), 0, static_cast<int>(bytes.size())) == static_cast<int>(bytes.size()));
  CHECK(p.header.frame_id == "map");
  CHECK(p.position[0] == 1.0);
}

TEST_CASE("from_json: variable arrays set their size members", "[unit]") {
  const StructType& image = examples().at("lcmx_examples.image_t");
  SECTION("the size member follows the array") {
    const auto bytes = encode(image, from_json(image, R"({"width": 2, "height": 1, "data": [1, 2, 255]})"));
    lcmx_examples::image_t m;
    REQUIRE(m.decode(bytes.data(), 0, static_cast<int>(bytes.size())) == static_cast<int>(bytes.size()));
    CHECK(m.size == 3);
    CHECK(m.data == std::vector<std::uint8_t>{1, 2, 255});
  }
  SECTION("a size given with the array must agree") {
    CHECK_NOTHROW(from_json(image, R"({"size": 2, "data": [7, 8]})"));
    CHECK_THAT(from_json_error(image, R"({"size": 3, "data": [7, 8]})"),
               Contains("from_json: data: has 2 elements but its size 'size' is 3 (given)"));
  }
  SECTION("a size given without the array makes a zero-filled one") {
    const Value v = from_json(image, R"({"size": 6})");
    CHECK(v.as<Struct>().find("data")->as<Bytes>() == Bytes(6, 0));
    CHECK(encode(image, v).size() == lcm_encode([] {
                                       lcmx_examples::image_t m;
                                       m.size = 6;
                                       m.data.assign(6, 0);
                                       return m;
                                     }()).size());
  }
  SECTION("arrays sharing a size member must agree, inner dimensions too") {
    const StructType& arrays = corpus().at("corpus_a.arrays_t");
    CHECK_THAT(from_json_error(arrays, R"({"var": [1, 2], "names": ["a"]})"),
               Contains("from_json: names: has 1 elements but its size 'n32' is 2 (the length of var)"));
    CHECK_THAT(from_json_error(arrays, R"({"mixed2": [[1], [2], [3, 4], [5]]})"),
               Contains("from_json: mixed2[2]: has 2 elements but its size 'n8' is 1 (the length of mixed2[0])"));
    const Value v = from_json(arrays, R"({"cube": [[[1, 2]], [[3, 4]]], "image": [[9]]})");
    CHECK(v.as<Struct>().find("n32")->as<std::int64_t>() == 2);
    CHECK(v.as<Struct>().find("n8")->as<std::int64_t>() == 1);
    CHECK(v.as<Struct>().find("n16")->as<std::int64_t>() == 1);
    // Arrays not given follow: names has n32 = 2 empty strings, mixed n8 = 1 row.
    CHECK(v.as<Struct>().find("names")->as<Array>().size() == 2);
    CHECK(v.as<Struct>().find("mixed")->as<Array>().size() == 1);
    CHECK_NOTHROW(encode(arrays, v));
  }
  SECTION("too many elements for the size member's type") {
    const StructType& arrays = corpus().at("corpus_a.arrays_t");
    std::string j = R"({"longs": [)";
    for (int i = 0; i < 128; ++i) j += (i ? "," : "") + std::to_string(i);
    j += "]}";
    CHECK_THAT(from_json_error(arrays, j), Contains("from_json: longs: has 128 elements: too many for its size member 'n8' (int8_t)"));
  }
}

TEST_CASE("from_json errors name the field and what is wrong", "[unit]") {
  const TypeRegistry& r = corpus();
  const StructType& prims = r.at("corpus_a.primitives_t");
  const StructType& pose = examples().at("lcmx_examples.pose_t");
  const StructType& scene = r.at("corpus_b.scene_t");

  // Unknown fields, by their full path.
  CHECK_THAT(from_json_error(pose, R"({"positon": [1, 2, 3]})"),
             Contains("from_json: positon: no such field in lcmx_examples.pose_t (its fields: header, position, orientation)"));
  CHECK_THAT(from_json_error(pose, R"({"header": {"sequence": 1}})"),
             Contains("from_json: header.sequence: no such field in lcmx_examples.header_t"));
  CHECK_THAT(from_json_error(scene, R"({"paths": [{}, {"points": [{"x": 1}, {"w": 2}]}]})"),
             Contains("from_json: paths[1].points[1].w: no such field in corpus_a.point_t"));

  // Wrong kinds.
  CHECK_THAT(from_json_error(prims, R"({"i32": "12"})"), Contains("from_json: i32: expected an integer (int32_t), got a string"));
  CHECK_THAT(from_json_error(prims, R"({"i32": true})"), Contains("i32: expected an integer (int32_t), got a boolean"));
  CHECK_THAT(from_json_error(prims, R"({"i32": 1.5})"), Contains("i32: expected an integer (int32_t), got 1.5"));
  CHECK_THAT(from_json_error(prims, R"({"text": 5})"), Contains("text: expected a string, got an integer"));
  CHECK_THAT(from_json_error(prims, R"({"flag": 1})"), Contains("flag: expected true or false, got 1"));
  CHECK_THAT(from_json_error(prims, R"({"f64": "x"})"), Contains("f64: expected a number (double"));
  CHECK_THAT(from_json_error(pose, R"({"position": 3})"), Contains("position: expected an array, got an integer"));
  CHECK_THAT(from_json_error(pose, R"({"header": []})"),
             Contains("header: expected an object (lcmx_examples.header_t), got an array"));
  CHECK_THAT(from_json_error(pose, "[]"), Contains("from_json: (message): expected an object (lcmx_examples.pose_t)"));

  // Out of range.
  CHECK_THAT(from_json_error(prims, R"({"i8": 128})"), Contains("i8: 128 is out of range for int8_t"));
  CHECK_THAT(from_json_error(prims, R"({"i16": -32769})"), Contains("i16: -32769 is out of range for int16_t"));
  CHECK_THAT(from_json_error(prims, R"({"octet": 256})"), Contains("octet: 256 is out of range for byte"));
  CHECK_THAT(from_json_error(prims, R"({"octet": -1})"), Contains("octet: -1 is out of range for byte"));
  CHECK_THAT(from_json_error(prims, R"({"i64": 9223372036854775808})"),
             Contains("i64: 9223372036854775808 is out of range for int64_t"));
  CHECK_THAT(from_json_error(prims, R"({"i64": 1e19})"), Contains("i64: 1e+19 is out of range for int64_t"));
  CHECK_THAT(from_json_error(prims, R"({"f32": 1e39})"), Contains("f32: 1e+39 is out of range for float"));
  const StructType& image = examples().at("lcmx_examples.image_t");
  CHECK_THAT(from_json_error(image, R"({"data": [0, 300]})"), Contains("data[1]: 300 is out of range for byte"));

  // Fixed lengths.
  CHECK_THAT(from_json_error(pose, R"({"position": [1, 2]})"),
             Contains("from_json: position: has 2 elements, the type says 3 ([3])"));
  CHECK_THAT(from_json_error(r.at("corpus_a.arrays_t"), R"({"grid": [[1, 2, 3], [4, 5]]})"),
             Contains("grid[1]: has 2 elements, the type says 3"));

  // Sizes.
  CHECK_THAT(from_json_error(image, R"({"size": -1})"), Contains("size: a size cannot be negative (-1)"));

  // JSON itself.
  CHECK_THAT(from_json_error(pose, "{\"position\": [1, 2,\n 3}"),
             Contains("from_json: invalid JSON: parse error at line 2, column 3"));
  CHECK_THAT(from_json_error(pose, ""), Contains("from_json: invalid JSON"));
  CHECK_THAT(from_json_error(pose, R"({"position": [1, 2, 3]} x)"), Contains("from_json: invalid JSON"));
  CHECK_THAT(from_json_error(pose, R"({"header": {"seq": 1, "seq": 2}})"),
             Contains("the key 'seq' appears twice in one object"));
}

TEST_CASE("from_json: integers written as whole floats, and non-finite floats", "[unit]") {
  const StructType& prims = corpus().at("corpus_a.primitives_t");
  const Struct s = from_json(prims, R"({"i32": 2.0, "i64": -1e3, "f64": null, "f32": "-inf", "octet": 255})").as<Struct>();
  CHECK(s.find("i32")->as<std::int64_t>() == 2);
  CHECK(s.find("i64")->as<std::int64_t>() == -1000);
  CHECK(std::isnan(s.find("f64")->as<double>()));
  CHECK(s.find("f32")->as<float>() == -INFINITY);
  CHECK(s.find("octet")->as<std::int64_t>() == 255);
  const Struct big = from_json(prims, R"({"i64": -9223372036854775808})").as<Struct>();
  CHECK(big.find("i64")->as<std::int64_t>() == INT64_MIN);
}

TEST_CASE("from_json bounds deep recursion and huge zero fills", "[unit]") {
  const StructType& tree = corpus().at("corpus_b.tree_t");
  std::string deep;
  for (int i = 0; i < 70; ++i) deep += R"({"children": [)";
  deep += "{}";
  for (int i = 0; i < 70; ++i) deep += "]}";
  CHECK_THAT(from_json_error(tree, deep), Contains("nesting deeper than 64 structs"));
  // A huge JSON nesting of arrays where a number is expected is an error, not a stack overflow.
  std::string nested(100000, '[');
  CHECK_THAT(from_json_error(examples().at("lcmx_examples.pose_t"), R"({"position": )" + nested),
             Contains("invalid JSON"));
  CHECK_THAT(from_json_error(examples().at("lcmx_examples.image_t"), R"({"size": 2000000000})"),
             Contains("more than 2^26 elements"));
}

TEST_CASE("from_json: float's extremes read back", "[unit]") {
  const StructType& prims = corpus().at("corpus_a.primitives_t");
  for (float f : {std::numeric_limits<float>::max(), -std::numeric_limits<float>::max(),
                  std::numeric_limits<float>::denorm_min(), std::numeric_limits<float>::min()}) {
    Value v = zero_value(prims);
    *v.as<Struct>().find("f32") = f;
    const std::string j = to_json(v);
    INFO(j);
    CHECK(from_json(prims, j).as<Struct>().find("f32")->as<float>() == f);
  }
  CHECK_THAT(from_json_error(prims, R"({"f32": 3.4028236e38})"), Contains("out of range for float"));
}
