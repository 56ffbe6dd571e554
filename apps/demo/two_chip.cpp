// lcmx-demo, two-chip mode: the paper's set-up on one machine.
//
//   chip A (namespace)                                   chip B (namespace)
//   chip-a: camera 6 MB @10 Hz, pose @100 Hz            cam_b1, cam_b2: camera subscribers
//   cam_a : camera subscriber (shm)                     pose_b: pose subscriber
//   lcmx bridge  ──── pcie (4 Gbit/s, preferred) ────   lcmx bridge
//                ──── eth  (1 Gbit/s)             ────
//
// The camera is a large topic: A's bridge reads it from A's shared memory and sends each image
// once over the active link; B's bridge republishes it into B's shared memory, where both
// camera subscribers read it. The pose is small: LCM UDP multicast on the vehicle group (eth).
// A third of the way in the pcie link goes down (the bridges fail over to eth), two thirds
// in it comes back (they fail back). The demo prints, per phase, the bytes each link carried,
// the camera images each subscriber on B missed (its losses given to the phase its next image
// was published in) and what the bridges counted of them (`lcmx bridge status --json` on both
// chips at each phase's start: B's `lost` in flight, A's `drops` and `lost_local`); then the
// bytes per image and the subscriber table. A failover loses what was in flight on pcie, all
// counted; a fail-back loses nothing (issue 37).
#include "demo.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <future>
#include <iostream>
#include <map>
#include <optional>
#include <sstream>
#include <thread>

#ifdef LCMX_DEMO_TWO_CHIP
#include "lcmx/test/netns.hpp"
#endif

