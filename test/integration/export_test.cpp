// `lcmx log export` (issue 11 item 7): logs of lcm-gen-encoded messages exported to MCAP —
// checked by an independent reader written from the MCAP spec (mcap_check.py: records, CRCs,
// summary, JSON Schema validation of every message) and compared field by field with the
// lcm-gen objects — and to CSV, checked by content. Unknown fingerprints, truncated logs, bad
// options.
#include <sched.h>
#include <sys/mount.h>
#include <sys/stat.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>

#include "corpus_a/arrays_t.hpp"
#include "corpus_a/primitives_t.hpp"
#include "corpus_b/tree_t.hpp"
#include "lcmx/log/eventlog.hpp"
#include "lcmx_examples/pose_t.hpp"
#include "support.hpp"

using namespace lcmx::it;
namespace el = lcmx::eventlog;

#ifdef LCMX_TOOL

namespace {

std::string slurp(const std::string& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

template <class T>
std::vector<std::byte> encode(const T& m) {
  std::vector<std::byte> b(static_cast<std::size_t>(m.getEncodedSize()));
  REQUIRE(m.encode(b.data(), 0, static_cast<int>(b.size())) == static_cast<int>(b.size()));
  return b;
}

// Python's json.dumps(s, ensure_ascii=False) of the strings used here.
std::string py_str(const std::string& s) {
  std::string o = "\"";
  for (char c : s) {
    if (c == '"') o += "\\\"";
    else if (c == '\\') o += "\\\\";
    else if (c == '\t') o += "\\t";
    else if (c == '\n') o += "\\n";
    else o += c;
  }
  return o + "\"";
}

// One message as mcap_check.py prints it.
struct Msg {
  std::string topic, schema;
  long long sequence = 0;
  unsigned long long log_time = 0, publish_time = 0;
  std::map<std::string, std::string> leaves;
  const std::string& at(const std::string& path) const {
    auto it = leaves.find(path);
    if (it == leaves.end()) FAIL("no field " << path << " in a message on " << topic);
    return it->second;
  }
};

struct Checked {
  int rc = -1;
  std::string out;
  std::vector<Msg> messages;
  std::vector<const Msg*> on(const std::string& topic) const {
    std::vector<const Msg*> r;
    for (const auto& m : messages)
      if (m.topic == topic) r.push_back(&m);
    return r;
  }
};

// Runs the independent reader on an MCAP file.
Checked mcap_check(Session& s, const std::string& mcap) {
  Checked c;
  const auto r = s.run({LCMX_PYTHON3, LCMX_MCAP_CHECK, mcap}, {"PYTHONIOENCODING=utf-8"}, 30000ms);
  c.rc = r.rc;
  c.out = r.out;
  std::istringstream in(r.out);
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("MSG\t", 0) != 0) continue;
    std::vector<std::string> f;
    std::size_t p = 0;
    for (;;) {
      const auto t = line.find('\t', p);
      f.push_back(line.substr(p, t == std::string::npos ? std::string::npos : t - p));
      if (t == std::string::npos) break;
      p = t + 1;
    }
    REQUIRE(f.size() >= 6);
    Msg m{f[1], f[2], std::stoll(f[3]), std::stoull(f[4]), std::stoull(f[5]), {}};
    for (std::size_t i = 6; i < f.size(); ++i) {
      const auto eq = f[i].find('=');
      m.leaves[f[i].substr(0, eq)] = f[i].substr(eq + 1);
    }
    c.messages.push_back(std::move(m));
  }
  return c;
}

double num(const std::string& s) {
  char* end = nullptr;
  const double v = std::strtod(s.c_str(), &end);
  if (end == s.c_str() || *end != '\0') FAIL("not a number: " << s);
  return v;
}

const std::int64_t kT0 = 1'763'900'000'000'000;  // µs

lcmx_examples::pose_t pose(int i) {
  lcmx_examples::pose_t p;
  p.header.seq = i;
  p.header.stamp_ns = 1'000'000'007LL * i;
  p.header.frame_id = i == 1 ? "map, \"quoted\"" : "map";
  p.position[0] = 1.5 * i;
  p.position[1] = -2.25;
  p.position[2] = 0.125 * i + 0.001;
  p.orientation[0] = 0;
  p.orientation[1] = 0.1;
  p.orientation[2] = 0.5;
  p.orientation[3] = i == 2 ? std::numeric_limits<double>::quiet_NaN() : 1.0;
  return p;
}

corpus_a::primitives_t prims() {
  corpus_a::primitives_t m;
  m.i8 = -128;
  m.i16 = -32768;
  m.i32 = -2147483647 - 1;
  m.i64 = std::numeric_limits<std::int64_t>::max();  // beyond a double's 2^53
  m.f32 = 0.1f;
  m.f64 = -2.5e300;
  m.text = "h\xc3\xa9llo\tw\"orld";
  m.flag = 1;
  m.octet = 255;
  m.a = 1;
  m.b = -2;
  m.c = 3;
  return m;
}

