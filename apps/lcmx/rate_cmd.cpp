// `lcmx hz CHANNEL...` and `lcmx bw CHANNEL...`: rate and bandwidth of live channels, like
// `ros2 topic hz/bw`, computed on the arrival times and sizes of the raw messages (nothing is
// decoded or copied, so a 30 Hz camera of 6 MB images reads 30 Hz).
//
// Threads: the node's executor stamps each message (CLOCK_MONOTONIC) into its channel's window
// of the last -w messages (a mutex, no allocation once the window is full); the main thread
// prints every --period and waits for SIGINT/SIGTERM.
#include <spdlog/spdlog.h>

#include <cmath>
#include <cstdio>
#include <deque>
#include <iostream>
#include <map>
#include <mutex>

#include "echo_cmds.hpp"
#include "log_common.hpp"
#include "tap.hpp"

namespace lcmx::cli {
namespace {

enum class Kind { hz, bw };

struct RateOptions {
  std::vector<std::string> channels;
  bool regex = false;
  std::size_t window = 100;
  double period_s = 1.0;
  long long reports = 0;
  bool json = false;
  const Globals* g = nullptr;
};
RateOptions g_hz, g_bw;

struct Arrival {
  std::int64_t ns;
  std::size_t size;
};

struct Channel {
  std::deque<Arrival> window;  // the last -w messages
  std::uint64_t total = 0;     // messages ever
  std::uint64_t reported = 0;  // `total` at the last report
};

std::int64_t mono_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

class Meter {
 public:
  explicit Meter(std::size_t window) : window_(window) {}

  // Executor thread.
  void on_message(const RawMessage& m) {
    const std::int64_t now = mono_ns();
    std::lock_guard lock(mu_);
    auto it = channels_.find(m.channel);
    if (it == channels_.end()) it = channels_.emplace(std::string(m.channel), Channel{}).first;
    Channel& c = it->second;
    if (c.window.size() == window_) c.window.pop_front();
    c.window.push_back({now, m.data.size()});
    ++c.total;
  }

  // A copy of every channel's window; marks them reported.
  std::map<std::string, Channel, std::less<>> take() {
    std::lock_guard lock(mu_);
    auto copy = channels_;
    for (auto& [name, c] : channels_) c.reported = c.total;
    return copy;
  }

