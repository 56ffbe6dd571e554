// Message Bridge across emulated hosts (DESIGN.md "Message Bridge", issue 4 "Tests"): real
// `lcmx bridge` daemons, lcmx_test_peer subscribers and a driven publisher
// (lcmx_bridge_test_pub) in network namespaces joined by two links, "pcie" and "eth". No
// vehicle group: everything that crosses hosts here goes through the bridges, so the veth
// byte counters measure the bridge alone.
#include <sys/stat.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "lcmx/test/netns.hpp"
#include "lcmx/test/watchdog.hpp"
#include "support.hpp"

namespace {

using namespace std::chrono_literals;
using lcmx::it::Child;
using lcmx::it::Clock;
using lcmx::it::ms;
using lcmx::it::Summary;
namespace fs = std::filesystem;

#define BRIDGE_REQUIRE_NETNS()                               \
  do {                                                       \
    std::string why_;                                        \
    if (!lcmx::test::netns_available(&why_)) {              \
      WARN("skipped: no network namespaces here: " << why_); \
      return;                                                \
    }                                                        \
  } while (0)

const char* kHostNames[] = {"chipA", "chipB", "chipC", "chipD"};

struct BridgeOpts {
  std::string channels;  // [[channel]] tables ("" = default channel)
  std::string extra;     // more top-level keys
  bool curve = false;
  std::string own_key = "";                  // key file prefix of this bridge (curve)
  std::map<int, std::string> peer_keys = {};  // host -> key file prefix it expects (curve)
};

// One test's world: hosts (namespaces), links, a temp folder for configs and keys, a
// discovery group of its own, every child killed and shm cleaned on every exit path.
class World {
 public:
  World(int hosts, int index, std::vector<lcmx::test::LinkSpec> links, ms timeout = 40000ms)
      : index_(index),
        watchdog_(timeout, "bridge test " + std::to_string(index)),
        emu_(lcmx::test::Emulation::create({.hosts = hosts, .links = std::move(links)})),
        discovery_url(lcmx::it::unique_url(index)) {
    std::string t = (fs::temp_directory_path() / "lcmx_bridge_test_XXXXXX").string();
    REQUIRE(::mkdtemp(t.data()) != nullptr);
    dir = t;
  }
  World(const World&) = delete;
  World& operator=(const World&) = delete;
  ~World() {
    std::vector<pid_t> pids;
    for (auto& c : children_) pids.push_back(c->started_pid());
    children_.clear();
    for (auto p : pids) lcmx::it::remove_shm_of(p);
    std::error_code ec;
    fs::remove_all(dir, ec);
  }

  lcmx::test::Emulation& emu() { return emu_; }

  std::string channel(const std::string& base) const {
    return "BR_" + base + "_" + std::to_string(::getpid()) + "_" + std::to_string(index_);
  }

  std::vector<std::string> env() const {
    return {"LCMX_DISCOVERY_URL=" + discovery_url, "LCMX_VEHICLE_URL", "LCMX_BEACON_PERIOD_MS=100",
            "LCMX_LEASE_MS=800", "SPDLOG_LEVEL=info"};
  }

  Child& spawn(int host, std::vector<std::string> argv, bool merge_stderr = false) {
    argv.insert(argv.begin(), {LCMX_IP, "netns", "exec", emu_.ns(host)});
    auto c = std::make_unique<Child>(argv, env(), merge_stderr);
    c->set_started();
    children_.push_back(std::move(c));
    return *children_.back();
  }

  // Writes host `host`'s bridge config: peers = `peers` (every link, in the emulation's order).
  std::string write_config(int host, const std::vector<int>& peers, const BridgeOpts& o = {}) {
    std::ostringstream s;
    s << "name = \"" << kHostNames[host] << "\"\nlisten = [";
    for (std::size_t i = 0; i < emu_.links().size(); ++i)
      s << (i ? ", " : "") << "\"" << emu_.address(host, emu_.links()[i].name) << "\"";
    s << "]\ncontrol_port = 7700\nheartbeat_ms = 50\nlink_timeout_ms = 300\nfailback_hold_ms = 600\n"
      << "status_period_ms = 200\n"
      << o.extra << "\n"
      << o.channels << "\n";
    for (int p : peers) {
      s << "[[peer]]\nname = \"" << kHostNames[p] << "\"\nendpoints = [";
      for (std::size_t i = 0; i < emu_.links().size(); ++i)
        s << (i ? ", " : "") << "{ link = \"" << emu_.links()[i].name << "\", address = \""
          << emu_.address(p, emu_.links()[i].name) << "\" }";
      s << "]\n";
      if (o.curve) {
        auto it = o.peer_keys.find(p);
        s << "public_key_file = \"" << (it != o.peer_keys.end() ? it->second : std::string(kHostNames[p])) << ".pub\"\n";
      }
    }
    if (o.curve) {
      const std::string own = o.own_key.empty() ? kHostNames[host] : o.own_key;
      s << "[security]\ncurve = true\nsecret_key_file = \"" << own << ".key\"\npublic_key_file = \"" << own << ".pub\"\n";
    }
    const auto path = dir / (std::string(kHostNames[host]) + ".toml");
    std::ofstream(path) << s.str();
    return path.string();
  }

