// Fixture of the multi-host tests: emulated hosts (lcmx::test::Emulation: one network namespace
// per host, joined by a bridge on link "eth"), real processes started inside them, a vehicle
// group and a host-local discovery group unique to the test, a watchdog, and cleanup of every
// child and shared-memory segment on every exit path.
//
// Children run through `ip netns exec <host ns>` with lcmx::it::Child (test/integration): unlike
// Emulation::spawn, whose children read /dev/null, it gives them a stdin pipe, which
// lcmx_test_peer needs ("status", "quit"; EOF = quit). If the test process dies, the pipes close
// and every peer exits by itself; the Emulation's destructor kills whatever is left inside the
// namespaces.
#pragma once

#include <algorithm>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "host_registries.hpp"
#include "lcmx/test/netns.hpp"
#include "lcmx/test/watchdog.hpp"
#include "support.hpp"

namespace lcmx::mh {

using namespace std::chrono_literals;
using it::Child;
using it::Clock;
using it::ms;
using it::Summary;
using it::of;
using it::poll_sub;
using it::published;
using it::json_num;
using it::json_until;

// "udpm://239.<a>.<b>.<c>:<port>?ttl=1&iface=eth": unique per (test process, test index) and
// in a range of its own (the host-local groups use 239.255.x.y).
inline std::string unique_vehicle_url(int index, const std::string& iface) {
  // index < 256, as unique_url's.
  if (index < 0 || index >= 256) throw std::invalid_argument("unique_vehicle_url: test index out of [0, 256)");
  const unsigned h = static_cast<unsigned>(::getpid()) * 256u + static_cast<unsigned>(index);
  const unsigned a = 1 + (h / 250u) % 250u, b = 1 + h % 250u;
  const unsigned port = 20000 + (h * 7u + 13u) % 40000u;
  return "udpm://239.254." + std::to_string(a) + "." + std::to_string(b) + ":" + std::to_string(port) +
         "?ttl=1&iface=" + iface;
}

// The same group as liblcm 1.3.1 spells it (no interface: the host's 224.0.0.0/4 route, which
// the Emulation points at the first link).
inline std::string without_iface(const std::string& url) {
  const auto p = url.find("&iface=");
  return p == std::string::npos ? url : url.substr(0, p);
}

// LCM's default URL (liblcm's and lcmx's default host-local group).
inline const std::string kLcmDefaultUrl = "udpm://239.255.76.67:7667?ttl=0";

// Hosts that look like ordinary computers (OrdinaryHosts below): two LAN interfaces, "eth" (the
// default route's) and "wlan", no multicast route, no vehicle group, lcmx and stock programs
// on LCM's default URL with default options. The namespaces are this test's own, so the
// default group and port are unique to the test.
struct Ordinary {
  lcmx::test::MulticastRoute routes = lcmx::test::MulticastRoute::default_route;
};

class Hosts {
 public:
  // `index` makes groups and channels unique within this process (one per TEST_CASE).
  Hosts(int hosts, int index, ms timeout = 50000ms, ms beacon = 100ms, ms lease = 800ms)
      : index_(index),
        watchdog_(timeout, "multihost test " + std::to_string(index)),
        emu_(lcmx::test::Emulation::create({.hosts = hosts, .links = {{.name = "eth"}}})),
        vehicle_url(unique_vehicle_url(index, emu_.interface(0, "eth"))),
        discovery_url(it::unique_url(index)),
        beacon_ms(beacon),
        lease_ms(lease) {}
  // Ordinary computers (see Ordinary): lcmx_env() sets no group at all.
  Hosts(int hosts, int index, Ordinary o, ms timeout = 50000ms)
      : index_(index),
        watchdog_(timeout, "multihost test " + std::to_string(index)),
        emu_(lcmx::test::Emulation::create(
            {.hosts = hosts, .links = {{.name = "eth"}, {.name = "wlan"}}, .routes = o.routes})),
        vehicle_url(),
        discovery_url(kLcmDefaultUrl),
        beacon_ms(100ms),
        lease_ms(800ms) {}
  Hosts(const Hosts&) = delete;
  Hosts& operator=(const Hosts&) = delete;
  ~Hosts() {
    std::vector<pid_t> pids;
    for (auto& c : children_) pids.push_back(c->started_pid());
    children_.clear();  // SIGKILL + reap
    for (auto p : pids) it::remove_shm_of(p);
    it::remove_host_registries(emu_, discovery_url);
  }

  lcmx::test::Emulation& emu() { return emu_; }

