// lcmx_bench_foxglove: the processes of bench/foxglove/run.sh (README.md there).
//
//   pub    --channels N --rate HZ --image-hz H --width W --height H --seconds S
//     N lcmx_fgbench.small_t channels FGB_S_<i> at HZ and one W x H rgb8 lcmx_fgbench.image_t
//     on FGB_IMAGE at H (its own thread, as its own process would), each stamped with utime =
//     CLOCK_REALTIME just before publish(). Waits (60 s at most) until every channel has a
//     subscriber ("MATCHED"), publishes for S seconds, then prints one JSON line: publish()
//     duration p50/p99 (µs) of small messages and of the image, and the counts.
//   sub    --channels N --seconds S --warmup W
//     A plain lcmx subscriber of every channel (raw: it reads utime from the bytes), the run
//     without the server: after the first message and W seconds it counts for S seconds and
//     prints one JSON line: rates and publish -> receipt latency.
//   client --port P --clients K --slow M --channels N --seconds S --warmup W
//     K WebSocket clients (ws_client.hpp: the frame header is all they read of a data message)
//     that subscribe to every channel (N small, the image and its /image RawImage view) and read,
//     and M that subscribe to everything and then never read their socket again. Each reading
//     client, once subscribed to all, waits W seconds, counts S seconds and prints one JSON line:
//     its delivered rates and publish -> receipt latency (frame timestamp = utime, the server's
//     rule).
// Every clock read is CLOCK_REALTIME (the frames' timestamps are utime); all on one host.
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "lcmx/core.hpp"
#include "lcmx_fgbench/image_t.hpp"
#include "lcmx_fgbench/small_t.hpp"
#include "ws_client.hpp"

namespace {

using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

std::int64_t real_ns() {
  timespec ts{};
  clock_gettime(CLOCK_REALTIME, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

double pct(std::vector<double>& v, double p) {
  if (v.empty()) return -1;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<std::size_t>(p / 100 * static_cast<double>(v.size())))];
}

// Receivers stay this long after their window (receiving, not counting), so the publishers'
// and the server's situation does not change before run.sh's CPU window ends.
constexpr std::int64_t kLinger = 5'000'000'000;

std::string small_channel(int i) { return "FGB_S_" + std::to_string(i); }
constexpr const char* kImageChannel = "FGB_IMAGE";

struct Args {
  int channels = 100, seconds = 15, warmup = 3, width = 1920, height = 1080, port = 8765, clients = 2, slow = 1;
  double rate = 100, image_hz = 10;
};

int run_pub(const Args& a) {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("fgb_pub");
  std::vector<lcmx::Publisher<lcmx_fgbench::small_t>> smalls;
  for (int i = 0; i < a.channels; ++i) smalls.push_back(node.advertise<lcmx_fgbench::small_t>(small_channel(i)));
  lcmx::PublisherOptions io;
  io.shm_initial_slot_size = static_cast<std::size_t>(a.width) * a.height * 3 + 4096;
  io.max_message_size = std::max(io.max_message_size, io.shm_initial_slot_size);
  auto image = node.advertise<lcmx_fgbench::image_t>(kImageChannel, io);
  const auto deadline = Clock::now() + 60s;
  auto all_matched = [&] {
    for (auto& p : smalls)
      if (p.subscriber_count() == 0) return false;
    return image.subscriber_count() > 0;
  };
  while (!all_matched()) {
    if (Clock::now() > deadline) {
      std::printf("{\"error\":\"not every channel has a subscriber after 60 s\"}\n");
      return 1;
    }
    std::this_thread::sleep_for(10ms);  // polling a condition with a deadline
  }
  std::printf("MATCHED\n");
  std::fflush(stdout);
  const auto start = Clock::now(), end = start + std::chrono::seconds(a.seconds);
  std::vector<double> image_us;
  long long images = 0;
  std::thread image_thread([&] {
    lcmx_fgbench::image_t img{};
    img.width = a.width;
    img.height = a.height;
    img.step = a.width * 3;
    img.encoding = "rgb8";
    img.frame_id = "camera";
    img.size = img.step * a.height;
    img.data.resize(static_cast<std::size_t>(img.size));
    for (std::size_t i = 0; i < img.data.size(); ++i) img.data[i] = static_cast<std::uint8_t>(i * 7);
    const auto period = std::chrono::duration<double>(1.0 / a.image_hz);
    for (long long k = 0;; ++k) {
      const auto due = start + std::chrono::duration_cast<Clock::duration>(period * static_cast<double>(k));
      if (due >= end) break;
      std::this_thread::sleep_until(due);  // the publisher's own period
      img.seq = k;
      const auto t0 = Clock::now();
      img.utime = real_ns() / 1000;
      image.publish(img);
      image_us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
      ++images;
    }
  });
  std::vector<double> small_us;
  small_us.reserve(static_cast<std::size_t>(a.channels * a.rate * a.seconds) + 16);
  lcmx_fgbench::small_t m{};
  const auto period = std::chrono::duration<double>(1.0 / a.rate);
  long long smalls_sent = 0;
  std::vector<double> late_ms;  // how late each round of small messages began
  for (long long k = 0;; ++k) {
    const auto due = start + std::chrono::duration_cast<Clock::duration>(period * static_cast<double>(k));
    if (due >= end) break;
    std::this_thread::sleep_until(due);  // the publishers' own period
    late_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - due).count());
    m.seq = k;
    for (auto& p : smalls) {
      m.values[0] = static_cast<double>(k);
      const auto t0 = Clock::now();
      m.utime = real_ns() / 1000;
      p.publish(m);
      small_us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
      ++smalls_sent;
    }
  }
  image_thread.join();
  std::printf("{\"small_p50_us\":%.2f,\"small_p99_us\":%.2f,\"image_p50_us\":%.1f,\"image_p99_us\":%.1f,"
              "\"small_published\":%lld,\"images_published\":%lld,\"round_late_p50_ms\":%.3f,\"round_late_p99_ms\":%.3f}\n",
              pct(small_us, 50), pct(small_us, 99), pct(image_us, 50), pct(image_us, 99), smalls_sent, images,
              pct(late_ms, 50), pct(late_ms, 99));
  return 0;
}