corpus_a::arrays_t arrays() {
  corpus_a::arrays_t m;
  m.n8 = 2;
  m.n16 = 3;
  m.n32 = 2;
  m.n64 = 5;
  for (int i = 0; i < 3; ++i) m.fixed[i] = 100 + i;
  for (int i = 0; i < 4; ++i) m.hexsized[i] = static_cast<std::int8_t>(-i);
  m.var = {0.25, -1e-9};
  m.blob = {0, 1, 127, 128, 255};
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j) m.grid[i][j] = static_cast<float>(i * 10 + j) + 0.5f;
  m.mixed.assign(2, std::vector<std::int16_t>(4));
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 4; ++j) m.mixed[i][j] = static_cast<std::int16_t>(i * 100 + j);
  m.mixed2.resize(4);
  for (int i = 0; i < 4; ++i) {
    m.mixed2[i].resize(2);
    for (int j = 0; j < 2; ++j) m.mixed2[i][j] = static_cast<std::int16_t>(-(i * 10 + j));
  }
  m.flags = {1, 0, 1};
  m.names = {"a", "b,c"};
  m.table.resize(2);
  for (int i = 0; i < 2; ++i) {
    m.table[i].resize(3);
    for (int j = 0; j < 3; ++j) m.table[i][j] = "t" + std::to_string(i) + std::to_string(j);
  }
  m.cube.resize(2);
  for (int i = 0; i < 2; ++i) {
    m.cube[i].assign(2, std::vector<std::int32_t>(2));
    for (int j = 0; j < 2; ++j)
      for (int k = 0; k < 2; ++k) m.cube[i][j][k] = i * 100 + j * 10 + k;
  }
  m.image.resize(2);
  for (int i = 0; i < 2; ++i) {
    m.image[i].resize(3);
    for (int j = 0; j < 3; ++j) m.image[i][j] = static_cast<std::uint8_t>(200 + i * 10 + j);
  }
  m.longs = {std::numeric_limits<std::int64_t>::min(), -1};
  m.more_longs[0] = 1LL << 60;
  m.more_longs[1] = 7;
  return m;
}

corpus_b::tree_t tree() {
  corpus_b::tree_t leaf;
  leaf.value = 3;
  leaf.num_children = 0;
  leaf.stamp.utime = 33;
  leaf.stamp.frame = "leaf";
  corpus_b::tree_t mid;
  mid.value = 2;
  mid.num_children = 1;
  mid.children = {leaf};
  mid.stamp.utime = 22;
  mid.stamp.frame = "mid";
  corpus_b::tree_t root;
  root.value = 1;
  root.num_children = 2;
  root.children = {mid, leaf};
  root.stamp.utime = 11;
  root.stamp.frame = "root";
  return root;
}

// Every leaf of an arrays_t as mcap_check.py flattens to_json's output (the lcm-gen object is
// the reference).
std::map<std::string, std::string> arrays_leaves(const corpus_a::arrays_t& m) {
  std::map<std::string, std::string> e;
  auto I = [](auto v) { return std::to_string(static_cast<long long>(v)); };
  e["n8"] = I(m.n8);
  e["n16"] = I(m.n16);
  e["n32"] = I(m.n32);
  e["n64"] = I(m.n64);
  for (int i = 0; i < 3; ++i) e["fixed[" + I(i) + "]"] = I(m.fixed[i]);
  for (int i = 0; i < 4; ++i) e["hexsized[" + I(i) + "]"] = I(m.hexsized[i]);
  for (std::size_t i = 0; i < m.blob.size(); ++i) e["blob[" + I(i) + "]"] = I(m.blob[i]);
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 4; ++j) e["mixed[" + I(i) + "][" + I(j) + "]"] = I(m.mixed[i][j]);
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 2; ++j) e["mixed2[" + I(i) + "][" + I(j) + "]"] = I(m.mixed2[i][j]);
  for (std::size_t i = 0; i < m.flags.size(); ++i) e["flags[" + I(i) + "]"] = m.flags[i] ? "true" : "false";
  for (std::size_t i = 0; i < m.names.size(); ++i) e["names[" + I(i) + "]"] = py_str(m.names[i]);
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j) e["table[" + I(i) + "][" + I(j) + "]"] = py_str(m.table[i][j]);
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j)
      for (int k = 0; k < 2; ++k) e["cube[" + I(i) + "][" + I(j) + "][" + I(k) + "]"] = I(m.cube[i][j][k]);
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j) e["image[" + I(i) + "][" + I(j) + "]"] = I(m.image[i][j]);
  for (std::size_t i = 0; i < m.longs.size(); ++i) e["longs[" + I(i) + "]"] = I(m.longs[i]);
  for (int i = 0; i < 2; ++i) e["more_longs[" + I(i) + "]"] = I(m.more_longs[i]);
  return e;
}

