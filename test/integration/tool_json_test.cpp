// Issue 11 item 8: `lcmx topics` / `lcmx nodes` name types with their package when the type
// path (--types / LCMX_TYPES_PATH) holds their fingerprint, and the tool's commands print JSON
// for scripts (--json), parsed here by Debian's python3 (an independent JSON parser).
#include <sys/stat.h>

#include <fstream>
#include <iterator>

#include "support.hpp"

using namespace lcmx::it;

#ifdef LCMX_TOOL

namespace {

// The first line of `out` that starts with '{'.
std::string first_json(const std::string& out) {
  std::istringstream in(out);
  for (std::string l; std::getline(in, l);)
    if (!l.empty() && l[0] == '{') return l;
  return "";
}

// Parses `json` with python3's json module and prints the Python expression `expr` over it
// (`d` is the document); the printed value, without the newline. FAILs if it does not parse.
std::string py(Session& s, const TmpDir& d, const std::string& json, const std::string& expr) {
  const auto f = d.file("doc.json");
  std::ofstream(f) << json;
  const auto r = s.run({LCMX_PYTHON3, "-c", "import json,sys; d=json.load(open(sys.argv[1])); print(" + expr + ")", f},
                       {"PYTHONIOENCODING=utf-8"});
  if (r.rc != 0) FAIL("python3 could not evaluate " << expr << " on:\n" << json << "\n" << r.out);
  auto out = r.out;
  while (!out.empty() && out.back() == '\n') out.pop_back();
  return out;
}

}  // namespace

