// lcmx_bench_log: the traffic and the observer of bench/log/run_log_bench.sh (recorder and
// player benchmarks; see bench/README.md "Log tools").
//
//   gen-stock URL CHANNELS RATE_HZ SIZE SECONDS [PREFIX [spread|burst]]
//     liblcm: CHANNELS channels PREFIX_000.. (BENCH_000..) at RATE_HZ each, bench_t of SIZE bytes (seq per
//     channel), for SECONDS. Prints "sent N". spread (default): channel c is sent at
//     c / CHANNELS of each period, as independent publishers would (their phases spread);
//     burst: all channels back to back at the start of each period, as one program that
//     publishes them all in one loop (the stress case: bursts of CHANNELS datagrams).
//   gen-lcmx CHANNELS RATE_HZ SIZE IMAGE_BYTES IMAGE_HZ SECONDS
//     lcmx: the same small channels plus IMAGE (bench_t of IMAGE_BYTES) at IMAGE_HZ, over
//     shared memory. Waits (10 s at most) for one subscriber per channel first. Prints
//     "sent N small M images B bytes".
//   observe URL LOG SECONDS
//     liblcm subscriber of every channel for SECONDS. LOG is the log being replayed: each
//     message is found in it by (channel, seq); its due time is start + (its log timestamp -
//     the first one's), start chosen as the median over all messages. Prints
//     "timing received=N matched=M p50_us=.. p99_us=.. max_us=.." (|actual - due|).
// One pacing thread (absolute deadlines, sleep_until), no busy waiting.
#include <lcm/lcm.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <unordered_map>
#include <vector>

#include "harness/options.hpp"
#include "harness/stats.hpp"
#include "lcmx/core.hpp"
#include "lcmx/log/eventlog.hpp"
#include "lcmx_examples/bench_t.hpp"

namespace {

using Clock = std::chrono::steady_clock;

std::int64_t mono_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

std::string channel_name(int i, const char* prefix = "BENCH") {
  char b[64];
  std::snprintf(b, sizeof b, "%s_%03d", prefix, i);
  return b;
}

lcmx_examples::bench_t make_msg(std::size_t size) {
  lcmx_examples::bench_t m;
  m.size = static_cast<std::int32_t>(size);
  m.data.assign(size, 0x5a);
  return m;
}

int gen_stock(const char* url, int channels, double rate, std::size_t size, double seconds, const char* prefix,
              bool spread) {
  lcm_t* lcm = lcm_create(url);
  if (!lcm) {
    std::fprintf(stderr, "lcm_create(%s) failed\n", url);
    return 1;
  }
  auto m = make_msg(size > 40 ? size - 40 : 8);
  std::vector<std::string> names;
  for (int c = 0; c < channels; ++c) names.push_back(channel_name(c, prefix));
  std::vector<std::uint8_t> buf;
  const auto period = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / rate));
  const auto end = Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  auto next = Clock::now();
  long sent = 0, failed = 0;
  for (std::int64_t seq = 0; Clock::now() < end; ++seq) {
    m.seq = seq;
    for (int c = 0; c < channels; ++c) {
      if (spread && c > 0) std::this_thread::sleep_until(next + period * c / channels);
      m.send_ns = mono_ns();
      buf.resize(static_cast<std::size_t>(m.getEncodedSize()));
      m.encode(buf.data(), 0, static_cast<int>(buf.size()));
      if (lcm_publish(lcm, names[static_cast<std::size_t>(c)].c_str(), buf.data(), static_cast<unsigned>(buf.size())) == 0) ++sent;
      else ++failed;
    }
    next += period;
    std::this_thread::sleep_until(next);
  }
  std::printf("sent %ld failed %ld\n", sent, failed);
  lcm_destroy(lcm);
  return 0;
}

int gen_lcmx(int channels, double rate, std::size_t size, std::size_t image_bytes, double image_hz, double seconds) {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("bench_gen");
  std::vector<lcmx::Publisher<lcmx_examples::bench_t>> pubs;
  for (int c = 0; c < channels; ++c) pubs.push_back(node.advertise<lcmx_examples::bench_t>(channel_name(c)));
  lcmx::PublisherOptions io;
  io.shm_initial_slot_size = image_bytes + 64;
  auto image_pub = node.advertise<lcmx_examples::bench_t>("IMAGE", io);
  const auto wait_until = Clock::now() + std::chrono::seconds(10);
  for (auto& p : pubs) p.wait_for_subscribers(1, std::chrono::duration_cast<std::chrono::milliseconds>(wait_until - Clock::now()));
  image_pub.wait_for_subscribers(1, std::chrono::duration_cast<std::chrono::milliseconds>(wait_until - Clock::now()));
  std::size_t matched = image_pub.subscriber_count() > 0 ? 1 : 0;
  for (auto& p : pubs) matched += p.subscriber_count() > 0 ? 1 : 0;
  std::fprintf(stderr, "gen-lcmx: %zu of %d channels have a subscriber\n", matched, channels + 1);
  auto small = make_msg(size > 40 ? size - 40 : 8);
  auto image = make_msg(image_bytes);
  const auto small_period = std::chrono::duration<double>(1.0 / rate);
  const auto image_period = std::chrono::duration<double>(1.0 / image_hz);
  const auto t0 = Clock::now();
  const auto end = t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  long n_small = 0, n_image = 0;
  double bytes = 0;
  std::int64_t small_seq = 0, image_seq = 0;
  for (;;) {
    const auto next_small = t0 + std::chrono::duration_cast<Clock::duration>(small_period * static_cast<double>(small_seq));
    const auto next_image = t0 + std::chrono::duration_cast<Clock::duration>(image_period * static_cast<double>(image_seq));
    const auto next = std::min(next_small, next_image);
    if (next >= end) break;
    std::this_thread::sleep_until(next);
    if (next == next_image) {
      image.seq = image_seq++;
      image.send_ns = mono_ns();
      image_pub.publish(image);
      ++n_image;
      bytes += static_cast<double>(image.getEncodedSize());
    } else {
      small.seq = small_seq++;
      for (auto& p : pubs) {
        small.send_ns = mono_ns();
        p.publish(small);
        ++n_small;
        bytes += static_cast<double>(small.getEncodedSize());
      }
    }
  }
  std::printf("sent %ld small %ld images %ld bytes %.0f\n", n_small + n_image, n_small, n_image, bytes);
  return 0;
}

