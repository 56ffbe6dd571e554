// `lcmx record` / `lcmx play` beside stock LCM on a host that looks like an ordinary computer
// (issue 9, items 2 and 3): a default route via a LAN interface and no multicast route to lo.
// The lo-routed variants are in test/integration/log_test.cpp.
#include "lcmx/log/eventlog.hpp"
#include "lcmx/test/catch_netns.hpp"
#include "lcmx/test/tmp_dir.hpp"
#include "lcmx_examples/bench_t.hpp"
#include "multihost.hpp"

using namespace lcmx::mh;
namespace el = lcmx::eventlog;

namespace {

struct TmpDir : lcmx::test::TmpDir {
  TmpDir() : lcmx::test::TmpDir("lcmx_mh_logs") {}
};

std::vector<el::Event> read_log(const std::string& path) {
  std::vector<el::Event> out;
  try {
    auto r = el::Reader::open(path);
    el::Event e;
    while (r.next(e)) out.push_back(e);
  } catch (const el::Error&) {
  }
  return out;
}

std::vector<std::int64_t> seqs_of(const std::vector<el::Event>& log, const std::string& channel) {
  std::vector<std::int64_t> out;
  for (const auto& e : log) {
    if (e.channel != channel) continue;
    lcmx_examples::bench_t m;
    if (m.decode(e.data.data(), 0, static_cast<int>(e.data.size())) > 0) out.push_back(m.seq);
  }
  return out;
}

std::vector<std::int64_t> iota(std::int64_t n) {
  std::vector<std::int64_t> v;
  for (std::int64_t i = 0; i < n; ++i) v.push_back(i);
  return v;
}

}  // namespace

TEST_CASE("ordinary computer: lcmx record gets stock liblcm and lcmx shm traffic exactly once, "
          "lcm-logplayer and lcmx play --udp replay it to lcmx and stock subscribers",
          "[multihost][local][log]") {
  LCMX_REQUIRE_NETNS();
  Hosts h(1, 40, Ordinary{});
  TmpDir d;
  const std::string log = d.file("ordinary.lcmlog");
  const auto stock = h.channel("LOG_STOCK"), shm = h.channel("LOG_SHM");
  const int n = 120;
  auto& rec = h.spawn(0, {LCMX_TOOL, "record", log, "-c", "MH_LOG_.*", "--json"}, h.lcmx_env(), true);
  REQUIRE(rec.expect("lcmx record: recording to"));
  auto& lcm = h.lcm_peer(0, {"pub", kLcmDefaultUrl, stock, std::to_string(n), "300", "200", "ST"});
  auto& pub = h.peer(0, {"pub", "--channel", shm, "--type", "bench", "--count", std::to_string(n), "--rate", "300",
                         "--size", "200", "--subscribers", "1", "--id", "SH"});
  REQUIRE(lcm.expect("done", 15000ms) == "done " + std::to_string(n));
  REQUIRE(pub.expect("PUBLISHED", 15000ms));
  REQUIRE(lcmx::it::wait_until(
      [&] {
        const auto l = read_log(log);
        return seqs_of(l, stock).size() >= static_cast<std::size_t>(n) && seqs_of(l, shm).size() >= static_cast<std::size_t>(n);
      },
      10000ms, 20ms));
  rec.signal(SIGINT);
  REQUIRE(rec.wait(10000ms) == 0);
  INFO(rec.text());
  const auto logged = read_log(log);
  CHECK(seqs_of(logged, stock) == iota(n));  // every stock message once, in order
  CHECK(seqs_of(logged, shm) == iota(n));
  CHECK(logged.size() == static_cast<std::size_t>(2 * n));

  // Stock lcm-logplayer -> a typed lcmx subscriber on this host (exactly once).
  auto& sub = h.peer(0, {"sub", "--channel", stock, "--type", "bench", "--expect", std::to_string(n), "--queue-depth",
                         "4096"});
  REQUIRE(sub.expect("READY"));
  const auto played = h.run(0, {LCMX_LCM_LOGPLAYER, "-s", "4", "-e", stock, log}, {"LCM_DEFAULT_URL"}, 30000ms);
  INFO(played.out);
  CHECK(played.rc == 0);
  const auto st = of(sub.read_summaries(15000ms), stock);
  CHECK(st.num("received") == n);
  CHECK(st.num("duplicates") == 0);
  CHECK(st.num("out_of_order") == 0);
  CHECK(st.num("bad_content") == 0);

  // lcmx play --udp -> a stock subscriber on this host.
  auto& stock_sub = h.lcm_peer(0, {"sub", kLcmDefaultUrl, shm, std::to_string(n), "30000"});
  REQUIRE(stock_sub.expect("ready"));
  const auto r = h.run(0, {LCMX_TOOL, "play", log, "-c", shm, "--udp", "--speed", "4", "--delay", "0.2"},
                       h.lcmx_env(), 30000ms);
  INFO(r.out);
  CHECK(r.rc == 0);
  const auto s2 = stock_sub.read_summaries(15000ms);
  REQUIRE(s2.size() == 1);
  CHECK(s2[0].num("received") == n);
  CHECK(s2[0].num("duplicates") == 0);
  CHECK(s2[0].num("bad_content") == 0);
}
