// lcmx monitor's model (apps/lcmx/monitor_model.hpp) without a terminal: rates, jitter,
// bandwidth from arrival times given by the test; type names from the type path, beacons or the
// fingerprint; publishers and paths; sort, filter; the opened channel; the folding tree.
#include <catch2/catch.hpp>

#include <algorithm>

#include "monitor_model.hpp"

using namespace lcmx::cli::monitor;
using namespace std::chrono_literals;
namespace ty = lcmx::types;

namespace {

const char* kTypes = R"(
package demo;
struct inner_t { int32_t a; double b; }
struct msg_t {
  int32_t n;
  inner_t inner;
  int16_t values[n];
  byte blob[20];
  string name;
}
)";

std::vector<std::byte> encoded(const ty::TypeRegistry& reg, int n) {
  const auto& t = reg.at("demo.msg_t");
  auto v = ty::zero_value(t);
  auto& s = v.as<ty::Struct>();
  s.find("n")->data = std::int64_t{n};
  ty::Array a;
  a.resize(static_cast<std::size_t>(n));
  for (int i = 0; i < n; ++i) a[static_cast<std::size_t>(i)].data = std::int64_t{i * 10};
  s.find("values")->data = a;
  s.find("inner")->as<ty::Struct>().find("a")->data = std::int64_t{42};
  s.find("name")->data = std::string("hello");
  const auto bytes = ty::encode(t, v);
  std::vector<std::byte> out(bytes.size());
  std::transform(bytes.begin(), bytes.end(), out.begin(), [](std::uint8_t b) { return std::byte{b}; });
  return out;
}

const Row* find(const std::vector<Row>& rows, const std::string& ch) {
  for (const auto& r : rows)
    if (r.channel == ch) return &r;
  return nullptr;
}

std::vector<std::string> order(const std::vector<Row>& rows) {
  std::vector<std::string> o;
  for (const auto& r : rows) o.push_back(r.channel);
  return o;
}

// A beacon with publishers / a subscriber.
lcmx::discovery::Participant participant(std::int64_t id, std::int64_t host, const std::string& proc, int pid) {
  lcmx::discovery::Participant p;
  p.beacon.participant_id = id;
  p.beacon.host_id = host;
  p.beacon.process_name = proc;
  p.beacon.pid = pid;
  p.beacon.flags = 0;  // lcm-gen leaves members uninitialised
  return p;
}
void add_endpoint(lcmx::discovery::Participant& p, std::int64_t id, std::int8_t kind, const std::string& node,
                  const std::string& topic, const std::string& type = "", std::int64_t fp = 0) {
  lcmx_msgs::endpoint_t e;
  e.id = id;
  e.kind = kind;
  e.node = node;
  e.topic = topic;
  e.type_name = type;
  e.fingerprint = fp;
  p.beacon.endpoints.push_back(e);
  p.beacon.num_endpoints = static_cast<std::int32_t>(p.beacon.endpoints.size());
  if (std::find(p.beacon.nodes.begin(), p.beacon.nodes.end(), node) == p.beacon.nodes.end()) {
    p.beacon.nodes.push_back(node);
    p.beacon.num_nodes = static_cast<std::int32_t>(p.beacon.nodes.size());
  }
}

}  // namespace

TEST_CASE("rate, jitter, bandwidth and age over the window from arrival times", "[monitor]") {
  const auto t0 = Clock::time_point{} + 1000s;
  Model m(nullptr, 2s, 60, t0);
  std::vector<std::byte> msg(100);
  // FAST: 100 Hz exactly for 3 s; JITTERY: 10 Hz with intervals alternating 50 / 150 ms.
  auto next_tick = t0 + 500ms;
  auto jt = t0;
  bool short_gap = true;
  for (int i = 0; i < 300; ++i) {
    const auto t = t0 + i * 10ms;
    while (t >= next_tick) {
      m.tick(next_tick);
      next_tick += 500ms;
    }
    m.on_message("FAST", msg, t);
    if (t >= jt) {
      m.on_message("JITTERY", std::span(msg).first(10), t);
      jt = t + (short_gap ? 50ms : 150ms);
      short_gap = !short_gap;
    }
  }
  m.tick(t0 + 3s);
  const auto rows = m.rows(t0 + 3s);
  const Row* fast = find(rows, "FAST");
  const Row* jit = find(rows, "JITTERY");
  REQUIRE(fast);
  REQUIRE(jit);
  CHECK(fast->hz == Approx(100).epsilon(0.02));
  CHECK(fast->jitter_ms < 0.01);
  CHECK(fast->bytes_per_s == Approx(10000).epsilon(0.02));
  CHECK(fast->messages == 300);
  CHECK(fast->last_size == 100);
  CHECK(fast->age_s == Approx(0.01).margin(1e-6));
  CHECK(jit->hz == Approx(10).epsilon(0.1));
  CHECK(jit->jitter_ms == Approx(50).epsilon(0.05));  // std dev of {50, 150} ms
  // The sparkline history: one sample per tick, ~100 Hz each.
  const auto h = m.rate_history("FAST");
  REQUIRE(h.size() == 6);
  CHECK(h.back() == Approx(100).epsilon(0.05));

  // Silence: the rate falls to zero once the window has passed, the age grows.
  m.tick(t0 + 3500ms);
  m.tick(t0 + 4000ms);
  m.tick(t0 + 4500ms);
  m.tick(t0 + 5000ms);
  m.tick(t0 + 5500ms);
  const auto later = m.rows(t0 + 5500ms);
  CHECK(find(later, "FAST")->hz == 0);
  CHECK(find(later, "FAST")->age_s == Approx(2.51).margin(1e-3));
}