TEST_CASE("lcmx topics and nodes: package-qualified type names from the type path, and --json", "[integration][cli]") {
  Session s(123);
  TmpDir d;
  const auto ch = unique_channel("QUAL", 123);
  const auto raw = unique_channel("RAWCH", 123);
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "50", "--node", "camera",
                      "--subscribers", "1"});
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose", "--node", "viewer", "--publishers", "1"});
  REQUIRE(pub.expect("MATCHED"));
  REQUIRE(sub.expect("MATCHED"));

  // Without a type path: lcm-gen's name (no package), as before.
  const auto plain = s.run({LCMX_TOOL, "--url", s.url, "topics"}, {"LCMX_TYPES_PATH"});
  INFO(plain.out);
  CHECK(plain.rc == 0);
  CHECK(contains(plain.out, ch + "  [pose_t]  1 publisher(s), 1 subscriber(s)"));

  // --types: the package-qualified name, found by fingerprint.
  const auto topics = s.run({LCMX_TOOL, "--url", s.url, "topics", "--types", LCMX_LCMTYPES_DIR}, {"LCMX_TYPES_PATH"});
  INFO(topics.out);
  CHECK(topics.rc == 0);
  CHECK(contains(topics.out, ch + "  [lcmx_examples.pose_t]  1 publisher(s), 1 subscriber(s)"));
  // LCMX_TYPES_PATH does the same for nodes.
  const auto nodes = s.run({LCMX_TOOL, "--url", s.url, "nodes"}, {std::string("LCMX_TYPES_PATH=") + LCMX_LCMTYPES_DIR});
  INFO(nodes.out);
  CHECK(nodes.rc == 0);
  CHECK(contains(nodes.out, "pub " + ch + "  [lcmx_examples.pose_t]"));
  CHECK(contains(nodes.out, "sub " + ch + "  [lcmx_examples.pose_t]"));
  // A type path without the type: lcm-gen's name again.
  std::ofstream(d.file("other.lcm")) << "package elsewhere;\nstruct thing_t { int32_t x; }\n";
  const auto other = s.run({LCMX_TOOL, "--url", s.url, "topics", "--types", d.file("other.lcm")});
  CHECK(contains(other.out, ch + "  [pose_t]"));
  // An explicit --types that does not load is an error; a broken LCMX_TYPES_PATH a warning.
  std::ofstream(d.file("bad.lcm")) << "package p;\nstruct s_t { int32_t x }\n";
  const auto bad = s.run({LCMX_TOOL, "--url", s.url, "topics", "--types", d.file("bad.lcm")});
  CHECK(bad.rc == 2);
  CHECK(contains(bad.out, "lcmx topics: --types: " + d.file("bad.lcm") + ":"));
  const auto warn = s.run({LCMX_TOOL, "--url", s.url, "topics"}, {"LCMX_TYPES_PATH=" + d.file("bad.lcm")});
  CHECK(warn.rc == 0);
  CHECK(contains(warn.out, "warning: LCMX_TYPES_PATH"));
  CHECK(contains(warn.out, ch + "  [pose_t]"));

  // --json: one document, parsed by python.
  const auto tj = s.run({LCMX_TOOL, "--url", s.url, "topics", "--json", "--types", LCMX_LCMTYPES_DIR});
  REQUIRE(tj.rc == 0);
  const auto tdoc = first_json(tj.out);
  INFO(tdoc);
  const std::string t = "[t for t in d['topics'] if t['topic']=='" + ch + "'][0]";
  CHECK(py(s, d, tdoc, t + "['types']") == "['lcmx_examples.pose_t']");
  CHECK(py(s, d, tdoc, t + "['conflict']") == "False");
  CHECK(py(s, d, tdoc, t + "['publishers'][0]['pid']") == std::to_string(pub.pid()));
  CHECK(py(s, d, tdoc, t + "['publishers'][0]['node']") == "camera");
  CHECK(py(s, d, tdoc, t + "['publishers'][0]['type']") == "lcmx_examples.pose_t");
  CHECK(py(s, d, tdoc, t + "['publishers'][0]['type_name']") == "pose_t");
  CHECK(py(s, d, tdoc, t + "['publishers'][0]['fingerprint'].startswith('0x')") == "True");
  CHECK(py(s, d, tdoc, t + "['subscribers'][0]['pid']") == std::to_string(sub.pid()));
  CHECK(py(s, d, tdoc, t + "['subscribers'][0]['matches'][0]['path']") == "shm");
  CHECK(py(s, d, tdoc, t + "['subscribers'][0]['matches'][0]['publisher']") ==
        "lcmx_test_peer[" + std::to_string(pub.pid()) + "]/camera");

  const auto nj = s.run({LCMX_TOOL, "--url", s.url, "nodes", "--json"}, {std::string("LCMX_TYPES_PATH=") + LCMX_LCMTYPES_DIR});
  REQUIRE(nj.rc == 0);
  const auto ndoc = first_json(nj.out);
  INFO(ndoc);
  const std::string p = "[p for p in d['participants'] if p['pid']==" + std::to_string(sub.pid()) + "][0]";
  CHECK(py(s, d, ndoc, p + "['process']") == "lcmx_test_peer");
  CHECK(py(s, d, ndoc, p + "['scope']") == "host");
  CHECK(py(s, d, ndoc, "[n['name'] for n in " + p + "['nodes']]") == "['viewer']");
  CHECK(py(s, d, ndoc, p + "['nodes'][0]['endpoints'][0]['kind']") == "sub");
  CHECK(py(s, d, ndoc, p + "['nodes'][0]['endpoints'][0]['topic']") == ch);
  CHECK(py(s, d, ndoc, p + "['nodes'][0]['endpoints'][0]['type']") == "lcmx_examples.pose_t");
  CHECK(py(s, d, ndoc, "type(" + p + "['nodes'][0]['endpoints'][0]['drops']).__name__") == "int");
}