// utime of an encoded lcmx_fgbench message: big-endian int64 after the 8-byte fingerprint.
std::int64_t utime_of(std::span<const std::byte> d) {
  if (d.size() < 16) return 0;
  std::uint64_t v = 0;
  for (int i = 8; i < 16; ++i) v = (v << 8) | std::to_integer<std::uint8_t>(d[static_cast<std::size_t>(i)]);
  return static_cast<std::int64_t>(v);
}

int run_sub(const Args& a) {
  auto rt = lcmx::Runtime::create();
  auto node = rt.create_node("fgb_sub");
  std::mutex mu;
  std::int64_t window_start = 0, window_end = 0;  // real ns; 0 until the first message
  long long small_n = 0, image_n = 0;
  std::vector<double> small_lat, image_lat;
  auto on = [&](bool is_image, const lcmx::RawMessage& m) {
    const std::int64_t now = real_ns();
    std::lock_guard l(mu);
    if (window_start == 0) {
      window_start = now + std::int64_t{a.warmup} * 1'000'000'000;
      window_end = window_start + std::int64_t{a.seconds} * 1'000'000'000;
    }
    if (now < window_start || now >= window_end) return;
    const double lat_us = static_cast<double>(now - utime_of(m.data) * 1000) / 1000.0;
    if (is_image) {
      ++image_n;
      image_lat.push_back(lat_us);
    } else {
      ++small_n;
      small_lat.push_back(lat_us);
    }
  };
  std::vector<lcmx::RawSubscriber> subs;
  for (int i = 0; i < a.channels; ++i)
    subs.push_back(node.subscribe_raw(small_channel(i), [&](const lcmx::RawMessage& m) { on(false, m); }));
  subs.push_back(node.subscribe_raw(kImageChannel, [&](const lcmx::RawMessage& m) { on(true, m); }));
  std::printf("READY\n");
  std::fflush(stdout);
  const auto deadline = Clock::now() + std::chrono::seconds(60 + a.warmup + a.seconds + 5);
  for (;;) {
    {
      std::lock_guard l(mu);
      if (window_end != 0 && real_ns() > window_end + kLinger) break;
    }
    if (Clock::now() > deadline) break;
    std::this_thread::sleep_for(50ms);  // polling the end of the window
  }
  subs.clear();
  std::lock_guard l(mu);
  std::printf("{\"role\":\"sub\",\"small_hz\":%.1f,\"image_hz\":%.2f,\"small_p50_us\":%.1f,\"small_p99_us\":%.1f,"
              "\"image_p50_us\":%.1f,\"image_p99_us\":%.1f}\n",
              static_cast<double>(small_n) / a.seconds, static_cast<double>(image_n) / a.seconds, pct(small_lat, 50),
              pct(small_lat, 99), pct(image_lat, 50), pct(image_lat, 99));
  return 0;
}

