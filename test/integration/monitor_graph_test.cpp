// `lcmx monitor` driven on a terminal (tmux: send-keys, capture-pane) and `lcmx graph` against
// live processes: an lcmx publisher over shared memory and a stock liblcm publisher (inside a
// network namespace the test creates, on LCM's default URL), lcmx peers in the root namespace
// (the session's group, iface=lo).
#include <sys/stat.h>

#include <fstream>
#include <iterator>
#include <regex>

#include "support.hpp"

using namespace lcmx::it;

namespace {

std::string slurp(const std::string& p) {
  std::ifstream f(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}

// The screen line (0-based) that contains `w`, or -1.
int line_of(const std::string& screen, const std::string& w) {
  std::istringstream in(screen);
  int i = 0;
  for (std::string l; std::getline(in, l); ++i)
    if (contains(l, w)) return i;
  return -1;
}

std::vector<std::string> lines(const std::string& screen) {
  std::vector<std::string> out;
  std::istringstream in(screen);
  for (std::string l; std::getline(in, l);) out.push_back(l);
  return out;
}

}  // namespace

TEST_CASE("lcmx monitor on a terminal (tmux): shm and stock LCM rows, sort, filter, open a channel, resize, quit",
          "[integration][tools][tty]") {
  Session s(95, 60000ms);
  Netns ns;
  REQUIRE_NETNS_OR_SKIP(ns);
  // Inside the namespace everything uses LCM's default group (no LCMX_DISCOVERY_URL).
  auto in_ns = [&](std::vector<std::string> argv) {
    argv.insert(argv.begin(), {LCMX_IP, "netns", "exec", ns.name()});
    return argv;
  };
  auto& shm_pub = s.spawn(in_ns({LCMX_TEST_PEER, "pub", "--channel", "MON_SHM", "--type", "pose", "--count", "0",
                                 "--rate", "50", "--id", "P", "--timeout-ms", "60000"}),
                          {"LCMX_DISCOVERY_URL"});
  REQUIRE(shm_pub.expect("READY"));
  auto& stock_pub = s.spawn(in_ns({LCMX_LCM_PEER, "pub", kLcmDefaultUrl, "MON_STOCK", "100000", "10", "64", "ST"}));
  REQUIRE(stock_pub.expect("ready"));

  Tmux tmux("lcmxit_mon_" + std::to_string(::getpid()));
  const std::string cmd = std::string(LCMX_IP) + " netns exec " + ns.name() +
                          " env -u LCMX_DISCOVERY_URL LCMX_TYPES_PATH=" + LCMX_LCMTYPES_DIR + " " + LCMX_TOOL +
                          " monitor";
  REQUIRE(tmux.run({"new-session", "-d", "-s", "mon", "-x", "120", "-y", "30",
                    cmd + "; echo MON-EXIT=$?; sleep 30"}).rc == 0);
  // Rows for both publishers: package-qualified types from the type path, publishers, paths.
  const bool rows = tmux.wait_screen("mon", [](const std::string& p) {
    return contains(p, "MON_SHM") && contains(p, "MON_STOCK") && contains(p, "lcmx_examples.pose_t") &&
           contains(p, "lcmx_examples.bench_t") && contains(p, "LCM sender") && contains(p, "lcmx_test_peer[");
  });
  INFO(tmux.pane("mon"));
  REQUIRE(rows);
  {
    const auto p = tmux.pane("mon");
    const auto l = lines(p);
    CHECK(contains(l.at(static_cast<std::size_t>(line_of(p, "MON_SHM"))), " shm "));
    CHECK(contains(l.at(static_cast<std::size_t>(line_of(p, "MON_STOCK"))), " udp "));
    CHECK(contains(p, "q:quit"));  // keys on screen
    CHECK(line_of(p, "MON_SHM") < line_of(p, "MON_STOCK"));  // sorted by channel
  }

  // Sort by Hz (column 5): ascending puts the 10 Hz stock channel first, 'r' reverses.
  REQUIRE(tmux.keys("mon", {"5"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) {
    return contains(p, "sort: Hz") && !contains(p, "(desc)") && line_of(p, "MON_STOCK") >= 0 &&
           line_of(p, "MON_STOCK") < line_of(p, "MON_SHM");
  }));
  REQUIRE(tmux.keys("mon", {"r"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) {
    return contains(p, "sort: Hz (desc)") && line_of(p, "MON_SHM") >= 0 && line_of(p, "MON_SHM") < line_of(p, "MON_STOCK");
  }));

  // Pause and resume.
  REQUIRE(tmux.keys("mon", {"p"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) {
    const auto l = lines(p);
    return !l.empty() && contains(l[0], "PAUSED");
  }));
  REQUIRE(tmux.keys("mon", {"p"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) { return !contains(p, "PAUSED"); }));

  // Filter: only the stock channel is left.
  REQUIRE(tmux.keys("mon", {"/"}));
  REQUIRE(tmux.wait_screen("mon", [](const std::string& p) { return contains(p, "filter (regex"); }));
  REQUIRE(tmux.keys("mon", {"-l", "st.ck"}));
  REQUIRE(tmux.keys("mon", {"Enter"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) {
    return contains(p, "filter: /st.ck/") && contains(p, "MON_STOCK") && !contains(p, "MON_SHM") && contains(p, "1 channels");
  }));

  // Open it: the decoded latest message, live; the byte array folded until Enter on it.
  REQUIRE(tmux.keys("mon", {"Enter"}));
  std::string seq_line;
  const bool opened = tmux.wait_screen("mon", [&](const std::string& p) {
    const int l = line_of(p, "seq: ");
    if (l >= 0) seq_line = lines(p)[static_cast<std::size_t>(l)];
    return contains(p, "lcmx_examples.bench_t") && contains(p, "rate (max") && contains(p, "size: 64") && contains(p, "data: bytes[64]") &&
           l >= 0;
  });
  INFO(tmux.pane("mon"));
  REQUIRE(opened);
  CHECK(tmux.wait_screen("mon", [&](const std::string& p) {  // updated live: seq moves on
    const int l = line_of(p, "seq: ");
    return l >= 0 && lines(p)[static_cast<std::size_t>(l)] != seq_line;
  }));
  CHECK_FALSE(contains(tmux.pane("mon"), "000030:"));
  REQUIRE(tmux.keys("mon", {"End"}));
  REQUIRE(tmux.keys("mon", {"Enter"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) { return contains(p, "000030:") && contains(p, "- data: bytes[64]"); }));

  // Back, resize to 80x24: everything fits, redrawn.
  REQUIRE(tmux.keys("mon", {"Escape"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) { return contains(p, "CHANNEL") && contains(p, "MON_STOCK"); }));
  REQUIRE(tmux.run({"resize-window", "-t", "mon", "-x", "80", "-y", "24"}).rc == 0);
  const bool resized = tmux.wait_screen("mon", [](const std::string& p) {
    const auto l = lines(p);
    return l.size() == 24 && contains(l.front(), "lcmx monitor") && contains(l.back(), "q:quit") && contains(l.back(), "/:filter") &&
           contains(p, "MON_STOCK") && contains(p, "DROPS");
  });
  INFO(tmux.pane("mon"));
  CHECK(resized);
  for (const auto& l : lines(tmux.pane("mon"))) CHECK(l.size() <= 80);
  // Clear the filter: both rows again.
  REQUIRE(tmux.keys("mon", {"/", "BSpace", "BSpace", "BSpace", "BSpace", "BSpace", "Enter"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) {
    return contains(p, "MON_SHM") && contains(p, "MON_STOCK") && !contains(p, "filter: /");
  }));

  // Ctrl-C: clean exit, terminal restored (the shell's echo shows on the normal screen).
  REQUIRE(tmux.keys("mon", {"C-c"}));
  CHECK(tmux.wait_screen("mon", [](const std::string& p) { return contains(p, "MON-EXIT=0"); }));

  // Without a type path: the beacon's type name (no package), the stock channel's fingerprint;
  // opening it shows the raw bytes and says why. q quits.
  const std::string cmd2 = std::string(LCMX_IP) + " netns exec " + ns.name() +
                           " env -u LCMX_DISCOVERY_URL -u LCMX_TYPES_PATH " + LCMX_TOOL + " monitor";
  REQUIRE(tmux.run({"new-session", "-d", "-s", "mon2", "-x", "100", "-y", "20",
                    cmd2 + "; echo MON2-EXIT=$?; sleep 30"}).rc == 0);
  const bool untyped = tmux.wait_screen("mon2", [](const std::string& p) {
    const int shm = line_of(p, "MON_SHM"), stock = line_of(p, "MON_STOCK");
    return shm >= 0 && stock >= 0 && contains(lines(p)[static_cast<std::size_t>(shm)], " pose_t ") &&
           std::regex_search(lines(p)[static_cast<std::size_t>(stock)], std::regex(" 0x[0-9a-f]+"));
  });
  INFO(tmux.pane("mon2"));
  CHECK(untyped);
  REQUIRE(tmux.keys("mon2", {"Down", "Enter"}));
  CHECK(tmux.wait_screen("mon2", [](const std::string& p) {
    return contains(p, "MON_STOCK") && contains(p, "type unknown (fingerprint 0x") && contains(p, "bytes[");
  }));
  REQUIRE(tmux.keys("mon2", {"q"}));
  CHECK(tmux.wait_screen("mon2", [](const std::string& p) { return contains(p, "MON2-EXIT=0"); }));

  const auto once = s.run(in_ns({"env", "LCMX_TYPES_PATH=" LCMX_LCMTYPES_DIR, LCMX_TOOL, "monitor", "--once",
                                 "--json", "--duration", "1.5", "--sort", "hz", "--reverse"}),
                          {"LCMX_DISCOVERY_URL"}, 15000ms);
  INFO(once.out);
  CHECK(once.rc == 0);
  CHECK(std::regex_search(once.out, std::regex(R"(\{"channel":"MON_SHM","type":"lcmx_examples.pose_t","publishers":"lcmx_test_peer\[[0-9]+\]@[0-9a-f]{4}","paths":"shm","hz":[1-9])")));
  CHECK(std::regex_search(once.out, std::regex(R"(\{"channel":"MON_STOCK","type":"lcmx_examples.bench_t","publishers":"LCM sender","paths":"udp","hz":[1-9])")));
  CHECK(once.out.find("MON_SHM") < once.out.find("MON_STOCK"));  // by Hz, descending
}

TEST_CASE("lcmx graph of live processes: DOT with hosts, processes, nodes, topics and pair paths, JSON, SVG/PNG "
          "through dot, --watch rewrites on change",
          "[integration][tools]") {
  Session s(96, 60000ms);
  TmpDir d;
  const std::string ch = unique_channel("GRAPH", 96);
  auto& pub = s.peer({"pub", "--channel", ch, "--type", "pose", "--count", "0", "--rate", "20"});
  REQUIRE(pub.expect("READY"));
  auto& sub = s.peer({"sub", "--channel", ch, "--type", "pose", "--publishers", "1"});
  REQUIRE(sub.expect("MATCHED", 10000ms));
  const std::string pub_proc = "lcmx_test_peer[" + std::to_string(pub.started_pid()) + "]";

  const auto dot = s.run({LCMX_TOOL, "graph"});
  INFO(dot.out);
  REQUIRE(dot.rc == 0);
  CHECK(contains(dot.out, "digraph lcmx {"));
  CHECK(contains(dot.out, "subgraph \"cluster_host_"));
  CHECK(contains(dot.out, "label=\"" + pub_proc + "\""));
  CHECK(contains(dot.out, "label=\"lcmx_test_peer[" + std::to_string(sub.started_pid()) + "]\""));
  CHECK(contains(dot.out, "\"t_" + ch + "\" [shape=ellipse"));
  CHECK(contains(dot.out, "\\npose_t\""));  // lcm-gen's name in beacons: no package
  CHECK(std::regex_search(dot.out, std::regex("\"n_[0-9]+_[a-z_]+\" -> \"t_" + ch + "\";")));
  CHECK(std::regex_search(dot.out, std::regex("\"t_" + ch + "\" -> \"n_[0-9]+_[a-z_]+\" \\[label=\"shm from " +
                                              std::regex_replace(pub_proc, std::regex(R"([\[\]])"), R"(\$&)") + "/")));

  // With the type path: package-qualified (by fingerprint).
  const auto json = s.run({LCMX_TOOL, "graph", "--json", "--types", LCMX_LCMTYPES_DIR});
  INFO(json.out);
  CHECK(json.rc == 0);
  CHECK(contains(json.out, "{\"hosts\":[{\"host\":\""));
  CHECK(contains(json.out, "\"pairs\":[{\"publisher\":\"" + pub_proc + "/"));
  CHECK(contains(json.out, "\"path\":\"shm\""));
  CHECK(contains(json.out, "{\"topic\":\"" + ch + "\",\"types\":[\"lcmx_examples.pose_t\"],\"publishers\":1,\"subscribers\":1}"));

  // Files: DOT by extension; SVG and PNG through Graphviz's dot when it is installed.
  REQUIRE(s.run({LCMX_TOOL, "graph", "-o", d.file("g.dot")}).rc == 0);
  CHECK(contains(slurp(d.file("g.dot")), "\"t_" + ch + "\""));
  if (::access("/usr/bin/dot", X_OK) == 0) {
    const auto svg = s.run({LCMX_TOOL, "graph", "-o", d.file("g.svg")});
    INFO(svg.out);
    REQUIRE(svg.rc == 0);
    const auto text = slurp(d.file("g.svg"));
    CHECK(text.rfind("<?xml", 0) == 0);
    CHECK(contains(text, "<svg"));
    CHECK(contains(text, ch));
    REQUIRE(s.run({LCMX_TOOL, "graph", "--format", "png", "-o", d.file("g.img")}).rc == 0);
    CHECK(slurp(d.file("g.img")).rfind("\x89PNG\r\n", 0) == 0);
  } else {
    WARN("Graphviz's dot not installed: SVG/PNG not checked");
  }
  // An extension that names no format: exit 2, no file (not DOT text under a .jpg name).
  const auto jpg = s.run({LCMX_TOOL, "graph", "-o", d.file("g.jpg")});
  CHECK(jpg.rc == 2);
  CHECK(contains(jpg.out, "no format for '.jpg'"));
  CHECK(::access(d.file("g.jpg").c_str(), F_OK) != 0);
  // Without dot in PATH: a clear error, no file.
  const auto nodot = s.run({LCMX_TOOL, "graph", "-o", d.file("none.svg")}, {"PATH=/nonexistent"});
  CHECK(nodot.rc == 1);
  CHECK(contains(nodot.out, "needs Graphviz's 'dot'"));
  CHECK(::access(d.file("none.svg").c_str(), F_OK) != 0);

  // --watch: a new subscriber on another topic appears in the file, and goes when it leaves.
  const std::string ch2 = ch + "_B";
  const std::string live = d.file("live.dot");
  auto& watch = s.spawn({LCMX_TOOL, "graph", "--watch", "-o", live}, {}, true);
  REQUIRE(watch.expect("lcmx graph: wrote", 10000ms));
  CHECK(contains(slurp(live), "\"t_" + ch + "\""));
  CHECK_FALSE(contains(slurp(live), ch2));
  auto& sub2 = s.peer({"sub", "--channel", ch2, "--type", "pose"});
  REQUIRE(sub2.expect("READY"));
  CHECK(wait_until([&] { return contains(slurp(live), "\"t_" + ch2 + "\""); }, 10000ms, 50ms));
  sub2.send("quit");
  CHECK(sub2.wait(10000ms) == 0);
  CHECK(wait_until([&] { return !contains(slurp(live), ch2); }, 10000ms, 50ms));
  watch.signal(SIGINT);
  CHECK(watch.wait(10000ms) == 0);
  const std::string log = watch.text();
  std::size_t writes = 0;
  for (auto at = log.find("wrote"); at != std::string::npos; at = log.find("wrote", at + 1)) ++writes;
  CHECK(writes >= 3);  // first, with the new subscriber, without it
}

TEST_CASE("lcmx monitor / graph: --help, and clear errors for bad input", "[integration][tools][cli]") {
  Session s(97, 30000ms);
  for (const std::string verb : {"monitor", "graph"}) {
    const auto r = s.run({LCMX_TOOL, verb, "--help"});
    INFO(r.out);
    CHECK(r.rc == 0);
    CHECK(contains(r.out, verb + " [OPTIONS]"));
    CHECK(contains(r.out, "--json"));
  }
  const auto notty = s.run({LCMX_TOOL, "monitor"});
  CHECK(notty.rc == 2);
  CHECK(contains(notty.out, "needs a terminal"));
  const auto filter = s.run({LCMX_TOOL, "monitor", "--once", "--filter", "(unclosed"});
  CHECK(filter.rc == 2);
  CHECK(contains(filter.out, "bad --filter expression"));
  const auto sort = s.run({LCMX_TOOL, "monitor", "--once", "--sort", "colour"});
  CHECK(sort.rc == 2);
  CHECK(contains(sort.out, "unknown --sort column 'colour'"));
  const auto types = s.run({LCMX_TOOL, "monitor", "--once", "--types", "/nonexistent/dir"});
  CHECK(types.rc == 2);
  CHECK(contains(types.out, "/nonexistent/dir"));
  const auto watch = s.run({LCMX_TOOL, "graph", "--watch"});
  CHECK(watch.rc == 2);
  CHECK(contains(watch.out, "--watch rewrites a file"));
  const auto svg = s.run({LCMX_TOOL, "graph", "--format", "svg"});
  CHECK(svg.rc == 2);
  CHECK(contains(svg.out, "needs -o FILE"));
}