TEST_CASE("lcmx bridge with --json: --check, keygen and status of a live bridge", "[integration][cli]") {
  Session s(124, 30000ms);
  TmpDir d;
  const int port = 21000 + static_cast<int>(::getpid() % 20000) * 2;
  const std::string name = "b" + std::to_string(::getpid());
  std::ofstream(d.file("good.toml")) << "name = \"" << name << "\"\nlisten = [\"127.0.0.1\"]\ncontrol_port = " << port
                                      << "\n";
  std::ofstream(d.file("bad.toml")) << "name = \"a\"\nlisten = [\"127.0.0.1\"]\ncontrol_port = 7700\n[[channel]]\n"
                                       "name = \"c\"\nport = 7701\ndrop = \"sometimes\"\n";
  const auto good = s.run({LCMX_TOOL, "bridge", "--config", d.file("good.toml"), "--check", "--json"}, {"LCMX_VEHICLE_URL"});
  CHECK(good.rc == 0);
  const auto gdoc = first_json(good.out);
  // The same facts as the text verdict ("...: ok: bridge NAME, N channel(s), M peer(s)").
  const auto text = s.run({LCMX_TOOL, "bridge", "--config", d.file("good.toml"), "--check"}, {"LCMX_VEHICLE_URL"});
  CHECK(contains(text.out, ": ok: bridge " + name + ", " + py(s, d, gdoc, "d['channels']") + " channel(s), " +
                               py(s, d, gdoc, "d['peers']") + " peer(s)\n"));
  CHECK(py(s, d, gdoc, "(d['ok'], d['name'], d['curve'])") == "(True, '" + name + "', False)");
  const auto bad = s.run({LCMX_TOOL, "bridge", "--config", d.file("bad.toml"), "--check", "--json"}, {"LCMX_VEHICLE_URL"});
  CHECK(bad.rc == 2);
  CHECK(py(s, d, first_json(bad.out), "d['ok']") == "False");
  CHECK(py(s, d, first_json(bad.out), "'channel[0].drop' in d['error']") == "True");

  const auto key = s.run({LCMX_TOOL, "bridge", "keygen", "--out", d.file("k"), "--json"});
  CHECK(key.rc == 0);
  const auto kdoc = first_json(key.out);
  CHECK(py(s, d, kdoc, "d['secret_file']") == d.file("k.key"));
  std::ifstream pubf(d.file("k.pub"));
  const std::string pubkey{std::istreambuf_iterator<char>(pubf), std::istreambuf_iterator<char>()};
  const auto key_json = py(s, d, kdoc, "d['public_key']");
  CHECK(key_json.size() == 40);  // Z85 CURVE key
  CHECK(contains(pubkey, key_json));

  // No bridge: an empty list and exit 1.
  const auto none = s.run({LCMX_TOOL, "bridge", "status", "--url", s.url, "--wait", "100", "--json"}, {"LCMX_VEHICLE_URL"});
  CHECK(none.rc == 1);
  CHECK(py(s, d, first_json(none.out), "d['bridges']") == "[]");

  auto& bridge = s.spawn({LCMX_TOOL, "bridge", "--config", d.file("good.toml")}, {"LCMX_VEHICLE_URL", "SPDLOG_LEVEL=info"});
  REQUIRE(bridge.expect("bridge " + name + ": ready"));
  const auto st = s.run({LCMX_TOOL, "bridge", "status", "--url", s.url, "--wait", "10000", "--json"}, {"LCMX_VEHICLE_URL"});
  INFO(st.out);
  CHECK(st.rc == 0);
  const auto sdoc = first_json(st.out);
  CHECK(py(s, d, sdoc, "[b['name'] for b in d['bridges']]") == "['" + name + "']");
  CHECK(py(s, d, sdoc, "d['bridges'][0]['pid']") == std::to_string(bridge.pid()));
  CHECK(py(s, d, sdoc, "(d['bridges'][0]['curve'], d['bridges'][0]['peers'], d['bridges'][0]['bad_frames'])") ==
        "(False, [], 0)");
  bridge.signal(SIGTERM);
  CHECK(bridge.wait(10000ms) == 0);
  // Its stdout carries the ready line and nothing else: the log ("listening on", "stopping")
  // goes to stderr.
  CHECK(bridge.text() == "bridge " + name + ": ready\n");
}

#endif