struct Log {
  std::string path, pose_ch, prim_ch, arr_ch, tree_ch, unknown_ch;
  std::vector<std::int64_t> pose_numbers;  // event numbers of the pose messages
};

// A log of lcm-gen-encoded messages of the corpus and lcmx_examples types, plus messages of a
// type in no .lcm file and one too short to hold a fingerprint.
Log write_log(const TmpDir& d, int index) {
  Log l;
  l.path = d.file("mixed.lcmlog");
  l.pose_ch = unique_channel("POSE", index);
  l.prim_ch = unique_channel("PRIM", index);
  l.arr_ch = unique_channel("ARR", index);
  l.tree_ch = unique_channel("TREE", index);
  l.unknown_ch = unique_channel("UNKNOWN", index);
  auto w = el::Writer::open(l.path, el::OpenMode::create);
  std::int64_t n = 0;
  for (int i = 0; i < 3; ++i) {
    w.write(kT0 + i * 1000, l.pose_ch, encode(pose(i)));
    l.pose_numbers.push_back(n++);
    std::vector<std::byte> unknown(20, std::byte{0x5a});
    const unsigned char fp[8] = {0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77, 0x88};
    std::memcpy(unknown.data(), fp, 8);
    w.write(kT0 + i * 1000 + 1, l.unknown_ch, unknown);
    ++n;
  }
  w.write(kT0 + 5000, l.prim_ch, encode(prims()));
  w.write(kT0 + 6000, l.arr_ch, encode(arrays()));
  w.write(kT0 + 7000, l.tree_ch, encode(tree()));
  w.write(kT0 + 8000, l.unknown_ch, std::vector<std::byte>(3, std::byte{1}));
  w.close();
  return l;
}

const std::string kTypes = std::string(LCMX_TYPES_CORPUS) + ":" + LCMX_LCMTYPES_DIR;

}  // namespace

