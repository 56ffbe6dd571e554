// lcmx::foxglove's pure pieces: the JSON Schema / JSON mapping of LCM types (flattening, base64,
// NaN), the image and point-cloud views, client JSON back into messages, and a client's bounded
// queue (drop policy: the oldest messages of the subscription holding the most bytes go first).
#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <memory>

#include "client_queue.hpp"
#include "mapping.hpp"

using namespace lcmx;
using namespace lcmx::foxglove::detail;

namespace {
const char* kTypes = R"(
package t;
struct inner_t { int32_t a; string s; }
struct m_t {
  int64_t utime;
  int32_t n;
  double grid[2][3];
  inner_t items[n];
  float f;
  byte raw[n][2];
  boolean ok;
}
struct img_t { string frame_id; int32_t width; int32_t height; string encoding; int32_t size; byte data[size]; }
struct jpg_t { string format; int32_t size; byte data[size]; }
struct cloud_t { int32_t nf; string fields[nf]; int32_t point_step; int32_t size; byte data[size]; }
)";

types::TypeRegistry reg() { return types::TypeRegistry::load_texts({{"t.lcm", kTypes}}); }
}  // namespace

TEST_CASE("foxglove mapping: schema within Foxglove's reader, flattened arrays, base64, NaN as null", "[foxglove]") {
  const auto r = reg();
  const auto& t = r.at("t.m_t");
  const auto schema = json_schema(t);
  CHECK(schema.find("$ref") == std::string::npos);
  CHECK(schema.find(R"("title":"t.m_t")") != std::string::npos);
  // double grid[2][3]: one array of 6 numbers; byte raw[n][2]: one base64 string.
  CHECK(schema.find(R"("grid":{"type":"array","items":{"type":"number")") != std::string::npos);
  CHECK(schema.find(R"("minItems":6,"maxItems":6)") != std::string::npos);
  CHECK(schema.find(R"("raw":{"type":"string","contentEncoding":"base64")") != std::string::npos);

  auto v = types::zero_value(t);
  auto& s = v.as<types::Struct>();
  s.find("utime")->data = std::int64_t{1'700'000'000'000'000};
  s.find("n")->data = std::int64_t{1};
  auto& grid = s.find("grid")->as<types::Array>();
  grid[0].as<types::Array>()[2].data = 2.5;
  grid[1].as<types::Array>()[0].data = std::numeric_limits<double>::quiet_NaN();
  types::Array items;
  items.push_back(types::zero_value(r.at("t.inner_t")));
  items[0].as<types::Struct>().find("s")->data = std::string("q\"\x01");
  s.find("items")->data = items;
  types::Array raw;
  raw.push_back(types::Bytes{0xff, 0x00});
  s.find("raw")->data = raw;
  s.find("f")->data = std::numeric_limits<float>::infinity();
  const auto j = foxglove::detail::to_json(v);
  CHECK(j ==
        R"({"utime":1700000000000000,"n":1,"grid":[0,0,2.5,null,0,0],"items":[{"a":0,"s":"q\"\u0001"}],"f":null,"raw":"/wA=","ok":false})");
  CHECK(utime_ns(v) == std::uint64_t{1'700'000'000'000'000'000});

  // And back: flattened arrays and base64 are taken, as are lcmx's own nested arrays.
  const auto back = from_foxglove_json(t, R"({"n":1,"grid":[1,2,3,4,5,6],"items":[{"a":3}],"raw":"/wA="})");
  const auto bytes = types::encode(t, back);
  const auto again = types::decode(t, bytes.data(), bytes.size());
  CHECK(foxglove::detail::to_json(again) ==
        R"({"utime":0,"n":1,"grid":[1,2,3,4,5,6],"items":[{"a":3,"s":""}],"f":0,"raw":"/wA=","ok":false})");
  CHECK_NOTHROW(from_foxglove_json(t, R"({"grid":[[1,2,3],[4,5,6]]})"));
  CHECK_THROWS_WITH(from_foxglove_json(t, R"({"grid":[1,2,3]})"), Catch::Contains("grid"));
  CHECK_THROWS_WITH(from_foxglove_json(t, R"({"nope":1})"), Catch::Contains("nope"));
  CHECK_THROWS(from_foxglove_json(t, "{"));
}