enum Kind { kSmall = 0, kImage = 1, kView = 2 };

struct ClientResult {
  long long n[3] = {0, 0, 0};
  double bytes = 0;
  std::vector<double> lat[3];
  std::map<int, long long> per_small;  // channel index -> messages in the window
  std::map<int, std::pair<long long, long long>> seq_range;  // channel index -> first, last seq seen
  std::string error;
};

// One client: subscribes to every bench channel as it is advertised; `reading` false: stops
// reading once subscribed to all (until `stop`).
void run_one_client(const Args& a, bool reading, std::atomic<bool>& stop, ClientResult& r) {
  try {
    lcmx::fgbench::WsClient ws("127.0.0.1", a.port, "foxglove.websocket.v1");
    std::map<std::uint32_t, std::pair<Kind, int>> subs;  // subscription (= channel id) -> kind, index
    const std::size_t want = static_cast<std::size_t>(a.channels) + 2;
    std::int64_t window_start = 0, window_end = 0;
    std::string head;
    const auto deadline = Clock::now() + std::chrono::seconds(60 + a.warmup + a.seconds + 5);
    while (!stop.load()) {
      if (Clock::now() > deadline) {
        r.error = "deadline";
        return;
      }
      if (window_end != 0 && real_ns() >= window_end + kLinger) return;
      auto m = ws.read(head, 64, 100);
      if (!m) continue;
      if (m->opcode == 1) {
        const auto j = nlohmann::json::parse(head, nullptr, false);
        if (j.is_discarded() || j.value("op", "") != "advertise") continue;
        nlohmann::json list = nlohmann::json::array();
        for (const auto& ch : j.at("channels")) {
          const auto topic = ch.at("topic").get<std::string>();
          const auto id = ch.at("id").get<std::uint32_t>();
          std::pair<Kind, int> k;
          if (topic == kImageChannel) k = {kImage, 0};
          else if (topic == std::string(kImageChannel) + "/image") k = {kView, 0};
          else if (topic.rfind("FGB_S_", 0) == 0) k = {kSmall, std::stoi(topic.substr(6))};
          else continue;
          if (subs.emplace(id, k).second) list.push_back({{"id", id}, {"channelId", id}});
        }
        if (!list.empty()) ws.send_text(nlohmann::json{{"op", "subscribe"}, {"subscriptions", list}}.dump());
        if (subs.size() == want && window_start == 0) {
          window_start = real_ns() + std::int64_t{a.warmup} * 1'000'000'000;
          window_end = window_start + std::int64_t{a.seconds} * 1'000'000'000;
          if (!reading) {
            while (!stop.load()) std::this_thread::sleep_for(50ms);  // a client that never reads again
            return;
          }
        }
        continue;
      }
      if (m->opcode != 2 || head.size() < 13 || head[0] != 1) continue;
      const std::int64_t now = real_ns();
      if (window_start == 0 || now < window_start) continue;
      if (now >= window_end) continue;
      std::uint32_t sub = 0;
      std::uint64_t ts = 0;
      for (int i = 0; i < 4; ++i) sub |= std::uint32_t{static_cast<std::uint8_t>(head[1 + i])} << (8 * i);
      for (int i = 0; i < 8; ++i) ts |= std::uint64_t{static_cast<std::uint8_t>(head[5 + i])} << (8 * i);
      const auto it = subs.find(sub);
      if (it == subs.end()) continue;
      const Kind k = it->second.first;
      ++r.n[k];
      r.bytes += static_cast<double>(m->size);
      r.lat[k].push_back(static_cast<double>(now - static_cast<std::int64_t>(ts)) / 1000.0);
      if (k == kSmall) {
        ++r.per_small[it->second.second];
        // `"seq":N` near the start of the JSON: how many were published in the window.
        const auto at = head.find("\"seq\":", 13);
        if (at != std::string::npos) {
          const long long seq = std::atoll(head.c_str() + at + 6);
          auto [sr, fresh] = r.seq_range.emplace(it->second.second, std::make_pair(seq, seq));
          if (!fresh) {
            sr->second.first = std::min(sr->second.first, seq);
            sr->second.second = std::max(sr->second.second, seq);
          }
        }
      }
    }
  } catch (const std::exception& e) {
    r.error = e.what();
  }
}