struct Observe {
  std::unordered_map<std::string, std::unordered_map<std::int64_t, std::int64_t>> due_us;  // channel -> seq -> log ts
  std::int64_t log_first = INT64_MIN;
  std::int64_t first_recv_ns = 0, first_ts = 0;
  bool have_first = false;
  long received = 0, matched = 0;
  std::vector<std::int64_t> dev_ns;
};

void on_msg(const lcm_recv_buf_t* rbuf, const char* channel, void* user) {
  const std::int64_t now = mono_ns();
  auto* o = static_cast<Observe*>(user);
  ++o->received;
  lcmx_examples::bench_t m;
  if (m.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) < 0) return;
  auto c = o->due_us.find(channel);
  if (c == o->due_us.end()) return;
  auto s = c->second.find(m.seq);
  if (s == c->second.end()) return;
  ++o->matched;
  if (!o->have_first) {
    o->have_first = true;
    o->first_recv_ns = now;
    o->first_ts = s->second;
  }
  // Arrival relative to the schedule anchored at the first message; the constant part (the
  // anchor's own delay) is removed afterwards (median).
  o->dev_ns.push_back(now - (o->first_recv_ns + (s->second - o->first_ts) * 1000));
}

int observe(const char* url, const char* log, double seconds) {
  Observe o;
  try {
    auto r = lcmx::eventlog::Reader::open(log);
    lcmx::eventlog::Event e;
    std::unordered_map<std::string, std::unordered_map<std::int64_t, int>> seen;
    while (r.next(e)) {
      lcmx_examples::bench_t m;
      if (m.decode(e.data.data(), 0, static_cast<int>(e.data.size())) < 0) continue;
      o.due_us[e.channel].emplace(m.seq, e.timestamp_us);
      ++seen[e.channel][m.seq];
    }
    // (channel, seq) logged twice (e.g. warm-up traffic sent more than once) is ambiguous.
    for (auto& [ch, seqs] : seen)
      for (auto& [seq, n] : seqs)
        if (n > 1) o.due_us[ch].erase(seq);
  } catch (const std::exception& ex) {
    std::fprintf(stderr, "observe: %s\n", ex.what());
    return 1;
  }
  lcm_t* lcm = lcm_create(url);
  if (!lcm) return 1;
  lcm_subscribe(lcm, ".*", on_msg, &o);
  std::printf("ready\n");
  std::fflush(stdout);
  const auto end = Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  while (Clock::now() < end) lcm_handle_timeout(lcm, 100);
  lcm_destroy(lcm);
  // |actual - due| with the schedule's start taken as the median offset: a player that keeps
  // the log's spacing scores 0 whatever its start-up delay; lateness that varies (jitter,
  // drift, falling behind) counts.
  if (!o.dev_ns.empty()) {
    auto sorted = o.dev_ns;
    std::nth_element(sorted.begin(), sorted.begin() + static_cast<long>(sorted.size() / 2), sorted.end());
    const std::int64_t median = sorted[sorted.size() / 2];
    for (auto& d : o.dev_ns) d = std::llabs(d - median);
  }
  const auto st = lcmxbench::stats_of_ns(o.dev_ns);  // nearest-rank percentiles, µs
  std::printf("timing received=%ld matched=%ld p50_us=%.1f p99_us=%.1f max_us=%.1f\n", o.received, o.matched,
              st.p50, st.p99, st.max);
  return 0;
}

const char* const kUsage =
    "usage: lcmx_bench_log gen-stock URL CHANNELS RATE_HZ SIZE SECONDS [PREFIX [spread|burst]]\n"
    "       lcmx_bench_log gen-lcmx CHANNELS RATE_HZ SIZE IMAGE_BYTES IMAGE_HZ SECONDS\n"
    "       lcmx_bench_log observe URL LOG SECONDS\n"
    "The traffic and the observer of bench/log/run_log_bench.sh (bench/README.md \"Log tools\").\n";
int usage() { return lcmxbench::usage(kUsage, false); }

}  // namespace

int main(int argc, char** argv) {
  if (lcmxbench::help_asked(argc, argv)) return lcmxbench::usage(kUsage, true);
  if (argc < 2) return usage();
  const std::string cmd = argv[1];
  if (cmd == "gen-stock" && argc >= 7 && argc <= 9) {
    const std::string phase = argc == 9 ? argv[8] : "spread";
    if (phase != "spread" && phase != "burst") return usage();
    return gen_stock(argv[2], std::atoi(argv[3]), std::atof(argv[4]), static_cast<std::size_t>(std::atol(argv[5])),
                     std::atof(argv[6]), argc >= 8 ? argv[7] : "BENCH", phase == "spread");
  }
  if (cmd == "gen-lcmx" && argc == 8)
    return gen_lcmx(std::atoi(argv[2]), std::atof(argv[3]), static_cast<std::size_t>(std::atol(argv[4])),
                    static_cast<std::size_t>(std::atol(argv[5])), std::atof(argv[6]), std::atof(argv[7]));
  if (cmd == "observe" && argc == 5) return observe(argv[2], argv[3], std::atof(argv[4]));
  return usage();
}