TEST_CASE("foxglove mapping: image, compressed image and point cloud views", "[foxglove]") {
  const auto r = reg();
  CHECK(view_of(r.at("t.m_t")).kind == ViewKind::none);
  const auto& img = r.at("t.img_t");
  REQUIRE(view_of(img).kind == ViewKind::raw_image);
  CHECK(std::string(view_of(img).schema_name) == "foxglove.RawImage");
  auto v = types::zero_value(img);
  auto& s = v.as<types::Struct>();
  s.find("frame_id")->data = std::string("cam");
  s.find("width")->data = std::int64_t{2};
  s.find("height")->data = std::int64_t{1};
  s.find("encoding")->data = std::string("mono8");
  s.find("size")->data = std::int64_t{2};
  s.find("data")->data = types::Bytes{1, 2};
  const auto j = to_view_json(ViewKind::raw_image, v, 1'500'000'000'123'456'789ull);
  REQUIRE(j);
  CHECK(*j ==
        R"({"timestamp":{"sec":1500000000,"nsec":123456789},"frame_id":"cam","width":2,"height":1,"encoding":"mono8","step":2,"data":"AQI="})");
  s.find("height")->data = std::int64_t{5};  // data too short for 5 rows
  CHECK_FALSE(to_view_json(ViewKind::raw_image, v, 0));

  CHECK(view_of(r.at("t.jpg_t")).kind == ViewKind::compressed_image);
  const auto& cl = r.at("t.cloud_t");
  REQUIRE(view_of(cl).kind == ViewKind::point_cloud);
  auto c = types::zero_value(cl);
  auto& cs = c.as<types::Struct>();
  cs.find("nf")->data = std::int64_t{3};
  cs.find("fields")->data = types::Array{std::string("x"), std::string("y"), std::string("z")};
  cs.find("point_step")->data = std::int64_t{12};
  const auto pj = to_view_json(ViewKind::point_cloud, c, 5);
  REQUIRE(pj);
  CHECK(pj->find(R"("fields":[{"name":"x","offset":0,"type":7},{"name":"y","offset":4,"type":7})") != std::string::npos);
}