  // Routes this test's host-local group to lo in every host (what LCM's documentation tells
  // users of a computer without a network to do), so stock liblcm joins and sends on lo. Without
  // it the group routes to the vehicle link here, which lcmx's host-local mode handles too (the
  // ordinary-computer cases: local_group_test.cpp).
  void route_local_group_to_lo() {
    const auto cfg_start = discovery_url.find("://") + 3;
    const auto group = discovery_url.substr(cfg_start, discovery_url.find(':', cfg_start) - cfg_start);
    for (int host = 0; host < emu_.hosts(); ++host) {
      const int rc = it::run_quiet({LCMX_IP, "-n", emu_.ns(host), "route", "add", group + "/32", "dev", "lo"});
      REQUIRE(rc == 0);
    }
  }

  // The environment of an lcmx process: this test's groups and short beacon period / lease.
  std::vector<std::string> lcmx_env(std::vector<std::string> extra = {}) const {
    std::vector<std::string> e = {"LCMX_BEACON_PERIOD_MS=" + std::to_string(beacon_ms.count()),
                                  "LCMX_LEASE_MS=" + std::to_string(lease_ms.count())};
    // Ordinary hosts: the defaults (unset, so a value inherited from ctest cannot leak in).
    e.push_back(discovery_url == kLcmDefaultUrl ? "LCMX_DISCOVERY_URL" : "LCMX_DISCOVERY_URL=" + discovery_url);
    e.push_back(vehicle_url.empty() ? "LCMX_VEHICLE_URL" : "LCMX_VEHICLE_URL=" + vehicle_url);
    for (auto& x : extra) e.push_back(std::move(x));
    return e;
  }

  // Starts argv inside `host`. Env entries "K=V" are added to ours.
  Child& spawn(int host, std::vector<std::string> argv, std::vector<std::string> env = {},
               bool merge_stderr = false) {
    argv.insert(argv.begin(), {LCMX_IP, "netns", "exec", emu_.ns(host)});
    auto c = std::make_unique<Child>(argv, env, merge_stderr);
    c->set_started();
    children_.push_back(std::move(c));
    return *children_.back();
  }

  // lcmx_test_peer inside `host` with lcmx_env(extra_env).
  Child& peer(int host, std::vector<std::string> args, std::vector<std::string> extra_env = {},
              bool merge_stderr = false) {
    args.insert(args.begin(), LCMX_TEST_PEER);
    args.insert(args.end(), {"--timeout-ms", "45000"});
    return spawn(host, std::move(args), lcmx_env(std::move(extra_env)), merge_stderr);
  }

  // The stock liblcm peer inside `host`.
  Child& lcm_peer(int host, std::vector<std::string> args) {
    args.insert(args.begin(), LCMX_LCM_PEER);
    return spawn(host, std::move(args));
  }

  // Runs a command to completion inside `host`: merged stdout+stderr and the exit code.
  struct Result {
    int rc;
    std::string out;
  };
  Result run(int host, std::vector<std::string> argv, std::vector<std::string> env = {},
             ms timeout = 15000ms) {
    Child& c = spawn(host, std::move(argv), std::move(env), true);
    const int rc = c.wait(timeout);
    return {rc, c.text()};
  }

  std::string channel(const std::string& base) const {
    return "MH_" + base + "_" + std::to_string(::getpid()) + "_" + std::to_string(index_);
  }

  const int index_;

 private:
  lcmx::test::Watchdog watchdog_;  // first: armed before the emulation is created
  lcmx::test::Emulation emu_;

 public:
  const std::string vehicle_url;
  const std::string discovery_url;
  const ms beacon_ms, lease_ms;

 private:
  std::vector<std::unique_ptr<Child>> children_;
};

inline bool contains(const std::string& s, const std::string& needle) { return s.find(needle) != std::string::npos; }

// How many lines of `text` contain `needle`.
inline int count_lines(const std::string& text, const std::string& needle) {
  int n = 0;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);)
    if (l.find(needle) != std::string::npos) ++n;
  return n;
}

// The lines of `text` containing `needle`.
inline std::vector<std::string> lines_with(const std::string& text, const std::string& needle) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);)
    if (l.find(needle) != std::string::npos) out.push_back(l);
  return out;
}

// The "host <hex>" of participant `pid` in `lcmx nodes` output ("" if absent).
inline std::string host_of(const std::string& nodes_out, pid_t pid) {
  for (const auto& l : lines_with(nodes_out, " pid " + std::to_string(pid) + " ")) {
    const auto h = l.find(" host ");
    if (l.rfind("participant ", 0) == 0 && h != std::string::npos) {
      std::istringstream in(l.substr(h + 6));
      std::string hex;
      in >> hex;
      return hex;
    }
  }
  return "";
}

// Every message 0..n-1 of a peer's stream arrived exactly once, in order, intact.
inline void check_exact(const Summary& s, long long n) {
  CHECK(s.num("received") == n);
  CHECK(s.num("first") == 0);
  CHECK(s.num("last") == n - 1);
  CHECK(s.num("duplicates") == 0);
  CHECK(s.num("out_of_order") == 0);
  CHECK(s.num("gaps") == 0);
  CHECK(s.num("bad_content") == 0);
}

}  // namespace lcmx::mh