 private:
  const std::size_t window_;
  std::mutex mu_;
  std::map<std::string, Channel, std::less<>> channels_;
};

std::string seconds_text(double s) {
  if (s >= 1.0) return fmt("%.3f s", s);
  if (s >= 1e-3) return fmt("%.3f ms", s * 1e3);
  return fmt("%.1f us", s * 1e6);
}
std::string bytes_text(double b) {
  if (b >= 1e9) return fmt("%.2f GB", b / 1e9);
  if (b >= 1e6) return fmt("%.2f MB", b / 1e6);
  if (b >= 1e3) return fmt("%.2f KB", b / 1e3);
  return fmt("%.0f B", b);
}

// One line for a channel, text or JSON; empty when the window holds too little.
std::string report(Kind kind, const std::string& name, const Channel& c, bool json) {
  const std::size_t n = c.window.size();
  const std::uint64_t fresh = c.total - c.reported;
  if (n < 2) {
    if (json) return "";
    return printable(name) + ": " + (n == 0 ? "no messages yet" : "1 message, waiting for the next") + "\n";
  }
  const double span = static_cast<double>(c.window.back().ns - c.window.front().ns) / 1e9;
  if (kind == Kind::hz) {
    double mn = 1e300, mx = 0, sum = 0, sum2 = 0;
    for (std::size_t i = 1; i < n; ++i) {
      const double p = static_cast<double>(c.window[i].ns - c.window[i - 1].ns) / 1e9;
      mn = std::min(mn, p);
      mx = std::max(mx, p);
      sum += p;
      sum2 += p * p;
    }
    const double k = static_cast<double>(n - 1);
    const double mean = sum / k;
    const double sd = std::sqrt(std::max(0.0, sum2 / k - mean * mean));
    const double rate = span > 0 ? k / span : 0;
    if (json)
      return "{\"channel\":" + json_str(name) + ",\"rate_hz\":" + fmt("%.6g", rate) + ",\"period_min_s\":" +
             fmt("%.6g", mn) + ",\"period_max_s\":" + fmt("%.6g", mx) + ",\"period_std_dev_s\":" + fmt("%.6g", sd) +
             ",\"window\":" + std::to_string(n) + ",\"new\":" + std::to_string(fresh) +
             ",\"total\":" + std::to_string(c.total) + "}\n";
    return printable(name) + ": " + fmt("%.3f Hz", rate) + "  min " + seconds_text(mn) + "  max " + seconds_text(mx) +
           "  std dev " + seconds_text(sd) + "  window " + std::to_string(n) + (fresh == 0 ? "  (no new messages)" : "") +
           "\n";
  }
  double mn = 1e300, mx = 0, sum = 0, after_first = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const auto s = static_cast<double>(c.window[i].size);
    mn = std::min(mn, s);
    mx = std::max(mx, s);
    sum += s;
    if (i > 0) after_first += s;
  }
  const double mean = sum / static_cast<double>(n);
  const double bps = span > 0 ? after_first / span : 0;  // bytes that arrived during the span
  if (json)
    return "{\"channel\":" + json_str(name) + ",\"bytes_per_s\":" + fmt("%.6g", bps) + ",\"size_mean\":" +
           fmt("%.6g", mean) + ",\"size_min\":" + fmt("%.0f", mn) + ",\"size_max\":" + fmt("%.0f", mx) +
           ",\"window\":" + std::to_string(n) + ",\"new\":" + std::to_string(fresh) +
           ",\"total\":" + std::to_string(c.total) + "}\n";
  return printable(name) + ": " + bytes_text(bps) + "/s  mean " + bytes_text(mean) + "  min " + bytes_text(mn) + "  max " +
         bytes_text(mx) + "  window " + std::to_string(n) + (fresh == 0 ? "  (no new messages)" : "") + "\n";
}

int run_rate(Kind kind, const RateOptions& o) {
  const char* verb = kind == Kind::hz ? "lcmx hz" : "lcmx bw";
  spdlog::set_level(spdlog::level::warn);
  std::shared_ptr<const ChannelMatcher> match;
  try {
    match = std::make_shared<ChannelMatcher>(o.channels, o.regex);
  } catch (const std::regex_error& e) {
    std::cerr << verb << ": bad channel expression: " << e.what() << "\n";
    return 2;
  }
  StopSignals stop;
  Meter meter(o.window);
  std::optional<Tap> tap;
  try {
    SubscriberOptions so;
    so.queue_depth = 1024;  // a burst of UDP messages between two executor turns is still timed
    tap.emplace(*o.g, kind == Kind::hz ? "lcmx_hz" : "lcmx_bw", match,
                [&meter](const RawMessage& m) { meter.on_message(m); }, so);
  } catch (const std::exception& e) {
    std::cerr << verb << ": " << e.what() << "\n";
    return 1;
  }
  std::cerr << verb << ": listening" << std::endl;
  using Clock = std::chrono::steady_clock;
  const auto period = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(o.period_s));
  auto next = Clock::now() + period;
  long long printed = 0;
  while (!stop.wait_until(next)) {
    next += period;  // drift-free
    const auto channels = meter.take();
    std::string out;
    bool any = false;
    for (const auto& [name, c] : channels) {
      const std::string line = report(kind, name, c, o.json);
      out += line;
      any = any || c.window.size() >= 2;
    }
    if (channels.empty() && !o.json) out = "(no matching channel seen yet)\n";
    if (!o.json && channels.size() > 1 && !out.empty()) out += "\n";
    if (std::fwrite(out.data(), 1, out.size(), stdout) != out.size() || std::fflush(stdout) != 0) break;
    if (any && o.reports > 0 && ++printed >= o.reports) break;
  }
  return 0;
}

Verb add_rate(CLI::App& app, const Globals& g, Kind kind, RateOptions& o) {
  o.g = &g;
  const bool hz = kind == Kind::hz;
  auto* c = app.add_subcommand(
      hz ? "hz" : "bw",
      hz ? "print the rate of channels and the min/max/std dev of their periods, from arrival times (no decoding)"
         : "print the bandwidth of channels and their message sizes (min/mean/max)");
  c->add_option("channel", o.channels,
                "channel names or globs (CAM_*, quote them for the shell); with --regex, regular expressions")
      ->required();
  c->add_flag("--regex", o.regex, "CHANNEL arguments are regular expressions (ECMAScript, whole name)");
  c->add_option("-w,--window", o.window, "compute over the last N messages of each channel")
      ->check(CLI::Range(2, 1000000))
      ->capture_default_str();
  c->add_option("--period", o.period_s, "print every this many seconds")
      ->check(CLI::Range(0.01, 3600.0))
      ->capture_default_str();
  c->add_option("-n,--reports", o.reports, "exit after this many reports with data (0: until SIGINT/SIGTERM)")
      ->check(non_negative_number());
  c->add_flag("--json", o.json,
              hz ? "one JSON object per channel and report: channel, rate_hz, period_min_s, period_max_s, "
                   "period_std_dev_s, window, new (messages since the last report), total"
                 : "one JSON object per channel and report: channel, bytes_per_s, size_mean, size_min, size_max, "
                   "window, new (messages since the last report), total");
  c->footer(hz ? "Rate = (N-1) / (arrival of the last - arrival of the first) over the window of N messages, "
                 "timed when lcmx delivers them (CLOCK_MONOTONIC)."
               : "Bandwidth = bytes of the window's messages after the first / the time between the first and "
                 "the last arrival.");
  return {c, [kind, &o] { return run_rate(kind, o); }};
}

}  // namespace

Verb add_hz(CLI::App& app, const Globals& g) { return add_rate(app, g, Kind::hz, g_hz); }
Verb add_bw(CLI::App& app, const Globals& g) { return add_rate(app, g, Kind::bw, g_bw); }

}  // namespace lcmx::cli