TEST_CASE("foxglove mapping: a large image's base64 is made once, shared by the struct and its view", "[foxglove]") {
  const auto r = reg();
  auto v = types::zero_value(r.at("t.img_t"));
  auto& s = v.as<types::Struct>();
  s.find("width")->data = std::int64_t{300};
  s.find("height")->data = std::int64_t{300};
  s.find("encoding")->data = std::string("mono8");
  types::Bytes px(90'000);
  for (std::size_t i = 0; i < px.size(); ++i) px[i] = static_cast<std::uint8_t>(i * 13);
  s.find("size")->data = std::int64_t{90'000};
  s.find("data")->data = px;
  Base64Cache cache;
  const Payload whole = foxglove::detail::to_json(v, cache);
  const auto view = to_view_json(ViewKind::raw_image, v, 7, cache);
  REQUIRE(view);
  // The same text as the one-string forms, and the base64 part is one object in both.
  CHECK(whole.joined() == foxglove::detail::to_json(v));
  CHECK(view->joined() == *to_view_json(ViewKind::raw_image, v, 7));
  CHECK(whole.size == whole.joined().size());
  REQUIRE(whole.parts.size() == 3);
  REQUIRE(view->parts.size() == 3);
  CHECK(whole.parts[1] == view->parts[1]);
  CHECK(whole.parts[1]->size() == 120'000);
  // Small byte arrays stay inline (one part).
  s.find("data")->data = types::Bytes{1, 2, 3};
  s.find("size")->data = std::int64_t{3};
  Base64Cache other;
  CHECK(foxglove::detail::to_json(v, other).parts.size() == 1);
}

TEST_CASE("foxglove mapping: unknown types and base64", "[foxglove]") {
  const std::uint8_t d[] = {0, 1, 2, 3, 4, 5, 6, 7, 8};
  CHECK(unknown_json(0x0001020304050607, d, 9) ==
        R"({"fingerprint":"0x0001020304050607","size":9,"data":"AAECAwQFBgcI"})");
  for (std::size_t n = 0; n < 9; ++n) {
    std::string b;
    base64_append(b, d, n);
    const auto back = base64_decode(b);
    CHECK(back == types::Bytes(d, d + n));
  }
  CHECK_THROWS(base64_decode("a$=="));
}

TEST_CASE("foxglove mapping: JSON strings carry valid UTF-8 as is, each byte of invalid UTF-8 escaped", "[foxglove]") {
  auto js = [](std::string_view s) {
    std::string o;
    json_string_append(o, s);
    return o;
  };
  // Valid: 2, 3 and 4 bytes, at the edges of each range (U+0080, U+07FF, U+0800, U+D7FF,
  // U+E000, U+FFFF, U+10000, U+10FFFF) and ordinary text.
  for (const std::string_view v : {"\xC2\x80", "\xDF\xBF", "\xE0\xA0\x80", "\xED\x9F\xBF", "\xEE\x80\x80", "\xEF\xBF\xBF",
                                   "\xF0\x90\x80\x80", "\xF4\x8F\xBF\xBF", "caf\xC3\xA9 \xE6\x97\xA5\xE6\x9C\xAC \xF0\x9F\x98\x80"}) {
    INFO(v);
    CHECK(js(v) == "\"" + std::string(v) + "\"");
  }
  // Invalid: each byte escaped on its own (a continuation byte alone is invalid too).
  CHECK(js("\xED\xA0\x80") == R"("\u00ed\u00a0\u0080")");           // U+D800, a surrogate
  CHECK(js("\xED\xBF\xBF") == R"("\u00ed\u00bf\u00bf")");           // U+DFFF
  CHECK(js("\xE0\x9F\xBF") == R"("\u00e0\u009f\u00bf")");           // overlong U+07FF
  CHECK(js("\xE0\x80\x80") == R"("\u00e0\u0080\u0080")");           // overlong U+0000
  CHECK(js("\xF0\x8F\xBF\xBF") == R"("\u00f0\u008f\u00bf\u00bf")"); // overlong U+FFFF
  CHECK(js("\xF4\x90\x80\x80") == R"("\u00f4\u0090\u0080\u0080")"); // U+110000
  CHECK(js("\xF5\x80\x80\x80") == R"("\u00f5\u0080\u0080\u0080")"); // lead bytes F5..F7
  CHECK(js("\xF7\xBF\xBF\xBF") == R"("\u00f7\u00bf\u00bf\u00bf")");
  CHECK(js("\xC0\x80") == R"("\u00c0\u0080")");                     // overlong 2-byte
  CHECK(js("\xE6\x97") == R"("\u00e6\u0097")");                     // truncated
  // Around an invalid sequence, the rest is unchanged.
  CHECK(js("a\xED\xA0\x80\xC3\xA9\"\x01") == R"("a\u00ed\u00a0\u0080)" "\xC3\xA9" R"(\"\u0001")");
}

namespace {
QueuedMessage msg(std::uint32_t sub, std::size_t bytes) {
  return {sub, 0, Payload::of(std::string(bytes, 'x')), 0};
}
}  // namespace

TEST_CASE("foxglove client queue: bounded, large channels lose their oldest first, arrival order kept", "[foxglove]") {
  ClientQueue q(1000, 100);
  // A large channel (sub 1, 300 B) and a small one (sub 2, 10 B), interleaved.
  std::size_t dropped = 0;
  for (int i = 0; i < 20; ++i) {
    dropped += q.push(msg(1, 300));
    dropped += q.push(msg(2, 10));
  }
  CHECK(q.bytes() <= 1000);
  CHECK(dropped == q.dropped());
  CHECK(q.last_dropped_subscription() == 1);
  // Every small message is still there: only the large channel paid.
  std::size_t small = 0, large = 0;
  std::uint64_t last = 0;
  bool ordered = true;
  while (auto m = q.pop()) {
    (m->subscription == 2 ? small : large)++;
    ordered = ordered && (m->order >= last);
    last = m->order;
  }
  CHECK(small == 20);
  CHECK(large >= 1);
  CHECK(ordered);
  CHECK(q.empty());
  CHECK(q.bytes() == 0);

  // The message bound too; a message larger than the byte bound is dropped itself.
  ClientQueue q2(1 << 20, 4);
  for (int i = 0; i < 10; ++i) q2.push(msg(7, 1));
  CHECK(q2.size() == 4);
  CHECK(q2.push(msg(8, 2 << 20)) == 1);
  CHECK(q2.size() == 4);
  q2.erase(7);
  CHECK(q2.empty());

  // Three subscriptions: pops follow arrival order across them; erasing one keeps the others'.
  ClientQueue q3(1 << 20, 100);
  for (int i = 0; i < 9; ++i) q3.push(msg(static_cast<std::uint32_t>(10 + i % 3), 5));
  q3.erase(11);
  CHECK(q3.size() == 6);
  CHECK(q3.bytes() == 30);
  std::vector<std::uint32_t> subs;
  while (auto m = q3.pop()) subs.push_back(m->subscription);
  CHECK(subs == std::vector<std::uint32_t>{10, 12, 10, 12, 10, 12});
}