TEST_CASE("log export --format mcap: lcm-gen messages decoded field by field, checked by an independent MCAP reader",
          "[integration][export]") {
  Session s(120);
  TmpDir d;
  const auto l = write_log(d, 120);
  const auto out = d.file("out.mcap");
  const auto r = s.run({LCMX_TOOL, "log", "export", l.path, "--types", kTypes, "-o", out, "--json"});
  INFO(r.out);
  REQUIRE(r.rc == 0);
  const auto j = json_line(r.out);
  CHECK(json_num(j, "events") == 10);
  CHECK(json_num(j, "exported") == 6);
  // The unknown channel: counted, its fingerprint named, the short message too.
  CHECK(contains(j, "{\"channel\":" + std::string("\"") + l.unknown_ch + "\",\"types\":[],\"exported\":0,\"unknown\":4"));
  CHECK(contains(j, "\"unknown_fingerprints\":[\"0x1122334455667788\"]"));
  // The text summary says the same.
  const auto text = s.run({LCMX_TOOL, "log", "export", l.path, "--types", kTypes, "-o", d.file("t.mcap")});
  CHECK(text.rc == 0);
  CHECK(contains(text.out, l.unknown_ch + "  [-]  0 exported, 4 of unknown type skipped (63 bytes; fingerprint "
                                          "0x1122334455667788 none: shorter than 8 bytes)"));
  CHECK(contains(text.out, l.pose_ch + "  [lcmx_examples.pose_t]  3 exported"));
  CHECK_FALSE(contains(text.out, "exporting"));  // no progress line when stderr is no terminal

  const auto c = mcap_check(s, out);
  INFO(c.out.substr(0, 4000));
  REQUIRE(c.rc == 0);
  CHECK(contains(c.out, "OK messages=6 schemas=4 channels=4"));
  // Foxglove's JSON Schema reader (objects, scalars, arrays of those) can show the usual types;
  // arrays of arrays and recursive types it cannot, and the export says so.
  CHECK(contains(c.out, "SCHEMA\tlcmx_examples.pose_t\tfoxglove=yes\n"));
  CHECK(contains(c.out, "SCHEMA\tcorpus_a.primitives_t\tfoxglove=yes\n"));
  CHECK(contains(c.out, "SCHEMA\tcorpus_a.arrays_t\tfoxglove=no: corpus_a.arrays_t.grid: array of"));
  CHECK(contains(c.out, "SCHEMA\tcorpus_b.tree_t\tfoxglove=no: corpus_b.tree_t.children: array of {\"$ref\""));
  CHECK(contains(j, "\"foxglove_unsupported\":[\"corpus_a.arrays_t: multi-dimensional array corpus_a.arrays_t.grid\","
                    "\"corpus_b.tree_t: corpus_b.tree_t contains itself\"]"));
  CHECK(contains(text.out, "note: Foxglove's JSON Schema reader cannot show corpus_a.arrays_t: multi-dimensional array"));

  const auto poses = c.on(l.pose_ch);
  REQUIRE(poses.size() == 3);
  for (int i = 0; i < 3; ++i) {
    const auto& m = *poses[static_cast<std::size_t>(i)];
    const auto p = pose(i);
    CHECK(m.schema == "lcmx_examples.pose_t");
    CHECK(m.sequence == l.pose_numbers[static_cast<std::size_t>(i)]);
    CHECK(m.log_time == static_cast<unsigned long long>(kT0 + i * 1000) * 1000ull);
    CHECK(m.publish_time == m.log_time);
    CHECK(m.leaves.size() == 3 + 3 + 4);
    CHECK(m.at("header.seq") == std::to_string(p.header.seq));
    CHECK(m.at("header.stamp_ns") == std::to_string(p.header.stamp_ns));
    CHECK(m.at("header.frame_id") == py_str(p.header.frame_id));
    for (int k = 0; k < 3; ++k) CHECK(num(m.at("position[" + std::to_string(k) + "]")) == p.position[k]);
    for (int k = 0; k < 4; ++k) {
      const auto& v = m.at("orientation[" + std::to_string(k) + "]");
      if (std::isnan(p.orientation[k])) CHECK(v == "null");
      else CHECK(num(v) == p.orientation[k]);
    }
  }

  const auto pr = c.on(l.prim_ch);
  REQUIRE(pr.size() == 1);
  {
    const auto& m = *pr[0];
    const auto p = prims();
    CHECK(m.schema == "corpus_a.primitives_t");
    CHECK(m.leaves.size() == 12);
    CHECK(m.at("i8") == "-128");
    CHECK(m.at("i16") == "-32768");
    CHECK(m.at("i32") == "-2147483648");
    CHECK(m.at("i64") == "9223372036854775807");  // exact, not rounded through a double
    CHECK(static_cast<float>(num(m.at("f32"))) == p.f32);
    CHECK(num(m.at("f64")) == p.f64);
    CHECK(m.at("text") == py_str(p.text));
    CHECK(m.at("flag") == "true");
    CHECK(m.at("octet") == "255");
    CHECK(m.at("a") == "1");
    CHECK(m.at("b") == "-2");
    CHECK(m.at("c") == "3");
  }

  const auto ar = c.on(l.arr_ch);
  REQUIRE(ar.size() == 1);
  {
    const auto& m = *ar[0];
    const auto a = arrays();
    CHECK(m.schema == "corpus_a.arrays_t");
    const auto want = arrays_leaves(a);
    for (const auto& [k, v] : want) CHECK(m.at(k) == v);
    for (std::size_t i = 0; i < a.var.size(); ++i) CHECK(num(m.at("var[" + std::to_string(i) + "]")) == a.var[i]);
    for (int i = 0; i < 2; ++i)
      for (int k = 0; k < 3; ++k)
        CHECK(static_cast<float>(num(m.at("grid[" + std::to_string(i) + "][" + std::to_string(k) + "]"))) == a.grid[i][k]);
    CHECK(m.leaves.size() == want.size() + a.var.size() + 6);
  }

  const auto tr = c.on(l.tree_ch);
  REQUIRE(tr.size() == 1);
  {  // a recursive type: its schema refers to itself, and the reader validated the message
    const auto& m = *tr[0];
    CHECK(m.schema == "corpus_b.tree_t");
    CHECK(m.at("value") == "1");
    CHECK(m.at("children[0].value") == "2");
    CHECK(m.at("children[0].children[0].stamp.frame") == "\"leaf\"");
    CHECK(m.at("children[1].stamp.utime") == "33");
    CHECK(m.at("stamp.frame") == "\"root\"");
  }
  CHECK(c.on(l.unknown_ch).empty());

  // The reader is not a rubber stamp: a flipped byte in a message fails the data CRC, a
  // cut file has no trailing magic.
  auto bytes = slurp(out);
  const auto at = bytes.find("\"frame_id\":\"map\"");
  REQUIRE(at != std::string::npos);
  bytes[at + 13] = 'X';
  std::ofstream(d.file("flipped.mcap"), std::ios::binary) << bytes;
  const auto bad = mcap_check(s, d.file("flipped.mcap"));
  CHECK(bad.rc == 1);
  CHECK(contains(bad.out, "FAIL Data End CRC"));
  auto summary = slurp(out);
  summary[summary.size() - 8 - 29 - 3] ^= 0x01;  // in the last Summary Offset record
  std::ofstream(d.file("summary.mcap"), std::ios::binary) << summary;
  const auto bad_summary = mcap_check(s, d.file("summary.mcap"));
  CHECK(bad_summary.rc == 1);
  CHECK(contains(bad_summary.out, "FAIL summary CRC"));
  std::ofstream(d.file("cut.mcap"), std::ios::binary) << slurp(out).substr(0, bytes.size() - 30);
  const auto cut = mcap_check(s, d.file("cut.mcap"));
  CHECK(cut.rc == 1);
  CHECK(contains(cut.out, "FAIL"));
}

