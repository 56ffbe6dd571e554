// bench/discovery peer: a user's kind of program. Publishes 10 topics at 1 Hz and subscribes to
// the 10 topics of other processes (--sub, repeatable: "<index>:<k>" = topic k of process
// <index>; default: the 10 topics of process index+1 mod n). Prints, on stdout, one line each
// (times are CLOCK_MONOTONIC ns, the driver's time.monotonic_ns()):
//   READY <ns> <cpu us> <wall ns since main>   once its endpoints exist
//   MATCHED <ns>                               once every subscription has a publisher
//   UNMATCHED <ns> <topic> <how>               a subscription that had a publisher has none
//                                              (publisher_count() went from >0 to 0)
//   REMATCHED <ns> <topic> <how>               a subscription that printed UNMATCHED has one again
// The subscriptions' publisher_count() is checked every --poll-ms ms (10) until MATCHED, every
// --idle-poll-ms ms (200) after, and at once whenever the runtime reports a publisher_matched
// or publisher_unmatched Event (--events 1, the default; Runtime::on_event, which wakes this
// thread by an eventfd). <how> says what the check that saw the change ran for: "event" (its
// time is the change's, to a wake-up) or "poll" (late by up to the period). Polling every 10 ms
// after MATCHED as well (--events 0 --idle-poll-ms 10) made each process cost 0.45 % of a core
// instead of 0.11 % (N = 50 on one host, 2-vCPU VM, 2026-12-08: the 100 wake-ups a second, more
// than the whole discovery target of 0.1 %); the events cost nothing measurable (0.11-0.12 %)
// and time a SIGKILL at 4-5 ms on the same host where 10 ms polling gave 16-17 ms.
// Runs until stdin closes (the driver's pipe) or SIGTERM. Discovery options come from the
// environment (LCMX_DISCOVERY_URL, LCMX_VEHICLE_URL, LCMX_BEACON_PERIOD_MS, LCMX_LEASE_MS...),
// RuntimeOptions::from_env.
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdint>
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
  int index = 0, n = 1, topics = 10, poll_ms = 10, idle_poll_ms = 200;
  bool events = true;
  std::string prefix = "DB";
  std::vector<std::string> subs;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string k = argv[i], v = argv[i + 1];
    if (k == "--index") index = std::atoi(v.c_str());
    else if (k == "--n") n = std::atoi(v.c_str());
    else if (k == "--topics") topics = std::atoi(v.c_str());
    else if (k == "--prefix") prefix = v;
    else if (k == "--poll-ms") poll_ms = std::max(1, std::atoi(v.c_str()));
    else if (k == "--idle-poll-ms") idle_poll_ms = std::max(1, std::atoi(v.c_str()));
    else if (k == "--events") events = std::atoi(v.c_str()) != 0;
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
  // Woken by the runtime's match events (on its threads: the callback only counts them).
  const int wake = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (wake < 0) {
    std::perror("eventfd");
    return 1;
  }
  if (events)
    rt.on_event([wake](const lcmx::Event& e) {
      if (e.kind == lcmx::Event::Kind::publisher_matched || e.kind == lcmx::Event::Kind::publisher_unmatched) {
        const std::uint64_t one = 1;
        [[maybe_unused]] const auto w = ::write(wake, &one, sizeof one);
      }
    });
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
  const char* how = "poll";  // what the check below runs for
  while (!g_stop) {
    bool all = true, printed = false;
    for (std::size_t i = 0; i < ss.size(); ++i) {
      const bool now = ss[i].publisher_count() > 0;
      all = all && now;
      if (now == static_cast<bool>(has[i])) continue;
      has[i] = now;
      if (!now) {
        lost[i] = 1;
        std::printf("UNMATCHED %lld %s %s\n", static_cast<long long>(mono_ns()), subs[i].c_str(), how);
        printed = true;
      } else if (lost[i]) {
        std::printf("REMATCHED %lld %s %s\n", static_cast<long long>(mono_ns()), subs[i].c_str(), how);
        printed = true;
      }
    }
    if (!matched && all) {
      matched = true;
      std::printf("MATCHED %lld\n", static_cast<long long>(mono_ns()));
      printed = true;
    }
    if (printed) std::fflush(stdout);
    const auto now = std::chrono::steady_clock::now();
    if (now >= next_pub) {
      for (auto& p : pubs) p.publish(msg);
      next_pub += std::chrono::seconds(1);
    }
    const auto to_pub = std::chrono::duration_cast<std::chrono::milliseconds>(next_pub - now).count() + 1;
    const int timeout = static_cast<int>(std::min<long long>(matched ? idle_poll_ms : poll_ms, std::max(0LL, static_cast<long long>(to_pub))));
    pollfd pfd[2] = {{0, POLLIN, 0}, {wake, POLLIN, 0}};  // stdin: the driver's pipe closes -> stop
    if (::poll(pfd, 2, timeout) > 0) {
      if (pfd[0].revents != 0) {
        char buf[64];
        if (::read(0, buf, sizeof buf) <= 0) break;
      }
      if (pfd[1].revents & POLLIN) {
        std::uint64_t count = 0;
        [[maybe_unused]] const auto r = ::read(wake, &count, sizeof count);
        how = "event";
        continue;
      }
    }
    how = "poll";
  }
  return 0;
}
