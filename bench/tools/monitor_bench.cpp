// lcmx_bench_monitor: traffic and the reference subscriber of the `lcmx monitor` benchmark
// (run_monitor_bench.sh).
//   lcmx_bench_monitor load PREFIX CHANNELS RATE_HZ SIZE SECONDS
//     CHANNELS raw publishers PREFIX_000.. in one process (shm to other processes), each
//     publishing an lcmx_examples::bench_t with SIZE data bytes at RATE_HZ, drift-free (one round every 1/RATE_HZ s); prints
//     "ready", runs SECONDS (or until SIGINT/SIGTERM), then prints "published <n>".
//   lcmx_bench_monitor sink SECONDS
//     a plain raw subscriber of every channel (Node::subscribe_channels, drop-oldest, the same
//     options as `lcmx monitor`) that only counts; prints "ready", runs SECONDS (or until
//     SIGINT/SIGTERM), then prints "received <n>".
// Both use the discovery group of LCMX_DISCOVERY_URL (the script gives one on lo).
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include "harness/options.hpp"
#include "lcmx/core.hpp"
#include "lcmx_examples/bench_t.hpp"

namespace {

std::atomic<bool> g_stop{false};
extern "C" void on_signal(int) { g_stop.store(true); }

using Clock = std::chrono::steady_clock;
Clock::time_point g_end;

// True after SECONDS or a signal.
bool should_stop() { return g_stop.load() || Clock::now() >= g_end; }

int load(const std::string& prefix, int channels, double rate, std::size_t size) {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("monitor_load");
  std::vector<lcmx::RawPublisher> pubs;
  for (int i = 0; i < channels; ++i) {
    char name[128];
    std::snprintf(name, sizeof name, "%s_%03d", prefix.c_str(), i);
    pubs.push_back(node.advertise_raw(name));
  }
  lcmx_examples::bench_t m;
  m.seq = 0;
  m.send_ns = 0;
  m.size = static_cast<std::int32_t>(size);
  m.data.assign(size, 0x5a);
  std::vector<std::byte> msg(static_cast<std::size_t>(m.getEncodedSize()));
  std::printf("ready\n");
  std::fflush(stdout);
  const auto period = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / rate));
  auto next = Clock::now();
  std::uint64_t n = 0;
  while (!should_stop()) {
    m.seq = static_cast<std::int64_t>(n);
    m.encode(msg.data(), 0, static_cast<int>(msg.size()));
    for (auto& p : pubs) {
      p.publish(msg);
      ++n;
    }
    next += period;
    std::this_thread::sleep_until(next);  // pacing the rate
  }
  std::printf("published %llu\n", static_cast<unsigned long long>(n));
  return 0;
}

int sink() {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("monitor_peer");
  std::atomic<std::uint64_t> n{0};
  lcmx::SubscriberOptions so;
  so.policy = lcmx::QueuePolicy::drop_oldest;
  auto sub = node.subscribe_channels([](const std::string&) { return true; },
                                     [&n](const lcmx::RawMessage&) { n.fetch_add(1, std::memory_order_relaxed); }, so);
  std::printf("ready\n");
  std::fflush(stdout);
  while (!should_stop()) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  sub.reset();
  std::printf("received %llu\n", static_cast<unsigned long long>(n.load()));
  return 0;
}

}  // namespace

const char* const kUsage =
    "usage: lcmx_bench_monitor load PREFIX CHANNELS RATE_HZ SIZE SECONDS | sink SECONDS\n"
    "The traffic and the peer of bench/tools/run_monitor_bench.sh (bench/README.md \"lcmx monitor CPU\").\n";

int main(int argc, char** argv) {
  if (lcmxbench::help_asked(argc, argv)) return lcmxbench::usage(kUsage, true);
  struct sigaction sa{};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  ::sigaction(SIGINT, &sa, nullptr);
  ::sigaction(SIGTERM, &sa, nullptr);
  const std::string role = argc > 1 ? argv[1] : "";
  try {
    if (role == "load" && argc == 7) {
      g_end = Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(std::atof(argv[6])));
      return load(argv[2], std::atoi(argv[3]), std::atof(argv[4]), static_cast<std::size_t>(std::atol(argv[5])));
    }
    if (role == "sink" && argc == 3) {
      g_end = Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(std::atof(argv[2])));
      return sink();
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "lcmx_bench_monitor: %s\n", e.what());
    return 1;
  }
  return lcmxbench::usage(kUsage, false);
}