  // Starts the bridge of `host` and waits for its "ready" line.
  Child& bridge(int host, const std::vector<int>& peers, const BridgeOpts& o = {}) {
    const auto cfg = write_config(host, peers, o);
    Child& b = spawn(host, {LCMX_TOOL, "bridge", "--config", cfg}, true);
    const auto ready = b.expect("bridge " + std::string(kHostNames[host]) + ": ready", 10000ms);
    INFO(b.output());
    REQUIRE(ready);
    return b;
  }

  // A subscriber (lcmx_test_peer sub --type bench) on `host`.
  Child& sub(int host, const std::vector<std::string>& channels, std::vector<std::string> extra = {}) {
    std::vector<std::string> a = {LCMX_TEST_PEER, "sub", "--type", "bench", "--queue-depth", "4096",
                                  "--timeout-ms", "45000"};
    for (const auto& c : channels) a.insert(a.end(), {"--channel", c});
    a.insert(a.end(), extra.begin(), extra.end());
    Child& s = spawn(host, a);
    REQUIRE(s.expect("READY", 10000ms));
    return s;
  }

  // A driven publisher (lcmx_bridge_test_pub) on `host`.
  Child& pub(int host, const std::string& channel, std::size_t size, const std::string& id) {
    Child& p = spawn(host, {LCMX_BRIDGE_PUB, "--channel", channel, "--size", std::to_string(size), "--id", id});
    REQUIRE(p.expect("READY", 10000ms));
    return p;
  }

  void keygen(const std::string& prefix) {
    auto& k = spawn(0, {LCMX_TOOL, "bridge", "keygen", "--out", (dir / prefix).string()}, true);
    REQUIRE(k.wait(10000ms) == 0);
  }

  const int index_;

 private:
  lcmx::test::Watchdog watchdog_;
  lcmx::test::Emulation emu_;

 public:
  const std::string discovery_url;
  fs::path dir;