TEST_CASE("log export --format csv: one file per channel, leaf fields flattened, --fields, quoting",
          "[integration][export]") {
  Session s(121);
  TmpDir d;
  const auto l = write_log(d, 121);
  const auto dir = d.file("csv");
  // --types before FILE: one value per --types, FILE stays the positional.
  const auto r = s.run({LCMX_TOOL, "log", "export", "--types", kTypes, "--format", "csv", l.path, "-o", dir});
  INFO(r.out);
  REQUIRE(r.rc == 0);
  const auto pose_csv = slurp(dir + "/" + l.pose_ch + ".csv");
  std::string want =
      "timestamp_us,header.seq,header.stamp_ns,header.frame_id,position[0],position[1],position[2],orientation[0],"
      "orientation[1],orientation[2],orientation[3]\n";
  want += std::to_string(kT0) + ",0,0,map,0,-2.25,0.001,0,0.1,0.5,1\n";
  want += std::to_string(kT0 + 1000) + ",1,1000000007,\"map, \"\"quoted\"\"\",1.5,-2.25,0.126,0,0.1,0.5,1\n";
  want += std::to_string(kT0 + 2000) + ",2,2000000014,map,3,-2.25,0.251,0,0.1,0.5,nan\n";
  CHECK(pose_csv == want);

  // Arrays with a variable dimension are one JSON cell; small fixed ones are expanded (grid is 2x3).
  const auto arr_csv = slurp(dir + "/" + l.arr_ch + ".csv");
  const auto nl = arr_csv.find('\n');
  REQUIRE(nl != std::string::npos);
  CHECK(arr_csv.substr(0, nl) ==
        "timestamp_us,n8,n16,n32,n64,fixed[0],fixed[1],fixed[2],hexsized[0],hexsized[1],hexsized[2],hexsized[3],var,"
        "blob,grid[0][0],grid[0][1],grid[0][2],grid[1][0],grid[1][1],grid[1][2],mixed,mixed2,flags,names,table,cube,"
        "image,longs,more_longs[0],more_longs[1]");
  CHECK(arr_csv.substr(nl + 1) ==
        std::to_string(kT0 + 6000) +
            ",2,3,2,5,100,101,102,0,-1,-2,-3,\"[0.25,-1e-09]\",\"[0,1,127,128,255]\",0.5,1.5,2.5,10.5,11.5,12.5,"
            "\"[[0,1,2,3],[100,101,102,103]]\",\"[[0,-1],[-10,-11],[-20,-21],[-30,-31]]\",\"[true,false,true]\","
            "\"[\"\"a\"\",\"\"b,c\"\"]\",\"[[\"\"t00\"\",\"\"t01\"\",\"\"t02\"\"],[\"\"t10\"\",\"\"t11\"\",\"\"t12\"\"]]\","
            "\"[[[0,1],[10,11]],[[100,101],[110,111]]]\",\"[[200,201,202],[210,211,212]]\","
            "\"[-9223372036854775808,-1]\",1152921504606846976,7\n");
  const auto prim_csv = slurp(dir + "/" + l.prim_ch + ".csv");
  CHECK(contains(prim_csv, ",-128,-32768,-2147483648,9223372036854775807,0.1,-2.5e+300,\"h\xc3\xa9llo\tw\"\"orld\",true,255,1,-2,3\n"));
  // No file for the channel of unknown type.
  CHECK_FALSE(std::ifstream(dir + "/" + l.unknown_ch + ".csv").good());

  SECTION("--fields picks columns, in order; a whole array is one JSON cell") {
    const auto dir2 = d.file("fields");
    const auto f = s.run({LCMX_TOOL, "log", "export", l.path, "--format", "csv", "--types", kTypes, "-o", dir2, "-c",
                          l.pose_ch, "--fields", "position[1],header.seq,orientation"});
    INFO(f.out);
    REQUIRE(f.rc == 0);
    CHECK(slurp(dir2 + "/" + l.pose_ch + ".csv") ==
          "timestamp_us,position[1],header.seq,orientation\n" + std::to_string(kT0) + ",-2.25,0,\"[0,0.1,0.5,1]\"\n" +
              std::to_string(kT0 + 1000) + ",-2.25,1,\"[0,0.1,0.5,1]\"\n" + std::to_string(kT0 + 2000) +
              ",-2.25,2,\"[0,0.1,0.5,null]\"\n");
    // Only the selected channel.
    CHECK_FALSE(std::ifstream(dir2 + "/" + l.prim_ch + ".csv").good());
  }
  SECTION("a field the type lacks is an error naming it; existing files are kept without --force") {
    const auto bad = s.run({LCMX_TOOL, "log", "export", l.path, "--format", "csv", "--types", kTypes, "-o", d.file("b"),
                            "-c", l.pose_ch, "--fields", "header.nope"});
    CHECK(bad.rc == 2);
    CHECK(contains(bad.out, "no field 'nope' in lcmx_examples.header_t"));
    const auto again = s.run({LCMX_TOOL, "log", "export", l.path, "--format", "csv", "--types", kTypes, "-o", dir});
    CHECK(again.rc == 2);
    CHECK(contains(again.out, "exists (use --force to overwrite)"));
    CHECK(s.run({LCMX_TOOL, "log", "export", l.path, "--format", "csv", "--types", kTypes, "-o", dir, "-f"}).rc == 0);
  }
}

