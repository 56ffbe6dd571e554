// bench/discovery peer: a user's kind of program. Publishes 10 topics at 1 Hz and subscribes to
// the 10 topics of other processes (--sub, repeatable: "<index>:<k>" = topic k of process
// <index>; default: the 10 topics of process index+1 mod n). Prints, on stdout, one line each
// (times are CLOCK_MONOTONIC ns, the driver's time.monotonic_ns()):
//   READY <ns> <cpu us> <wall ns since main>   once its endpoints exist
//   MATCHED <ns>                               once every subscription has a publisher
//   UNMATCHED <ns> <topic>                     a subscription that had a publisher has none
//                                              (publisher_count() went from >0 to 0)
//   REMATCHED <ns> <topic>                     a subscription that printed UNMATCHED has one again
// The subscriptions are polled every --poll-ms ms (default 10), before and after MATCHED, so a
// time is late by at most that (plus scheduling). Runs until stdin closes (the driver's pipe) or
// SIGTERM. Discovery options come from the environment (LCMX_DISCOVERY_URL, LCMX_VEHICLE_URL,
// LCMX_BEACON_PERIOD_MS, LCMX_LEASE_MS...), RuntimeOptions::from_env.
#include <poll.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include "lcmx/core/runtime.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace {
std::atomic<bool> g_stop{false};
void on_term(int) { g_stop = true; }
std::int64_t mono_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}
}  // namespace

int main(int argc, char** argv) {
  const auto t_main = mono_ns();
  int index = 0, n = 1, topics = 10, poll_ms = 10;
  std::string prefix = "DB";
  std::vector<std::string> subs;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string k = argv[i], v = argv[i + 1];
    if (k == "--index") index = std::atoi(v.c_str());
    else if (k == "--n") n = std::atoi(v.c_str());
    else if (k == "--topics") topics = std::atoi(v.c_str());
    else if (k == "--prefix") prefix = v;
    else if (k == "--poll-ms") poll_ms = std::max(1, std::atoi(v.c_str()));
    else if (k == "--sub") {
      const auto c = v.find(':');
      subs.push_back(prefix + "_" + v.substr(0, c) + "_" + v.substr(c + 1));
    } else {
      std::fprintf(stderr, "unknown option %s\n", k.c_str());
      return 2;
    }
  }
  if (subs.empty())
    for (int k = 0; k < topics; ++k) subs.push_back(prefix + "_" + std::to_string((index + 1) % n) + "_" + std::to_string(k));
  std::signal(SIGTERM, on_term);
  std::signal(SIGPIPE, SIG_IGN);
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("bench" + std::to_string(index));
  std::vector<lcmx::Publisher<lcmx_examples::pose_t>> pubs;
  for (int k = 0; k < topics; ++k)
    pubs.push_back(node.advertise<lcmx_examples::pose_t>(prefix + "_" + std::to_string(index) + "_" + std::to_string(k)));
  std::vector<lcmx::Subscriber<lcmx_examples::pose_t>> ss;
  for (const auto& s : subs) ss.push_back(node.subscribe<lcmx_examples::pose_t>(s, [](const lcmx_examples::pose_t&) {}));
  rusage ru{};
  ::getrusage(RUSAGE_SELF, &ru);
  const long long cpu_us = (ru.ru_utime.tv_sec + ru.ru_stime.tv_sec) * 1000000LL + ru.ru_utime.tv_usec + ru.ru_stime.tv_usec;
  std::printf("READY %lld %lld %lld\n", static_cast<long long>(mono_ns()), cpu_us,
              static_cast<long long>(mono_ns() - t_main));  // endpoints created: CPU and wall time so far
  std::fflush(stdout);
  bool matched = false;
  std::vector<char> has(ss.size(), 0), lost(ss.size(), 0);  // per subscription: a publisher now; UNMATCHED printed
  auto next_pub = std::chrono::steady_clock::now();
  lcmx_examples::pose_t msg{};
  while (!g_stop) {
    bool all = true, printed = false;
    for (std::size_t i = 0; i < ss.size(); ++i) {
      const bool now = ss[i].publisher_count() > 0;
      all = all && now;
      if (now == static_cast<bool>(has[i])) continue;
      has[i] = now;
      if (!now) {
        lost[i] = 1;
        std::printf("UNMATCHED %lld %s\n", static_cast<long long>(mono_ns()), subs[i].c_str());
        printed = true;
      } else if (lost[i]) {
        std::printf("REMATCHED %lld %s\n", static_cast<long long>(mono_ns()), subs[i].c_str());
        printed = true;
      }
    }
    if (!matched && all) {
      matched = true;
      std::printf("MATCHED %lld\n", static_cast<long long>(mono_ns()));
      printed = true;
    }
    if (printed) std::fflush(stdout);
    if (std::chrono::steady_clock::now() >= next_pub) {
      for (auto& p : pubs) p.publish(msg);
      next_pub += std::chrono::seconds(1);
    }
    pollfd pfd{0, POLLIN, 0};  // stdin: the driver's pipe closes -> stop
    if (::poll(&pfd, 1, poll_ms) > 0) {
      char buf[64];
      if (::read(0, buf, sizeof buf) <= 0) break;
    }
  }
  return 0;
}