namespace lcmx_demo {

#ifndef LCMX_DEMO_TWO_CHIP
bool two_chip_available(std::string* why) {
  if (why) *why = "built without the network-namespace helper (LCMX_BUILD_TESTS=OFF)";
  return false;
}
int run_two_chip(const char*, double, int, int, double) {
  std::cerr << "lcmx-demo: two-chip mode was not built (needs LCMX_BUILD_TESTS=ON)\n";
  return 1;
}
#else

namespace {

using namespace std::chrono_literals;
namespace fs = std::filesystem;
using lcmx::test::Child;
using lcmx::test::Emulation;

constexpr const char* kEthRate = "1gbit";
constexpr const char* kPcieRate = "4gbit";  // pcie is 4x eth

// A bridge config for `self` (index 0 or 1) with the other chip as its only peer: pcie first.
std::string bridge_config(const Emulation& emu, int self) {
  const int peer = 1 - self;
  const char* names[] = {"chipA", "chipB"};
  std::string c;
  c += "# written by lcmx-demo (two-chip mode)\n";
  c += "name = \"" + std::string(names[self]) + "\"\n";
  c += "listen = [\"" + emu.address(self, "pcie") + "\", \"" + emu.address(self, "eth") + "\"]\n";
  c += "control_port = 7700\nheartbeat_ms = 100\nlink_timeout_ms = 500\nfailback_hold_ms = 1000\n";
  c += "\n[[channel]]\nname = \"control\"\nport = 7701\npriority = 1\nhwm = 100\ndrop = \"oldest\"\n"
       "topics = [\"DEMO_POSE*\"]\n";
  c += "\n[[channel]]\nname = \"bulk\"\nport = 7702\npriority = 0\nhwm = 4\ndrop = \"oldest\"\n"
       "topics = [\"*\"]\n";
  c += "\n[[peer]]\nname = \"" + std::string(names[peer]) + "\"\nendpoints = [ { link = \"pcie\", address = \"" +
       emu.address(peer, "pcie") + "\" }, { link = \"eth\", address = \"" + emu.address(peer, "eth") + "\" } ]\n";
  return c;
}

struct Bytes {
  std::uint64_t pcie = 0, eth = 0;
};
Bytes sent_by_a(const Emulation& emu) { return {emu.tx_bytes(0, "pcie"), emu.tx_bytes(0, "eth")}; }

std::string mb(std::uint64_t bytes) {
  char b[32];
  std::snprintf(b, sizeof b, "%.1f", static_cast<double>(bytes) / 1e6);
  return b;
}

// What the bridges counted so far of the camera's losses to chip B: B's `lost` (in transit) and
// A's `drops` (its queue to B) and `lost_local` (never read from A's shared memory), from
// `lcmx bridge status --json` on each chip. -1 each when a status could not be read.
struct Counted {
  long long lost = -1, drops = -1, lost_local = -1;
};
long long json_sum(const std::string& text, const std::string& key) {
  long long n = 0;
  const std::string k = "\"" + key + "\":";
  for (auto at = text.find(k); at != std::string::npos; at = text.find(k, at + 1))
    n += std::strtoll(text.c_str() + at + k.size(), nullptr, 10);
  return n;
}
std::string status_json(const Emulation& emu, const std::string& lcmx, int host) {
  try {
    auto status = emu.spawn(host, {lcmx, "bridge", "status", "--json", "--wait", "1500"});
    std::string text;
    while (auto line = status.read_line(5s)) text += *line;
    return status.wait(2s) == 0 ? text : std::string();
  } catch (const std::exception&) {
    return {};
  }
}
Counted counted(const Emulation& emu, const std::string& lcmx) {
  // Both chips at once: each `lcmx bridge status` takes about a second (discovery, then 300 ms
  // for other daemons), and the phases wait for it.
  auto on_a = std::async(std::launch::async, [&] { return status_json(emu, lcmx, 0); });
  const std::string b = status_json(emu, lcmx, 1), a = on_a.get();
  if (a.empty() || b.empty()) return {};
  return {json_sum(b, "lost"), json_sum(a, "drops"), json_sum(a, "lost_local")};
}

// Runs `lcmx bridge status` on chip B and prints what it says (indented).
void show_status(const Emulation& emu, const std::string& lcmx) {
  try {
    auto status = emu.spawn(1, {lcmx, "bridge", "status", "--wait", "1500"});
    while (auto line = status.read_line(5s)) std::cout << "    " << *line << "\n";
    status.wait(2s);
  } catch (const std::exception& e) {
    std::cout << "    (lcmx bridge status failed: " << e.what() << ")\n";
  }
}

}  // namespace

bool two_chip_available(std::string* why) { return lcmx::test::netns_available(why); }

int run_two_chip(const char* self, double seconds, int width, int height, double cam_hz) {
  const fs::path dir = fs::path(self).parent_path();
  const std::string lcmx = (dir / "lcmx").string();
  if (!fs::exists(lcmx)) throw std::runtime_error("cannot find the lcmx tool next to lcmx-demo: " + lcmx);

  std::cerr << "lcmx-demo: creating two emulated chips (eth " << kEthRate << ", pcie " << kPcieRate << ")\n";
  lcmx::test::LinkSpec eth, pcie;
  eth.name = "eth", eth.rate = kEthRate;  // first link: the vehicle LAN (multicast route)
  pcie.name = "pcie", pcie.rate = kPcieRate;
  auto emu = Emulation::create({.hosts = 2, .links = {eth, pcie}});
  char tmpl[] = "/tmp/lcmx-demo-XXXXXX";
  if (!::mkdtemp(tmpl)) throw std::runtime_error("mkdtemp failed");
  const fs::path tmp = tmpl;
  struct RemoveDir {
    fs::path p;
    ~RemoveDir() {
      std::error_code ec;
      fs::remove_all(p, ec);
    }
  } remove_tmp{tmp};
  std::vector<std::string> configs;
  for (int h = 0; h < 2; ++h) {
    configs.push_back((tmp / (h == 0 ? "chipA.toml" : "chipB.toml")).string());
    std::ofstream(configs.back()) << bridge_config(emu, h);
  }

  // Inside the namespaces LCM's default host-local group is private to each chip. The pose
  // crosses on the vehicle group, pinned to eth.
  const lcmx::test::Env env = {{"LCMX_VEHICLE_URL", "udpm://239.255.76.68:7668?ttl=1&iface=eth"},
                               {"LCMX_BEACON_PERIOD_MS", "200"}, {"LCMX_LEASE_MS", "1500"}};
  const lcmx::test::Env bridge_env = {{"LCMX_BEACON_PERIOD_MS", "200"}, {"LCMX_LEASE_MS", "1500"}};
  std::vector<Child> bridges;
  for (int h = 0; h < 2; ++h) bridges.push_back(emu.spawn(h, {lcmx, "bridge", "--config", configs[h]}, bridge_env));

  // Chip A publishes a little longer than the three phases of seconds/3: between them the demo
  // asks the bridges for their counts (a few seconds), and the link changes only after that, so
  // each phase's bytes and losses are those between two link changes.
  const double publish_s = seconds + 4;
  const int timeout_s = static_cast<int>(publish_s) + 60;
  struct Sub {
    int host;
    std::string name, topics;
  };
  const std::vector<Sub> subs = {{0, "cam_a", "camera"}, {1, "cam_b1", "camera"}, {1, "cam_b2", "camera"},
                                 {1, "pose_b", "pose"}};
  std::vector<Child> sub_procs;
  for (const auto& s : subs) {
    sub_procs.push_back(emu.spawn(s.host, {self, "--role", "sub", "--name", s.name, "--topics", s.topics,
                                           "--timeout", std::to_string(timeout_s)},
                                  env));
    if (!sub_procs.back().expect("READY", 20s)) throw std::runtime_error("subscriber " + s.name + " did not start");
  }
  auto pub = emu.spawn(0, {self, "--role", "chip-a", "--seconds", std::to_string(publish_s), "--width",
                           std::to_string(width), "--height", std::to_string(height), "--camera-hz",
                           std::to_string(cam_hz)},
                       env);
  if (!pub.expect("PUBLISHING", 20s)) throw std::runtime_error("chip A's publisher did not start");
  const double image_mb = width * height * 3 / 1e6;
  std::cerr << "lcmx-demo: chip A publishes " << width << "x" << height << " rgb8 (" << image_mb << " MB) at "
            << cam_hz << " Hz and poses at 100 Hz for " << publish_s << " s\n";

  // Phases: pcie up, pcie down (failover to eth), pcie up again (fail-back).
  using Clock = std::chrono::steady_clock;
  const auto start = Clock::now();
  const auto third = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds / 3));
  struct Phase {
    const char* what;
    Bytes before, after;
  };
  // Each phase's start and the run's end (CLOCK_MONOTONIC, the subscribers' clock too: their
  // losses are given to the phase their next image was published in) and what the bridges had
  // counted then.
  std::vector<Phase> phases = {{"pcie up", {}, {}}, {"pcie DOWN", {}, {}}, {"pcie up again", {}, {}}};
  phases[0].before = sent_by_a(emu);
  std::int64_t phase_start[4] = {now_ns(), 0, 0, 0};
  Counted count_at[4];
  // The bridges count from when chip B's bridge has republished an image (the chain is up):
  // what A's queue dropped before is no phase's (the subscribers on B had received nothing).
  while (Clock::now() < start + third / 2) {
    if (json_sum(status_json(emu, lcmx, 1), "messages_received") > 0) break;
  }
  count_at[0] = counted(emu, lcmx);
  // Each phase: its bytes and losses from one link change to the next. The counts are asked for
  // at the end of a phase, before its link change (what they take is the phase's steady state).
  std::this_thread::sleep_until(start + third);  // pacing, not synchronisation
  count_at[1] = counted(emu, lcmx);
  phases[0].after = phases[1].before = sent_by_a(emu);
  std::cerr << "lcmx-demo: taking the pcie link of chip A down\n";
  phase_start[1] = now_ns();
  const auto down_at = Clock::now();
  emu.set_link_up(0, "pcie", false);
  std::this_thread::sleep_until(down_at + third);
  std::cout << "\nbridge status on chip B while pcie is down:\n";
  show_status(emu, lcmx);
  count_at[2] = counted(emu, lcmx);
  phases[1].after = phases[2].before = sent_by_a(emu);
  std::cerr << "lcmx-demo: pcie link of chip A up again\n";
  phase_start[2] = now_ns();
  emu.set_link_up(0, "pcie", true);
  const auto done = pub.expect("DONE", std::chrono::milliseconds(static_cast<int>(publish_s * 1000)) + 30s);
  phases[2].after = sent_by_a(emu);
  phase_start[3] = now_ns();
  if (!done) throw std::runtime_error("chip A's publisher did not finish");
  unsigned long long cams = 0, poses = 0;
  std::sscanf(done->c_str(), "DONE %llu %llu", &cams, &poses);
  std::cout << "\nbridge status on chip B after fail-back:\n";
  show_status(emu, lcmx);

  // The tail of the camera stream is still crossing: give it a moment, then stop everyone.
  std::this_thread::sleep_for(500ms);  // pacing, not synchronisation
  count_at[3] = counted(emu, lcmx);
  std::vector<std::string> lines;
  // Camera images each subscriber on B missed, per phase (from its GAPS line).
  std::map<std::string, std::array<unsigned long long, 3>> lost_in;
  bool ok = true;
  for (auto& p : sub_procs) {
    p.kill(SIGTERM);
    while (auto line = p.read_line(10s)) {
      if (line->rfind("RESULT", 0) == 0) lines.push_back(*line);
      if (line->rfind("GAPS ", 0) == 0) {
        std::istringstream in(line->substr(5));
        std::string who, topic, list;
        in >> who >> topic >> list;
        auto& per = lost_in[who];
        per = {0, 0, 0};
        std::istringstream items(list == "-" ? std::string() : list);
        for (std::string item; std::getline(items, item, ',');) {
          const auto colon = item.find(':');
          if (colon == std::string::npos) continue;
          const long long stamp = std::strtoll(item.c_str(), nullptr, 10);
          const unsigned long long n = std::strtoull(item.c_str() + colon + 1, nullptr, 10);
          for (int ph = 2; ph >= 0; --ph)
            if (stamp >= phase_start[ph]) {
              per[static_cast<std::size_t>(ph)] += n;
              break;
            }
        }
      }
      if (*line == "END") break;
    }
    if (p.wait(10s) != 0) ok = false;
  }
  for (auto& b : bridges) b.kill(SIGTERM);
  for (auto& b : bridges)
    if (!b.wait(10s)) b.kill(SIGKILL);

  std::printf("\nlcmx demo (two chips): %.0f s, camera %dx%d rgb8 (%.1f MB) at %.0f Hz, pose at 100 Hz\n",
              publish_s, width, height, image_mb, cam_hz);
  std::printf("published on chip A: camera %llu, pose %llu\n\n", cams, poses);
  std::printf("bytes chip A sent per link (all traffic: images, poses, beacons, heartbeats), and the camera\n"
              "images the subscribers on chip B missed in each phase (a failover loses what was in flight on\n"
              "the dead link, and what A's queue drops until eth carries the traffic: all counted by the\n"
              "bridges; a fail-back loses nothing):\n\n");
  std::printf("| %-14s | %6s | %10s | %10s | %13s | %13s | %18s |\n", "phase", "s", "pcie MB", "eth MB",
              "lost cam_b1", "lost cam_b2", "counted (bridges)");
  std::printf("|----------------|--------|------------|------------|---------------|---------------|--------------------|\n");
  std::uint64_t total = 0;
  for (std::size_t i = 0; i < phases.size(); ++i) {
    const auto& ph = phases[i];
    const auto p = ph.after.pcie - ph.before.pcie, e = ph.after.eth - ph.before.eth;
    total += p + e;
    auto lost = [&](const char* who) {
      const auto it = lost_in.find(who);
      return it == lost_in.end() ? std::string("?") : std::to_string(it->second[i]);
    };
    const Counted &c0 = count_at[i], &c1 = count_at[i + 1];
    std::string counted_text = "?";
    if (c0.lost >= 0 && c1.lost >= 0) {
      const long long lost_b = c1.lost - c0.lost, drops = c1.drops - c0.drops, never = c1.lost_local - c0.lost_local;
      counted_text = std::to_string(lost_b + drops + never) + " (" + std::to_string(lost_b) + " in flight)";
    }
    const double secs = static_cast<double>(phase_start[i + 1] - phase_start[i]) / 1e9;
    std::printf("| %-14s | %6.1f | %10s | %10s | %13s | %13s | %18s |\n", ph.what, secs, mb(p).c_str(),
                mb(e).c_str(), lost("cam_b1").c_str(), lost("cam_b2").c_str(), counted_text.c_str());
  }
  // Images chip B received (cam_b1's count; cam_b2 got the same ones from the same slot).
  unsigned long long on_b = 0;
  for (const auto& l : lines)
    if (l.rfind("RESULT cam_b1 ", 0) == 0) std::sscanf(l.c_str(), "RESULT %*s %*s %*s %llu", &on_b);
  const double per_image = on_b ? static_cast<double>(total) / static_cast<double>(on_b) / 1e6 : 0;
  std::printf("\nper camera image received on chip B: %.2f MB sent on the links = %.3fx one image (%.2f MB)\n"
              "for two camera subscribers there: one transmission per image.\n\n",
              per_image, image_mb > 0 ? per_image / image_mb : 0, image_mb);
  if (on_b == 0) ok = false;
  if (!print_results(lines)) ok = false;
  return ok ? 0 : 1;
}

#endif

}  // namespace lcmx_demo