TEST_CASE("log export of a truncated log exports up to the damage and says where - bad types and options are errors",
          "[integration][export]") {
  Session s(122);
  TmpDir d;
  const auto ch = unique_channel("CUT", 122);
  const auto good = d.file("good.lcmlog");
  std::vector<std::uint64_t> offsets;
  {
    auto w = el::Writer::open(good, el::OpenMode::create);
    for (int i = 0; i < 10; ++i) w.write(kT0 + i * 100, ch, encode(pose(i)));
    w.close();
    auto r = el::Reader::open(good);
    el::Event e;
    while (r.next(e)) offsets.push_back(e.offset);
  }
  REQUIRE(offsets.size() == 10);
  const auto all = slurp(good);
  const auto cut = d.file("cut.lcmlog");
  std::ofstream(cut, std::ios::binary) << all.substr(0, offsets[7] + 40);

  const auto r = s.run({LCMX_TOOL, "log", "export", cut, "--types", LCMX_LCMTYPES_DIR, "-o", d.file("cut.mcap"), "--json"});
  INFO(r.out);
  CHECK(r.rc == 0);
  CHECK(json_num(json_line(r.out), "exported") == 7);
  CHECK(contains(r.out, "\"kind\":\"truncated\",\"offset\":" + std::to_string(offsets[7]) + ",\"length\":40"));
  CHECK(contains(r.out, "the log ends with truncated bytes at offset " + std::to_string(offsets[7]) +
                            " (40 bytes): exported up to there"));
  const auto c = mcap_check(s, d.file("cut.mcap"));
  INFO(c.out);
  CHECK(c.rc == 0);
  CHECK(contains(c.out, "OK messages=7 schemas=1 channels=1"));
  REQUIRE(c.on(ch).size() == 7);
  CHECK(c.on(ch)[6]->at("header.seq") == "6");

  // A corrupt event in the middle: skipped, said where, the rest exported.
  auto bad_bytes = all;
  bad_bytes[offsets[3] + 25] = '\x55';  // its data length
  std::ofstream(d.file("corrupt.lcmlog"), std::ios::binary) << bad_bytes;
  const auto cr = s.run({LCMX_TOOL, "log", "export", d.file("corrupt.lcmlog"), "--types", LCMX_LCMTYPES_DIR, "-o",
                         d.file("corrupt.mcap"), "--json"});
  INFO(cr.out);
  CHECK(cr.rc == 0);
  CHECK(json_num(json_line(cr.out), "exported") == 9);
  CHECK(contains(cr.out, "damaged log: " + std::to_string(offsets[4] - offsets[3]) + " bytes skipped at offset " +
                             std::to_string(offsets[3])));
  CHECK(mcap_check(s, d.file("corrupt.mcap")).on(ch).size() == 9);

  // The default output name: FILE with .mcap.
  CHECK(s.run({LCMX_TOOL, "log", "export", good}, {std::string("LCMX_TYPES_PATH=") + LCMX_LCMTYPES_DIR}).rc == 0);
  CHECK(mcap_check(s, d.file("good.mcap")).on(ch).size() == 10);

  const auto no_types = s.run({LCMX_TOOL, "log", "export", good, "-o", d.file("x.mcap")}, {"LCMX_TYPES_PATH"});
  CHECK(no_types.rc == 2);
  CHECK(contains(no_types.out, "no types: give --types"));
  std::ofstream(d.file("bad.lcm")) << "package p;\nstruct s_t {\n  int32_t x\n}\n";
  const auto bad_lcm = s.run({LCMX_TOOL, "log", "export", good, "--types", d.file("bad.lcm"), "-o", d.file("y.mcap")});
  CHECK(bad_lcm.rc == 2);
  CHECK(contains(bad_lcm.out, d.file("bad.lcm") + ":"));
  const auto bad_format = s.run({LCMX_TOOL, "log", "export", good, "--format", "bag"});
  CHECK(bad_format.rc != 0);
  CHECK(contains(bad_format.out, "--format"));
  const auto missing = s.run({LCMX_TOOL, "log", "export", d.file("missing.lcmlog"), "--types", LCMX_LCMTYPES_DIR});
  CHECK(missing.rc == 1);
  CHECK(contains(missing.out, "cannot open"));
  const auto self = s.run({LCMX_TOOL, "log", "export", good, "--types", LCMX_LCMTYPES_DIR, "-o", good, "-f"});
  CHECK(self.rc == 2);
  CHECK(contains(self.out, "is the log itself"));
  CHECK(slurp(good) == all);
  const auto help = s.run({LCMX_TOOL, "log", "export", "--help"});
  CHECK(help.rc == 0);
  CHECK(contains(help.out, "--fields"));
}

