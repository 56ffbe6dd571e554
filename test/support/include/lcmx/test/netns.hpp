// Emulated hosts for multi-host tests and benchmarks: N network namespaces ("hosts") joined by
// veth links through Linux bridges that live in a dedicated "switch" namespace, so nothing at
// all is created in (or changed in) the root network namespace.
//
//            switch ns "lx<pid>_<n>_sw"
//        br_eth ───────────┬───────────── (one bridge = one L2 network per link)
//   h0_eth │          h1_eth │ ...
//      eth │             eth │
//   host ns "lx<pid>_<n>_h0"   host ns "lx<pid>_<n>_h1"  ...
//
// Inside each host: lo up (127.0.0.1, multicast flag on), one veth per link named after the
// link with its IPv4 address, a route 224.0.0.0/4 via the first link's interface (or a default
// route, or none: EmulationSpec::routes), IPv6 off (so
// the interface counters only see what the test sends, plus ARP/IGMP), ARP retries every 100 ms
// (not 1 s, so traffic resumes quickly after set_link_up). Bridges have multicast snooping and
// STP off, so multicast floods to every host on the link.
//
// Names carry the creating pid; Emulation::create() first removes namespaces left by dead
// creators (and kills processes still inside them). Root (CAP_SYS_ADMIN) is required; tests
// check netns_available() and skip with its reason.
//
// Use (link lcmx::test_netns):
//   std::string why;
//   LCMX_REQUIRE_NETNS();  // lcmx/test/catch_netns.hpp: skipped (CTest "Skipped") without namespaces
//   auto emu = lcmx::test::Emulation::create({.hosts = 2, .links = {{.name = "eth"},
//                                            {.name = "pcie", .rate = "8gbit"}}});
//   auto peer = emu.spawn(1, {"/path/to/app", "--iface", emu.interface(1, "eth")});
//   peer.expect("ready", 5s);
//   int fd = emu.run_in(0, [] { return ::socket(AF_INET, SOCK_DGRAM, 0); });  // host 0's socket
//   auto sent = emu.tx_bytes(0, "eth");
// Timings on a 2-vCPU VM: create 2 hosts x 1 link ~35 ms, 4 hosts x 2 links 50-100 ms; the
// destructor ~2 ms (the kernel frees the namespaces asynchronously).
#pragma once

#include <sched.h>

#include <cstdint>
#include <exception>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <type_traits>
#include <utility>
#include <vector>

#include "lcmx/test/process.hpp"

namespace lcmx::test {

struct LinkSpec {
  // Interface name inside every host (1..10 chars of [a-z0-9], not "lo"), e.g. "eth", "pcie".
  std::string name = "eth";
  // IPv4 subnet "a.b.c.d/len"; host i gets the (i+1)-th address. Empty: 10.x.y.0/24 derived
  // from the creating pid, the emulation's serial number and the link's index, so emulations
  // that run at the same time (threads or ctest -j) use different subnets.
  std::string subnet;
  // tc rate (e.g. "1gbit", "400mbit", "10gbps"): a tbf qdisc on each host's end of the link, so
  // every host-to-host path through this link is shaped once (at the sender).
  std::optional<std::string> rate;
  // One-way delay (e.g. "50us"): netem on each host's end. Needs CONFIG_NET_SCH_NETEM; create()
  // throws SetupError when the kernel lacks it (see delay_available()).
  std::optional<std::string> delay;
};

// How every host routes multicast (224.0.0.0/4), i.e. where liblcm joins and sends.
enum class MulticastRoute {
  first_link,     // "224.0.0.0/4 dev <first link>": the vehicle network (default)
  default_route,  // an ordinary computer: "default via <first link's last address>" and no
                  // multicast route (the laptop, Jetson, CI runner), so groups route to the LAN
  none,           // no route beyond the links' subnets: liblcm refuses to start, lo still works
};

struct EmulationSpec {
  int hosts = 2;                          // 1..250
  std::vector<LinkSpec> links = {LinkSpec{}};  // 1..8 links; one bridge per link
  MulticastRoute routes = MulticastRoute::first_link;
  // TCP congestion control of every host (net.ipv4.tcp_congestion_control in its namespace).
  // Default: Linux's own default, cubic, which Debian, Ubuntu and Jetson L4T ship, whatever
  // the machine running the emulation uses: a new namespace inherits the machine's choice, and
  // some VM images (this project's CI runners) pick bbr, whose pacing spreads a 1 MB burst at
  // its bandwidth estimate (2-3x the time of the same burst under cubic on a veth; bench/README
  // "TCP congestion control"). Empty: inherit the machine's. When the machine lets namespaces
  // pick only some algorithms (net.ipv4.tcp_allowed_congestion_control; some VMs list only
  // "reno bbr"), create() adds the one named to that list, which changes no default. create()
  // throws SetupError when the kernel does not offer the one named or the list cannot be written.
  std::string tcp_congestion = "cubic";
};

// Moves the calling thread into a network namespace; moves it back on destruction (aborts if
// that fails: the thread must not continue in the wrong namespace). Sockets created and
// threads/processes started meanwhile stay in the namespace. Move-only.
class ScopedNetns {
 public:
  explicit ScopedNetns(int netns_fd);  // throws SetupError
  ScopedNetns(ScopedNetns&& o) noexcept : home_(std::exchange(o.home_, -1)) {}
  ScopedNetns& operator=(ScopedNetns&&) = delete;
  ScopedNetns(const ScopedNetns&) = delete;
  ScopedNetns& operator=(const ScopedNetns&) = delete;
  ~ScopedNetns();