TEST_CASE("type names: the type path by fingerprint, else the beacon's, else the fingerprint in hex", "[monitor]") {
  const auto reg = ty::TypeRegistry::load_texts({{"demo.lcm", kTypes}});
  const auto bytes = encoded(reg, 3);
  const auto t = Clock::now();
  Model with(&reg);
  with.on_message("A", bytes, t);
  CHECK(with.rows(t).at(0).type == "demo.msg_t");

  Model without(nullptr);
  without.on_message("A", bytes, t);
  char hex[32];
  std::snprintf(hex, sizeof hex, "0x%016llx", static_cast<unsigned long long>(reg.at("demo.msg_t").fingerprint));
  CHECK(without.rows(t).at(0).type == hex);
  // Shorter than a fingerprint.
  std::vector<std::byte> tiny(3);
  without.on_message("TINY", tiny, t);
  CHECK(find(without.rows(t), "TINY")->type == "?");

  // The beacon's name when the type path does not know it (lcm-gen's name, no package).
  auto p = participant(7, 0x1234, "camera", 99);
  add_endpoint(p, 1, lcmx_msgs::endpoint_t::KIND_PUBLISHER, "cam", "A", "msg_t", 5);
  without.set_topology({p}, 1);
  CHECK(find(without.rows(t), "A")->type == "msg_t");
}

TEST_CASE("publishers and paths from beacons and our pairs, announced silent topics, our own left out",
          "[monitor]") {
  Model m(nullptr);
  const auto t = Clock::now();
  auto cam = participant(7, 0xabcd1234, "camera", 99);
  add_endpoint(cam, 1, lcmx_msgs::endpoint_t::KIND_PUBLISHER, "cam", "IMAGE", "image_t", 5);
  add_endpoint(cam, 2, lcmx_msgs::endpoint_t::KIND_PUBLISHER, "cam", "SILENT", "image_t", 5);
  add_endpoint(cam, 3, lcmx_msgs::endpoint_t::KIND_SUBSCRIBER, "cam", "CMD");
  auto self = participant(8, 0xabcd1234, "lcmx", 100);
  add_endpoint(self, 1, lcmx_msgs::endpoint_t::KIND_PUBLISHER, "mon", "OURS");
  m.on_message("IMAGE", std::vector<std::byte>(10), t);
  m.on_message("STOCK", std::vector<std::byte>(10), t);
  m.set_topology({cam, self}, 8);
  lcmx::SubscriberStats image, stock;
  image.drops = 4;
  image.publishers.push_back({7, 1, lcmx::Path::shm, 10, 4});
  stock.publishers.push_back({0, 77, lcmx::Path::udp, 10, 0});
  m.set_stats({{"IMAGE", image}, {"STOCK", stock}});
  const auto rows = m.rows(t);
  CHECK(order(rows) == std::vector<std::string>{"IMAGE", "SILENT", "STOCK"});
  CHECK(find(rows, "IMAGE")->publishers == "camera[99]@1234");
  CHECK(find(rows, "IMAGE")->paths == "shm");
  CHECK(find(rows, "IMAGE")->drops == 4);
  CHECK(find(rows, "SILENT")->age_s < 0);
  CHECK(find(rows, "STOCK")->publishers == "LCM sender");
  CHECK(find(rows, "STOCK")->paths == "udp");
  // The publisher leaves: its silent topic goes, the one with messages stays.
  m.set_topology({}, 8);
  CHECK(order(m.rows(t)) == std::vector<std::string>{"IMAGE", "STOCK"});
}