int run_client(const Args& a) {
  std::atomic<bool> stop_slow{false}, never{false};
  std::vector<ClientResult> results(static_cast<std::size_t>(a.clients + a.slow));
  std::vector<std::thread> slow, reading;
  for (int i = 0; i < a.slow; ++i)
    slow.emplace_back([&, i] { run_one_client(a, false, stop_slow, results[static_cast<std::size_t>(a.clients + i)]); });
  for (int i = 0; i < a.clients; ++i)
    reading.emplace_back([&, i] { run_one_client(a, true, never, results[static_cast<std::size_t>(i)]); });
  for (auto& t : reading) t.join();
  stop_slow = true;
  for (auto& t : slow) t.join();
  for (int i = 0; i < a.clients; ++i) {
    auto& r = results[static_cast<std::size_t>(i)];
    long long expected = 0;
    for (const auto& [c, range] : r.seq_range) expected += range.second - range.first + 1;
    long long min_ch = -1;
    for (int c = 0; c < a.channels; ++c) {
      const long long n = r.per_small.count(c) ? r.per_small[c] : 0;
      if (min_ch < 0 || n < min_ch) min_ch = n;
    }
    const double s = a.seconds;
    std::printf("{\"role\":\"client\",\"client\":%d,\"small_delivered\":%.4f,\"small_hz\":%.1f,\"small_min_channel_hz\":%.1f,\"image_hz\":%.2f,"
                "\"view_hz\":%.2f,\"small_p50_us\":%.1f,\"small_p99_us\":%.1f,\"image_p50_us\":%.1f,"
                "\"image_p99_us\":%.1f,\"view_p50_us\":%.1f,\"view_p99_us\":%.1f,\"mb_per_s\":%.1f,\"error\":\"%s\"}\n",
                i + 1, expected > 0 ? static_cast<double>(r.n[kSmall]) / static_cast<double>(expected) : 0.0,
                static_cast<double>(r.n[kSmall]) / s, static_cast<double>(min_ch) / s,
                static_cast<double>(r.n[kImage]) / s, static_cast<double>(r.n[kView]) / s, pct(r.lat[kSmall], 50),
                pct(r.lat[kSmall], 99), pct(r.lat[kImage], 50), pct(r.lat[kImage], 99), pct(r.lat[kView], 50),
                pct(r.lat[kView], 99), r.bytes / s / 1e6, r.error.c_str());
  }
  for (int i = 0; i < a.slow; ++i) {
    const auto& r = results[static_cast<std::size_t>(a.clients + i)];
    std::printf("{\"role\":\"slow\",\"client\":%d,\"error\":\"%s\"}\n", i + 1, r.error.c_str());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lcmx_bench_foxglove: publishers, a plain subscriber, or WebSocket clients for bench/foxglove"};
  std::string role;
  Args a;
  app.add_option("role", role, "pub | sub | client")->required()->check(CLI::IsMember({"pub", "sub", "client"}));
  app.add_option("--channels", a.channels, "small channels")->check(CLI::Range(1, 10000));
  app.add_option("--rate", a.rate, "pub: Hz of each small channel")->check(CLI::PositiveNumber);
  app.add_option("--image-hz", a.image_hz, "pub: Hz of the image")->check(CLI::PositiveNumber);
  app.add_option("--width", a.width, "pub: image width")->check(CLI::Range(1, 16384));
  app.add_option("--height", a.height, "pub: image height")->check(CLI::Range(1, 16384));
  app.add_option("--seconds", a.seconds, "measured seconds")->check(CLI::Range(1, 3600));
  app.add_option("--warmup", a.warmup, "sub, client: seconds before measuring")->check(CLI::Range(0, 600));
  app.add_option("--port", a.port, "client: the server's port on 127.0.0.1")->check(CLI::Range(1, 65535));
  app.add_option("--clients", a.clients, "client: reading clients")->check(CLI::Range(0, 64));
  app.add_option("--slow", a.slow, "client: clients that stop reading")->check(CLI::Range(0, 64));
  CLI11_PARSE(app, argc, argv);
  try {
    if (role == "pub") return run_pub(a);
    if (role == "sub") return run_sub(a);
    return run_client(a);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "lcmx_bench_foxglove: %s\n", e.what());
    return 1;
  }
}