// The ordinary case: a log `lcmx record` made of a live lcm-gen publisher (pose_t over shared
// memory), exported with the type path from LCMX_TYPES_PATH.
// A full disk mid-export: the error names its reason and the half-written outputs are removed
// (a truncated CSV or MCAP would look complete). A private 16 KiB tmpfs in this test's own
// mount namespace (each test case runs as its own process); skipped where that is refused.
TEST_CASE("log export on a full disk says why and leaves no partial output", "[integration][export][tmpfs]") {
  Session s(127);
  TmpDir d;
  const auto log = d.file("many.lcmlog");
  {
    auto w = el::Writer::open(log, el::OpenMode::create);
    lcmx_examples::pose_t p{};
    for (int i = 0; i < 3000; ++i) {
      p.position[0] = i;
      w.write(kT0 + i * 1000, "FULL_POSE", encode(p));
    }
    w.close();
  }
  const auto small = d.file("small");
  REQUIRE(::mkdir(small.c_str(), 0755) == 0);
  if (::unshare(CLONE_NEWNS) != 0 || ::mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0 ||
      ::mount("tmpfs", small.c_str(), "tmpfs", MS_NOSUID | MS_NODEV, "size=16k") != 0) {
    LCMX_SKIP("cannot mount a private tmpfs");
  }
  struct Unmount {
    std::string path;
    ~Unmount() { ::umount2(path.c_str(), MNT_DETACH); }
  } unmount{small};
  for (const std::string format : {"csv", "mcap"}) {
    const auto out = small + (format == "csv" ? "/csv" : "/out.mcap");
    const auto r = s.run({LCMX_TOOL, "log", "export", "--types", kTypes, "--format", format, log, "-o", out});
    INFO(format << ": " << r.out);
    CHECK(r.rc == 1);
    CHECK(r.out.find("No space left on device") != std::string::npos);
    CHECK(r.out.find("removed the partial output") != std::string::npos);
    if (format == "csv") CHECK_FALSE(std::filesystem::exists(out + "/FULL_POSE.csv"));
    else CHECK_FALSE(std::filesystem::exists(out));
  }
}

TEST_CASE("log export of a log lcmx record made from a live lcm-gen publisher", "[integration][export]") {
  Session s(125, 40000ms);
  TmpDir d;
  const std::string log = d.file("rec.lcmlog");
  const std::string ch = unique_channel("LIVE", 125);
  const int n = 60;
  auto& rec = s.spawn({LCMX_TOOL, "record", log, "-c", ch, "-q"}, {}, true);
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", std::to_string(n), "--rate", "300",
                      "--subscribers", "1"});
  REQUIRE(pub.expect("PUBLISHED", 20000ms));
  auto recorded = [&] {
    try {
      auto r = el::Reader::open(log);
      el::Event e;
      int k = 0;
      while (r.next(e)) k += e.channel == ch;
      return k;
    } catch (const el::Error&) {
      return 0;
    }
  };
  REQUIRE(wait_until([&] { return recorded() == n; }, 10000ms, 20ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);

  const auto env = std::string("LCMX_TYPES_PATH=") + LCMX_LCMTYPES_DIR;
  const auto r = s.run({LCMX_TOOL, "log", "export", log, "-o", d.file("rec.mcap"), "--json"}, {env});
  INFO(r.out);
  REQUIRE(r.rc == 0);
  CHECK(json_num(json_line(r.out), "exported") == n);
  const auto c = mcap_check(s, d.file("rec.mcap"));
  INFO(c.out.substr(0, 2000));
  REQUIRE(c.rc == 0);
  const auto msgs = c.on(ch);
  REQUIRE(msgs.size() == static_cast<std::size_t>(n));
  for (int i = 0; i < n; ++i) {
    const auto& m = *msgs[static_cast<std::size_t>(i)];
    CHECK(m.schema == "lcmx_examples.pose_t");
    CHECK(m.at("header.seq") == std::to_string(i));
    CHECK(num(m.at("position[0]")) == static_cast<double>(i));  // what the peer publishes
    CHECK(num(m.at("orientation[3]")) == 1.0);
    if (i > 0) CHECK(m.log_time >= msgs[static_cast<std::size_t>(i - 1)]->log_time);
  }

  const auto csv = s.run({LCMX_TOOL, "log", "export", log, "--format", "csv", "-o", d.file("csv"), "--fields",
                          "header.seq,position[0]"},
                         {env});
  REQUIRE(csv.rc == 0);
  std::istringstream in(slurp(d.file("csv") + "/" + ch + ".csv"));
  std::string line;
  REQUIRE(std::getline(in, line));
  CHECK(line == "timestamp_us,header.seq,position[0]");
  for (int i = 0; i < n; ++i) {
    REQUIRE(std::getline(in, line));
    CHECK(line.substr(line.find(',')) == "," + std::to_string(i) + "," + std::to_string(i));
  }
  CHECK_FALSE(std::getline(in, line));
}