 private:
  int home_ = -1;
};

// Move-only RAII owner of one emulation. A moved-from Emulation may only be destroyed or
// assigned to. Const members may be called from several threads at once.
class Emulation {
 public:
  // Creates the namespaces, bridges, veths, addresses, routes and qdiscs, and waits until every
  // host interface has carrier. Throws SetupError (failing command + its stderr) on any fault,
  // after removing whatever it had created. Thread-safe (emulations may be created in parallel).
  static Emulation create(const EmulationSpec& spec = {});

  Emulation(Emulation&&) noexcept;
  Emulation& operator=(Emulation&&) noexcept;
  Emulation(const Emulation&) = delete;
  Emulation& operator=(const Emulation&) = delete;
  // Kills every process still inside the emulation's namespaces, then deletes the namespaces
  // (which deletes the veths and bridges in them). Never throws.
  ~Emulation();

  int hosts() const;
  const std::vector<LinkSpec>& links() const;         // as created (subnets filled in)
  const std::string& ns(int host) const;               // host namespace name (for `ip netns exec`)
  const std::string& switch_ns() const;                // namespace holding the bridges
  int ns_fd(int host) const;                           // O_RDONLY fd of the namespace, for setns()
  std::string address(int host, const std::string& link) const;    // e.g. "10.3.17.2"
  std::string interface(int host, const std::string& link) const;  // e.g. "eth" (= link name)

  // Takes a host's link down (cable pulled: the switch-side port goes down, the host's
  // interface loses carrier and keeps its address and routes) or up again. Returns once the
  // host's interface shows the new carrier state. Throws SetupError (or std::out_of_range).
  void set_link_up(int host, const std::string& link, bool up);

  // Byte counters of a host's interface on a link (the kernel's per-device counters, as in
  // /sys/class/net/<if>/statistics/{tx,rx}_bytes inside the namespace; read from /proc net/dev).
  // Counts Ethernet frames (payload + 42 bytes for UDP/IPv4 without options). Thread-safe.
  std::uint64_t tx_bytes(int host, const std::string& link) const;
  std::uint64_t rx_bytes(int host, const std::string& link) const;

  // Starts argv in a host namespace (fork, setns(CLONE_NEWNET), private mount namespace with
  // /sys remounted like `ip netns exec`, execve). See Child. Throws SetupError.
  Child spawn(int host, std::vector<std::string> argv, Env env = {}) const;

  // Runs f() on a new thread inside the host namespace and returns its result (or rethrows its
  // exception); blocks until f returns. Sockets f creates belong to the host and may be used
  // from any thread afterwards. Note: /proc/self/ns/net on that thread still names the process's
  // namespace; /proc/thread-self/ns/net names the host's.
  template <class F>
  auto run_in(int host, F&& f) -> std::invoke_result_t<F&> {
    using R = std::invoke_result_t<F&>;
    std::exception_ptr error;
    if constexpr (std::is_void_v<R>) {
      run_on_thread(host, [&] {
        try {
          f();
        } catch (...) {
          error = std::current_exception();
        }
      });
      if (error) std::rethrow_exception(error);
    } else {
      std::optional<R> result;
      run_on_thread(host, [&] {
        try {
          result.emplace(f());
        } catch (...) {
          error = std::current_exception();
        }
      });
      if (error) std::rethrow_exception(error);
      return std::move(*result);
    }
  }

  // Moves the calling thread into a host namespace until the guard is destroyed.
  ScopedNetns enter(int host) const { return ScopedNetns(ns_fd(host)); }

  // Removes namespaces named like this helper's ("lx<pid>_<n>_h<i>", "lx<pid>_<n>_sw") whose
  // creator pid is dead, killing processes left inside them. Returns how many it removed.
  // create() calls it; exposed for tests and tools.
  static int remove_stale();

 private:
  struct State;
  explicit Emulation(std::unique_ptr<State> s);
  void run_on_thread(int host, const std::function<void()>& body) const;
  std::unique_ptr<State> s_;
};

// Whether network namespaces can be created here; if not, `why` (if given) says why
// (not root / no CAP_SYS_ADMIN, `ip` missing, unshare(CLONE_NEWNET) refused, ...). Cached.
bool netns_available(std::string* why = nullptr);
// Bytes per second of a tc rate as LinkSpec::rate takes it ("10gbit", "400mbit", "1gbps"; a bare
// number is bits). Throws SetupError naming the rate when it is not one; for checking a user's
// option before any namespace is made.
double rate_bytes_per_second(const std::string& rate);
// Whether LinkSpec::delay can work (the kernel has the netem qdisc). Cached.
bool delay_available(std::string* why = nullptr);

// Async-signal-safe best effort for a dying process (a watchdog about to abort): kills the
// process groups of live Childs and deletes the namespaces of live Emulations.
void emergency_teardown() noexcept;

}  // namespace lcmx::test