 private:
  std::vector<std::unique_ptr<Child>> children_;
};


// The latest summary of `channel` from a subscriber ("status").
Summary status_of(Child& sub, const std::string& channel) {
  for (const auto& s : sub.summaries("status", 10000ms))
    if (s.str("channel") == channel) return s;
  FAIL("no summary for " << channel << "\n" << sub.output());
  return {};
}

// Waits until `pred(summary)` holds (deadline); returns the last summary and whether it held.
std::pair<Summary, bool> wait_sub(Child& sub, const std::string& channel, const std::function<bool(const Summary&)>& pred,
                                  ms timeout) {
  const auto deadline = Clock::now() + timeout;
  for (;;) {
    auto s = status_of(sub, channel);
    if (pred(s)) return {s, true};
    if (Clock::now() >= deadline) return {s, false};
    std::this_thread::sleep_for(20ms);  // polling a condition with a deadline
  }
}

std::string pub_cmd(long n, double rate) { return "pub " + std::to_string(n) + " " + std::to_string(rate); }

long long published_total(Child& pub, ms timeout = 20000ms) {
  auto line = pub.expect("PUBLISHED", timeout);
  INFO(pub.output());
  REQUIRE(line);
  return std::stoll(line->substr(10));
}

// Publishes single messages until every subscriber has received one (the whole chain —
// discovery, demand, subscription, republisher, matching — is up); returns messages published.
long long warm_up(Child& pub, std::vector<Child*> subs, const std::string& channel, ms timeout = 15000ms) {
  const auto deadline = Clock::now() + timeout;
  long long sent = 0;
  for (;;) {
    pub.send(pub_cmd(1, 0));
    sent = published_total(pub);
    bool all = true;
    for (auto* s : subs) all = all && status_of(*s, channel).num("received") > 0;
    if (all) return sent;
    if (Clock::now() >= deadline) {
      for (auto* s : subs) UNSCOPED_INFO("subscriber:\n" << s->output());
      FAIL("the bridge chain did not come up within " << timeout.count() << " ms");
    }
    std::this_thread::sleep_for(50ms);  // a new probe message per poll
  }
}

void check_clean(const Summary& s) {
  CHECK(s.num("duplicates") == 0);
  CHECK(s.num("out_of_order") == 0);
  CHECK(s.num("bad_content") == 0);
  CHECK(s.num("decode_errors") == 0);
}

// Two or four subscribers on host B, publisher on host A: every message crosses the link once.
void one_transmission_per_message(int index, int subscribers) {
  BRIDGE_REQUIRE_NETNS();
  World w(2, index, {{.name = "eth"}});
  const auto ch = w.channel("ONCE");
  auto& ba = w.bridge(0, {1});
  auto& bb = w.bridge(1, {0});
  std::vector<Child*> subs;
  for (int i = 0; i < subscribers; ++i) subs.push_back(&w.sub(1, {ch}));
  constexpr std::size_t kSize = 200000;  // large: above the 65000-byte UDP limit
  auto& pub = w.pub(0, ch, kSize, "A");
  const long long warm = warm_up(pub, subs, ch);

  // Let the warm-up traffic drain, then measure N messages.
  // (Probes published before a subscriber matched the bridge's republisher are not delivered.)
  std::vector<long long> before;
  for (auto* s : subs) {
    auto [st, ok] = wait_sub(*s, ch, [&](const Summary& x) { return x.num("last") == warm - 1; }, 5000ms);
    REQUIRE(ok);
    before.push_back(st.num("received"));
  }
  constexpr long kN = 60;
  const auto tx0 = w.emu().tx_bytes(0, "eth");
  const auto t0 = Clock::now();
  pub.send(pub_cmd(kN, 100));
  REQUIRE(published_total(pub) == warm + kN);
  for (std::size_t i = 0; i < subs.size(); ++i) {
    auto* s = subs[i];
    auto [st, ok] = wait_sub(*s, ch, [&](const Summary& x) { return x.num("received") == before[i] + kN; }, 10000ms);
    INFO("subscriber:\n" << s->output() << "\nbridge A:\n" << ba.output() << "\nbridge B:\n" << bb.output());
    REQUIRE(ok);
    check_clean(st);
    CHECK(st.num("last") == warm + kN - 1);
    CHECK(st.str("paths") == "bridge");
  }
  const auto tx = w.emu().tx_bytes(0, "eth") - tx0;
  const double secs = std::chrono::duration<double>(Clock::now() - t0).count();
  // Payload: the LCM encoding of bench_t (8 fingerprint + 8 + 8 + 4 + data) plus the bridge's
  // frames (topic, 16-byte header). Protocol overhead: TCP/IP/Ethernet headers per segment
  // (66 bytes per 1448-byte segment at most, far fewer with segmentation offload), ZMTP
  // framing, heartbeats of both bridges (< 200 bytes every 50 ms per link) and ARP.
  const double payload = static_cast<double>(kN) * (kSize + 28 + ch.size() + 16);
  const double overhead = static_cast<double>(kN) * std::ceil(static_cast<double>(kSize) / 1448.0) * 66.0 +
                          secs * 20 * 2 * 400 + 4096;
  INFO("tx bytes on A's link: " << tx << " for " << kN << " messages of " << kSize << " bytes to " << subscribers
                                << " subscribers: " << tx / static_cast<double>(kN) << " per message, ratio "
                                << tx / payload);
  CHECK(static_cast<double>(tx) >= payload);               // it did cross this link
  CHECK(static_cast<double>(tx) <= 1.01 * payload + overhead);  // once, not once per subscriber
  pub.send("quit");
}

}  // namespace

TEST_CASE("two subscribers on host B cost one transmission per message on the link", "[bridge][multihost]") {
  one_transmission_per_message(1, 2);
}

TEST_CASE("four subscribers on host B cost one transmission per message on the link", "[bridge][multihost]") {
  one_transmission_per_message(2, 4);
}