TEST_CASE("log export on a terminal (tmux) shows a progress line", "[integration][export][tty]") {
  Session s(126, 30000ms);
  TmpDir d;
  const std::string ch = unique_channel("TTYX", 126);
  const std::string log = d.file("tty.lcmlog");
  {
    auto w = el::Writer::open(log, el::OpenMode::create);
    for (int i = 0; i < 3000; ++i) w.write(kT0 + i * 100, ch, encode(pose(i % 3)));
    w.close();
  }
  const Tmux tmux("lcmxit_x" + std::to_string(::getpid()));
  auto pane = [&] { return tmux.pane("exp"); };
  REQUIRE(tmux.run({"new-session", "-d", "-s", "exp", "-x", "200", "-y", "20",
                std::string(LCMX_TOOL) + " log export " + log + " --types " + LCMX_LCMTYPES_DIR + " -o " +
                    d.file("tty.mcap") + "; echo EXPORT-EXIT=$?; sleep 30"})
              .rc == 0);
  REQUIRE(wait_until([&] { return contains(pane(), "EXPORT-EXIT="); }, 15000ms, 20ms));
  const auto p = pane();
  INFO(p);
  CHECK(contains(p, "EXPORT-EXIT=0"));
  CHECK(contains(p, "exporting " + log + ": 100.0 %  3000 events"));
  CHECK(contains(p, "exported 3000 of 3000 events"));
}

#else
TEST_CASE("lcmx log export tests", "[integration][export]") { WARN("lcmx tool not built (LCMX_BUILD_APPS=OFF)"); }
#endif

// Issue 34 item 6: a string from a log (whoever wrote it chose it) that a spreadsheet would run
// as a formula gets a leading apostrophe; negative numbers stay numbers.
TEST_CASE("log export --format csv: text cells that start like a formula are neutralised, numbers are not",
          "[integration][export][trust]") {
  Session s(161);
  TmpDir d;
  const auto log = d.file("formula.lcmlog");
  const auto ch = unique_channel("FORMULA", 161);
  {
    auto w = el::Writer::open(log, el::OpenMode::create);
    std::int64_t t = kT0;
    for (const std::string text : {"=HYPERLINK(\"http://x\",\"y\")", "+1+1", "-1", "@SUM(A1)", "\tx", "plain, text"}) {
      auto m = prims();
      m.text = text;
      w.write(t++, ch, encode(m));
    }
    w.close();
  }
  const auto dir = d.file("csv");
  const auto r = s.run({LCMX_TOOL, "log", "export", "--types", kTypes, "--format", "csv", log, "-o", dir, "--fields",
                        "i8,b,text"});
  INFO(r.out);
  REQUIRE(r.rc == 0);
  const auto csv = slurp(dir + "/" + ch + ".csv");
  const auto T = [](int i) { return std::to_string(kT0 + i); };
  CHECK(csv == "timestamp_us,i8,b,text\n" + T(0) + ",-128,-2,\"'=HYPERLINK(\"\"http://x\"\",\"\"y\"\")\"\n" + T(1) +
                   ",-128,-2,'+1+1\n" + T(2) + ",-128,-2,'-1\n" + T(3) + ",-128,-2,'@SUM(A1)\n" + T(4) +
                   ",-128,-2,'\tx\n" + T(5) + ",-128,-2,\"plain, text\"\n");
}