TEST_CASE("sort by any column both ways (ties by name), filter by regex, bad regex rejected", "[monitor]") {
  const auto t0 = Clock::now();
  Model m(nullptr, 2s, 60, t0);
  // B at 3 messages, A at 1, C at 2 within the window.
  for (int i = 0; i < 3; ++i) m.on_message("cam/B", std::vector<std::byte>(10), t0 + i * 1ms);
  m.on_message("cam/A", std::vector<std::byte>(30), t0);
  for (int i = 0; i < 2; ++i) m.on_message("lidar/C", std::vector<std::byte>(5), t0 + i * 1ms);
  m.tick(t0 + 1s);
  const auto now = t0 + 1s;
  CHECK(order(m.rows(now)) == std::vector<std::string>{"cam/A", "cam/B", "lidar/C"});
  m.set_sort(Column::hz, true);
  CHECK(order(m.rows(now)) == std::vector<std::string>{"cam/B", "lidar/C", "cam/A"});
  m.set_sort(Column::hz, false);
  CHECK(order(m.rows(now)) == std::vector<std::string>{"cam/A", "lidar/C", "cam/B"});
  m.set_sort(Column::bandwidth, true);  // B 30, A 30, C 10 bytes: tie by name
  CHECK(order(m.rows(now)) == std::vector<std::string>{"cam/B", "cam/A", "lidar/C"});
  m.set_sort(Column::channel, true);
  CHECK(order(m.rows(now)) == std::vector<std::string>{"lidar/C", "cam/B", "cam/A"});
  m.set_filter("^CAM/");  // case-insensitive search
  CHECK(order(m.rows(now)) == std::vector<std::string>{"cam/B", "cam/A"});
  CHECK(m.filter() == "^CAM/");
  CHECK_THROWS_AS(m.set_filter("(unclosed"), std::regex_error);
  CHECK(m.filter() == "^CAM/");  // unchanged
  m.set_filter("");
  CHECK(m.rows(now).size() == 3);
}

TEST_CASE("only the opened channel's latest message is kept, once per arrival", "[monitor]") {
  Model m(nullptr);
  const auto t = Clock::now();
  std::vector<std::byte> a(4, std::byte{1}), b(4, std::byte{2}), c(4, std::byte{3});
  m.on_message("X", a, t);
  CHECK_FALSE(m.take_latest());  // nothing opened
  m.open("X");
  CHECK_FALSE(m.take_latest());  // opened after that message
  m.on_message("Y", c, t);
  m.on_message("X", a, t);
  m.on_message("X", b, t);
  const auto got = m.take_latest();
  REQUIRE(got);
  CHECK(*got == b);
  CHECK_FALSE(m.take_latest());
  m.close();
  m.on_message("X", a, t);
  CHECK_FALSE(m.take_latest());
}

TEST_CASE("tree: nested structs open, long arrays and bytes folded, toggles flip them", "[monitor]") {
  const auto reg = ty::TypeRegistry::load_texts({{"demo.lcm", kTypes}});
  const auto bytes = encoded(reg, 12);
  const auto v = ty::decode(reg, bytes.data(), bytes.size());
  auto text = [](const std::vector<TreeLine>& ls) {
    std::string o;
    for (const auto& l : ls) o += std::string(static_cast<std::size_t>(l.depth) * 2, ' ') + l.text + "\n";
    return o;
  };
  const auto lines = tree_lines(v, {});
  INFO(text(lines));
  REQUIRE(lines.size() == 8);  // msg_t, n, inner, a, b, values (folded), blob (folded), name
  CHECK(lines[0].text == "demo.msg_t");
  CHECK(lines[2].text == "inner: demo.inner_t");
  CHECK(lines[2].foldable);
  CHECK_FALSE(lines[2].folded);
  CHECK(lines[3].text == "a: 42");
  CHECK(lines[3].path == "inner.a");
  CHECK(lines[5].path == "values");
  CHECK(lines[5].folded);
  CHECK(lines[5].text == "values: [12] {0, 10, 20, 30, ...}");
  CHECK(lines[6].folded);
  CHECK(lines[6].text.rfind("blob: bytes[20] {00 00", 0) == 0);
  CHECK(lines[7].text == "name: \"hello\"");

  const auto open = tree_lines(v, {"values", "inner"});
  INFO(text(open));
  REQUIRE(open.size() == 8 - 2 + 12);  // inner folded (-2), values open (+12)
  CHECK(open[2].text == "inner: demo.inner_t {...}");
  CHECK(open[4].text == "[0]: 0");
  CHECK(open[4].depth == 2);
  CHECK(open[15].text == "[11]: 110");

  // Long arrays are cut at max_elements.
  const auto cut = tree_lines(v, {"values"}, 8, 5);
  const auto more = std::find_if(cut.begin(), cut.end(), [](const TreeLine& l) { return l.text == "... 7 more"; });
  CHECK(more != cut.end());

  // Bytes open: rows of 16.
  const auto blob = tree_lines(v, {"blob"});
  CHECK(std::count_if(blob.begin(), blob.end(), [](const TreeLine& l) { return l.path.rfind("blob@", 0) == 0; }) == 2);
}

TEST_CASE("sparkline and human numbers", "[monitor]") {
  CHECK(sparkline({0, 1, 2, 4, 8}, 10, false) == " .:=#");
  CHECK(sparkline({0, 1, 2, 4, 8}, 2, false) == "=#");  // the last `width`
  CHECK(sparkline({0, 8}, 10, true) == " \u2588");
  CHECK(sparkline({}, 10, true).empty());
  CHECK(human(999) == "999");
  CHECK(human(12345) == "12.3k");
  CHECK(human(4.5e6) == "4.5M");
}
