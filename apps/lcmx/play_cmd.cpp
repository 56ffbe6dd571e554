// `lcmx play FILE`: replays an LCM event log (lcm-logger's or lcmx record's) through lcmx, so
// typed subscribers on every path receive it; optionally also on the UDP groups for stock
// LCM programs.
//
// Each channel is published by a raw publisher that announces the lcm-gen fingerprint found
// in the log (the first 8 bytes of its messages), so typed subscribers match it and
// subscribers of another type get a type-mismatch error. A first pass over the headers finds
// channels, fingerprints, duration and damage.
//
// Timing: event k is due at start + (t_k - t_first) / speed on CLOCK_MONOTONIC. The player
// sleeps (clock_nanosleep, absolute, timer slack 1 ns) until --spin-us before that and spins
// the rest, so it publishes within microseconds of the due time when it has a CPU. Pauses
// shift the start. Threads: the main thread plays; a stdin thread reads the space bar (TTY)
// or lines "pause"/"resume"/"toggle"/"quit"; a clock thread publishes the log's time
// (lcmtypes/play.lcm, on LCMX_PLAY_CLOCK, unless --no-clock); signal handlers set flags.
#include <signal.h>
#include <spdlog/spdlog.h>
#include <sys/prctl.h>
#include <termios.h>
#include <poll.h>
#include <unistd.h>

#include <pthread.h>
#include <sched.h>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstring>
#include <cmath>
#include <iostream>
#include <map>
#include <optional>
#include <sstream>
#include <thread>

#include "lcmx/discovery/beacon_codec.hpp"
#include "lcmx/core.hpp"
#include "lcmx/foxglove/server.hpp"  // kPlayClockChannel
#include "lcmx/log/eventlog.hpp"
#include "lcmx_msgs/play_clock_t.hpp"
#include "log_cmds.hpp"
#include "log_common.hpp"

namespace lcmx::cli {
namespace {

struct PlayOptions {
  std::string file;
  double speed = 1.0;
  bool fast = false;
  bool loop = false;
  std::string channel = ".*";
  std::vector<std::string> exclude;
  double start_s = 0;
  double end_s = -1;
  double delay_s = 0.5;
  bool paused = false;
  std::vector<std::string> remap;
  bool udp = false;
  int wait_subscribers = 0;
  double wait_timeout_s = 10;
  int spin_us = 50;
  int rt_priority = 0;
  bool stop_on_damage = false;
  bool no_clock = false;
  bool quiet = false;
  bool json = false;
  const Globals* g = nullptr;  // read when the verb runs (filled by the parse)
};
PlayOptions g_play;

std::atomic<bool> g_quit{false};
std::atomic<bool> g_paused{false};
extern "C" void on_play_signal(int) { g_quit.store(true); }

using Clock = std::chrono::steady_clock;

std::int64_t mono_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

// Waits until `due` (CLOCK_MONOTONIC ns): sleeps in slices of at most 50 ms (so pause and quit
// are seen) until spin_ns before it, then spins. Returns false when interrupted (quit or
// pause: the caller re-plans).
bool wait_until(std::int64_t due, std::int64_t spin_ns) {
  for (;;) {
    if (g_quit.load(std::memory_order_relaxed) || g_paused.load(std::memory_order_relaxed)) return false;
    const std::int64_t now = mono_ns();
    if (now >= due) return true;
    const std::int64_t left = due - now;
    if (left > spin_ns) {
      const std::int64_t wake = std::min(due - spin_ns, now + 50'000'000);
      timespec ts{static_cast<time_t>(wake / 1'000'000'000), static_cast<long>(wake % 1'000'000'000)};
      ::clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
    } else {
#if defined(__x86_64__) || defined(__i386__)
      __builtin_ia32_pause();
#endif
    }
  }
}

// The log's clock as it is played (lcmtypes/play.lcm): the playing thread moves it; a thread of
// its own publishes it on kPlayClockChannel every 50 ms, and at once when play pauses or resumes.
// While playing in real time it runs between events (base_ts + elapsed * speed); paused, or with
// --fast, it stands at the last event published. Every member is thread-safe.
class PlayClock {
 public:
  PlayClock(Publisher<lcmx_msgs::play_clock_t> pub, double speed, bool fast, std::int64_t start_ts)
      : pub_(std::move(pub)), speed_(speed), fast_(fast), last_ts_(start_ts) {
    thread_ = std::thread([this] { run(); });
  }
  ~PlayClock() {
    {
      std::lock_guard l(mu_);
      stop_ = true;
    }
    cv_.notify_all();
    thread_.join();
  }
  PlayClock(const PlayClock&) = delete;
  PlayClock& operator=(const PlayClock&) = delete;

  // The event of log time `ts` is due at `mono` (CLOCK_MONOTONIC ns): the clock runs from there.
  void rebase(std::int64_t mono, std::int64_t ts) {
    std::lock_guard l(mu_);
    base_ns_ = mono;
    base_ts_ = ts;
    have_base_ = true;
  }
  // An event of log time `ts` was published.
  void event(std::int64_t ts) {
    std::lock_guard l(mu_);
    last_ts_ = ts;
  }
  // Pausing stops the clock where it is; resuming publishes at once (call rebase() first).
  void pause(bool paused) {
    {
      std::lock_guard l(mu_);
      if (paused == paused_) return;
      if (paused) last_ts_ = now_locked();
      paused_ = paused;
      changed_ = true;
    }
    cv_.notify_all();
  }

 private:
  std::int64_t now_locked() const {
    if (fast_ || paused_ || !have_base_) return last_ts_;
    return base_ts_ + static_cast<std::int64_t>(static_cast<double>(mono_ns() - base_ns_) * speed_ / 1000.0);
  }
  void run() {
    std::unique_lock l(mu_);
    while (!stop_) {
      lcmx_msgs::play_clock_t m{};
      m.log_utime = now_locked();
      m.speed = fast_ ? 0.0 : speed_;
      m.paused = paused_;
      changed_ = false;
      l.unlock();
      try {
        pub_.publish(m);
      } catch (const std::exception& e) {
        spdlog::warn("lcmx play: clock: {}", e.what());
      }
      l.lock();
      cv_.wait_for(l, std::chrono::milliseconds(50), [this] { return stop_ || changed_; });
    }
  }

  Publisher<lcmx_msgs::play_clock_t> pub_;  // the clock thread's only
  const double speed_;
  const bool fast_;
  std::mutex mu_;
  std::condition_variable cv_;
  bool stop_ = false, paused_ = false, changed_ = false, have_base_ = false;
  std::int64_t base_ns_ = 0, base_ts_ = 0, last_ts_ = 0;
  std::thread thread_;
};

struct ChannelInfo {
  std::int64_t fingerprint = 0;
  bool mixed = false;  // messages with different first 8 bytes: announced as raw
  std::uint64_t count = 0;
  std::size_t max_size = 0;
};

std::int64_t fingerprint_of(const std::vector<std::byte>& d) {
  if (d.size() < 8) return 0;
  std::uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | std::to_integer<std::uint8_t>(d[static_cast<std::size_t>(i)]);
  return static_cast<std::int64_t>(v);
}

// Terminal in non-canonical mode without echo while playing (restored on destruction).
class RawTerminal {
 public:
  RawTerminal() {
    if (!::isatty(STDIN_FILENO) || ::tcgetattr(STDIN_FILENO, &saved_) != 0) return;
    termios t = saved_;
    t.c_lflag &= static_cast<tcflag_t>(~(ICANON | ECHO));
    t.c_cc[VMIN] = 1;
    t.c_cc[VTIME] = 0;
    active_ = ::tcsetattr(STDIN_FILENO, TCSANOW, &t) == 0;
  }
  ~RawTerminal() {
    if (active_) ::tcsetattr(STDIN_FILENO, TCSANOW, &saved_);
  }
  bool active() const { return active_; }

 private:
  termios saved_{};
  bool active_ = false;
};

// Reads the keyboard (space: pause/resume, q: quit) or, when stdin is no terminal, lines
// "pause" / "resume" / "toggle" / "quit". EOF ends reading (not playing).
void input_loop(bool tty, std::atomic<bool>& done) {
  std::string line;
  while (!done.load()) {
    pollfd p{STDIN_FILENO, POLLIN, 0};
    if (::poll(&p, 1, 100) <= 0) continue;
    char buf[256];
    const ssize_t n = ::read(STDIN_FILENO, buf, sizeof buf);
    if (n <= 0) return;
    for (ssize_t i = 0; i < n; ++i) {
      const char c = buf[i];
      if (tty) {
        if (c == ' ') g_paused.store(!g_paused.load());
        if (c == 'q' || c == 'Q') g_quit.store(true);
        continue;
      }
      if (c != '\n') {
        if (line.size() < 64) line += c;
        continue;
      }
      if (line == "pause") g_paused.store(true);
      else if (line == "resume") g_paused.store(false);
      else if (line == "toggle" || line == " ") g_paused.store(!g_paused.load());
      else if (line == "quit" || line == "q") g_quit.store(true);
      line.clear();
    }
  }
}

std::string hex64(std::int64_t v) {
  char b[20];
  std::snprintf(b, sizeof b, "%016llx", static_cast<unsigned long long>(v));
  return b;
}

std::string bar(double frac, int width) {
  frac = std::clamp(frac, 0.0, 1.0);
  const int full = static_cast<int>(std::lround(frac * width));
  return "[" + std::string(static_cast<std::size_t>(full), '#') +
         std::string(static_cast<std::size_t>(width - full), '.') + "]";
}

}  // namespace

int run_play();

Verb add_play(CLI::App& app, const Globals& g) {
  g_play.g = &g;
  auto* c = app.add_subcommand(
      "play",
      "replay an LCM log file through lcmx (typed subscribers on every path receive it; --udp "
      "also for stock LCM programs)");
  c->add_option("file", g_play.file, "LCM log file (lcm-logger or lcmx record)")->required();
  c->add_option("--speed", g_play.speed, "playback speed factor (2: twice as fast)")
      ->check(positive_number())
      ->capture_default_str();
  c->add_flag("--fast", g_play.fast, "publish as fast as possible (ignore timestamps)");
  c->add_flag("--loop", g_play.loop, "start over at the end, until stopped");
  c->add_option("-c,--channel", g_play.channel, "play channels whose whole name matches this regular expression")
      ->capture_default_str();
  c->add_option("-x,--exclude", g_play.exclude, "leave out channels matching this expression (repeatable)")
      ->allow_extra_args(false);
  c->add_option("--start", g_play.start_s, "begin this many seconds after the log's first event")
      ->check(non_negative_number());
  c->add_option("--end", g_play.end_s, "stop this many seconds after the log's first event")
      ->check(non_negative_number());
  c->add_option("--delay", g_play.delay_s,
                "seconds between advertising the channels and the first message (lets running "
                "subscribers connect)")
      ->check(non_negative_number())
      ->capture_default_str();
  c->add_flag("--paused", g_play.paused, "start paused (space bar, or \"resume\" on stdin, to start)");
  c->add_option("--remap", g_play.remap, "publish channel FROM as TO: FROM=TO (repeatable)")
      ->allow_extra_args(false);
  c->add_flag("--udp", g_play.udp,
              "also send on the UDP groups for stock LCM programs (host-local group; the "
              "vehicle group too when configured); small messages only (<= LCMX_UDP_LIMIT)");
  c->add_option("--wait-subscribers", g_play.wait_subscribers,
                "before playing, wait until this many subscribers are matched (over all "
                "channels), at most --wait-timeout seconds")
      ->check(non_negative_number());
  c->add_option("--wait-timeout", g_play.wait_timeout_s, "seconds --wait-subscribers waits at most")
      ->check(positive_number())
      ->capture_default_str();
  c->add_option("--spin-us", g_play.spin_us,
                "spin (instead of sleeping) this many microseconds before each message is due")
      ->check(CLI::Range(0, 100000))
      ->capture_default_str();
  c->add_option("--rt-priority", g_play.rt_priority,
                "play from a SCHED_FIFO thread of this priority (1-99; needs CAP_SYS_NICE): due "
                "times are kept on a busy machine too")
      ->check(CLI::Range(0, 99));
  c->add_flag("--stop-on-damage", g_play.stop_on_damage, "stop at the first damaged part of the log");
  c->add_flag("--no-clock", g_play.no_clock,
              "do not publish the log's clock on " + std::string(foxglove::kPlayClockChannel) +
                  " (lcmx_msgs.play_clock_t: what `lcmx foxglove` shows as the viewers' time)");
  c->add_flag("-q,--quiet", g_play.quiet, "no progress bar and no summary (errors only)");
  c->add_flag("--json", g_play.json, "print the summary as JSON on stdout");
  c->footer("On a terminal: space pauses and resumes, q quits. Otherwise stdin lines pause, "
            "resume, toggle, quit do the same.");
  return {c, [] { return run_play(); }};
}

int run_play() {
  const auto& o = g_play;
  spdlog::set_level(spdlog::level::warn);
  std::optional<ChannelFilter> filter;
  try {
    filter.emplace(o.channel, o.exclude);
  } catch (const std::regex_error& e) {
    std::cerr << "lcmx play: bad channel expression: " << e.what() << "\n";
    return 2;
  }
  std::map<std::string, std::string> remap;
  for (const auto& r : o.remap) {
    const auto eq = r.find('=');
    if (eq == std::string::npos || eq == 0 || eq + 1 == r.size() || r.size() - eq - 1 > kMaxChannelLength) {
      std::cerr << "lcmx play: --remap '" << r << "': expected FROM=TO (TO at most 63 bytes)\n";
      return 2;
    }
    remap[r.substr(0, eq)] = r.substr(eq + 1);
  }
  if (o.end_s >= 0 && o.end_s <= o.start_s) {
    std::cerr << "lcmx play: --end must be after --start\n";
    return 2;
  }

  // Pass 1: headers and the first 8 data bytes of every event.
  std::map<std::string, ChannelInfo> info;
  std::int64_t first_ts = 0, last_ts = 0;
  std::uint64_t events = 0;
  std::vector<eventlog::Damage> damage;
  try {
    eventlog::ReaderOptions ro;
    ro.data_prefix = 8;
    auto r = eventlog::Reader::open(o.file, ro);
    eventlog::Event e;
    while (r.next(e)) {
      if (events == 0) first_ts = e.timestamp_us;
      last_ts = std::max(last_ts, e.timestamp_us);
      ++events;
      auto& ci = info[e.channel];
      const auto fp = fingerprint_of(e.data);
      if (ci.count == 0) ci.fingerprint = fp;
      else if (ci.fingerprint != fp) ci.mixed = true;
      ++ci.count;
      ci.max_size = std::max(ci.max_size, e.size);
    }
    damage = r.damage();
  } catch (const std::exception& e) {
    std::cerr << "lcmx play: " << e.what() << "\n";
    return 1;
  }
  if (events == 0) {
    std::cerr << "lcmx play: '" << o.file << "' holds no readable event";
    if (!damage.empty()) std::cerr << " (" << damage.size() << " damaged regions)";
    std::cerr << "\n";
    return 1;
  }
  const double duration_s = static_cast<double>(last_ts - first_ts) / 1e6;
  const std::int64_t from_ts = first_ts + static_cast<std::int64_t>(o.start_s * 1e6);
  const std::int64_t to_ts = o.end_s >= 0 ? first_ts + static_cast<std::int64_t>(o.end_s * 1e6) : INT64_MAX;

  struct sigaction sa{};
  sa.sa_handler = on_play_signal;
  sigemptyset(&sa.sa_mask);
  ::sigaction(SIGINT, &sa, nullptr);
  ::sigaction(SIGTERM, &sa, nullptr);
  ::prctl(PR_SET_TIMERSLACK, 1UL, 0, 0, 0);

  std::optional<Runtime> rt;
  std::optional<Node> node;
  std::map<std::string, RawPublisher> pubs;  // by original channel
  std::map<std::string, std::int64_t> announced;  // by published channel
  std::optional<PlayClock> clock;
  try {
    rt.emplace(Runtime::create(runtime_options(*o.g, o.udp)));
    node.emplace(rt->create_node("lcmx_play"));
    std::map<std::string, RawPublisher> by_out;
    for (const auto& [ch, ci] : info) {
      if (!(*filter)(ch)) continue;
      if (ch == discovery::kBeaconChannel) {
        // Recorded beacons (lcm-logger records them too) would announce the processes of
        // the recording as alive here: `lcmx nodes` and `topics` would list ghosts.
        std::cerr << "lcmx play: " << ci.count << " events of " << printable(ch)
                  << " (lcmx's discovery beacons) not played: they would announce the recorded processes as alive\n";
        continue;
      }
      if (ch == foxglove::kPlayClockChannel && !o.no_clock) {
        // A clock recorded from an earlier play: two clocks would fight. --no-clock plays it.
        std::cerr << "lcmx play: " << ci.count << " events of " << ch
                  << " (a recorded play clock) not played: this play publishes its own (--no-clock plays them)\n";
        continue;
      }
      auto it = remap.find(ch);
      const std::string out = it == remap.end() ? ch : it->second;
      if (out.size() > kMaxChannelLength) {
        std::cerr << "lcmx play: channel '" << printable(ch) << "' is longer than 63 bytes: skipped (use --remap)\n";
        continue;
      }
      if (!by_out.count(out)) {
        PublisherOptions po;
        po.max_message_size = std::max<std::size_t>(po.max_message_size, ci.max_size);
        // Slots sized for the channel's largest message now: growing the segment mid-play
        // (a new generation, page faults) would delay the messages after it by milliseconds.
        po.shm_initial_slot_size = std::max<std::size_t>(po.shm_initial_slot_size, ci.max_size);
        const std::int64_t fp = ci.mixed ? 0 : ci.fingerprint;
        by_out.emplace(out, fp == 0 ? node->advertise_raw(out, po)
                                    : node->advertise_raw(out, "lcm-log:" + hex64(fp), fp, po));
        announced[out] = fp;
      }
      pubs[ch] = by_out.at(out);
    }
  } catch (const std::exception& e) {
    std::cerr << "lcmx play: " << e.what() << "\n";
    return 1;
  }
  if (pubs.empty()) {
    std::cerr << "lcmx play: no channel of the log matches the channel expressions\n";
    return 1;
  }
  if (!o.no_clock) {
    try {
      clock.emplace(node->advertise<lcmx_msgs::play_clock_t>(foxglove::kPlayClockChannel), o.speed, o.fast, from_ts);
    } catch (const std::exception& e) {
      std::cerr << "lcmx play: cannot publish the clock on " << foxglove::kPlayClockChannel << ": " << e.what() << "\n";
      return 1;
    }
  }
  if (o.wait_subscribers > 0) {
    const auto deadline = Clock::now() + std::chrono::duration<double>(o.wait_timeout_s);
    for (;;) {
      std::size_t n = 0;
      for (auto& [ch, p] : pubs) n += p.subscriber_count();
      if (static_cast<int>(n) >= o.wait_subscribers) break;
      if (Clock::now() >= deadline || g_quit.load()) {
        std::cerr << "lcmx play: only " << n << " of " << o.wait_subscribers
                  << " subscribers after " << o.wait_timeout_s << " s; playing anyway\n";
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
  }
  if (o.delay_s > 0) {
    const auto until = Clock::now() + std::chrono::duration<double>(o.delay_s);
    while (Clock::now() < until && !g_quit.load()) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }

  const bool tty_out = !o.quiet && ::isatty(STDERR_FILENO);
  RawTerminal term;
  std::atomic<bool> input_done{false};
  g_paused.store(o.paused);
  std::thread input([&] { input_loop(term.active(), input_done); });
  if (!o.quiet) {
    std::cerr << "lcmx play: playing " << o.file << " (" << events << " events, " << fmt("%.3f", duration_s)
              << " s, " << pubs.size() << " channels)" << (o.paused ? " paused" : "") << std::endl;
  }

  int rc = 0;
  if (o.rt_priority > 0) {
    // Only this (the playing) thread: the runtime's and the input threads exist already
    // and keep the default policy (threads inherit it from their creator).
    sched_param sp{};
    sp.sched_priority = o.rt_priority;
    if (const int e = ::pthread_setschedparam(::pthread_self(), SCHED_FIFO, &sp); e != 0) {
      std::cerr << "lcmx play: --rt-priority " << o.rt_priority << ": " << std::strerror(e) << "\n";
      g_quit.store(true);
      rc = 1;
    }
  }
  // Pass 2: play.
  std::map<std::string, std::uint64_t> sent;
  std::vector<std::int64_t> late_ns;
  late_ns.reserve(std::min<std::uint64_t>(events, 1u << 22));
  std::uint64_t published = 0, loops = 0;
  std::string stopped_at;
  std::size_t damage_reported = 0;
  const std::int64_t spin_ns = std::int64_t{o.spin_us} * 1000;
  try {
    auto r = eventlog::Reader::open(o.file);
    eventlog::Event e;
    bool have_base = false;
    std::int64_t base_ns = 0, base_ts = 0;
    auto last_progress = Clock::now() - std::chrono::seconds(1);
    // The progress bar (terminal only): position / duration, messages, speed, pause state.
    auto progress = [&](std::int64_t ts, bool force) {
      if (!tty_out || (!force && Clock::now() - last_progress < std::chrono::milliseconds(200))) return;
      last_progress = Clock::now();
      const double pos = static_cast<double>(ts - first_ts) / 1e6;
      std::cerr << "\r\x1b[K" << bar(duration_s > 0 ? pos / duration_s : 1.0, 30) << " " << fmt("%.1f", pos)
                << " / " << fmt("%.1f", duration_s) << " s  " << published << " msgs"
                << (o.fast ? "" : "  x" + fmt("%g", o.speed)) << (loops ? "  loop " + std::to_string(loops + 1) : "")
                << (g_paused.load() ? "  PAUSED (space)" : "") << std::flush;
    };
    auto wait_paused = [&](std::int64_t ts) {
      if (clock && g_paused.load()) clock->pause(true);
      while (g_paused.load() && !g_quit.load()) {
        progress(ts, false);
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
      }
    };
    for (;;) {
      if (g_quit.load()) break;
      if (!r.next(e)) {
        if (r.damage().size() > damage_reported) {
          const auto& d = r.damage().back();
          stopped_at = "the log ends with " + std::string(eventlog::to_string(d.kind)) + " bytes at offset " +
                       std::to_string(d.offset) + " (" + std::to_string(d.length) + " bytes)";
          damage_reported = r.damage().size();
        }
        if (!o.loop || published == 0) break;
        r = eventlog::Reader::open(o.file);
        damage_reported = 0;
        have_base = false;
        ++loops;
        continue;
      }
      for (; damage_reported < r.damage().size(); ++damage_reported) {
        const auto& d = r.damage()[damage_reported];
        if (!o.quiet)
          std::cerr << (tty_out ? "\r\x1b[K" : "") << "lcmx play: damaged log: " << d.length
                    << " bytes skipped at offset " << d.offset << ", resumed at offset " << e.offset << "\n";
        if (o.stop_on_damage) {
          stopped_at = "damage at offset " + std::to_string(d.offset) + " (--stop-on-damage)";
          g_quit.store(true);
        }
      }
      if (g_quit.load()) break;
      if (e.timestamp_us < from_ts) continue;
      if (e.timestamp_us > to_ts) {
        if (!o.loop) break;
        r.seek(r.size());  // to the end: the next call starts the next loop
        continue;
      }
      auto pit = pubs.find(e.channel);
      if (pit == pubs.end()) continue;
      if (!o.fast) {
        for (;;) {
          if (!have_base) {
            base_ns = mono_ns();
            base_ts = e.timestamp_us;
            have_base = true;
            if (clock) clock->rebase(base_ns, base_ts);
          }
          const std::int64_t due =
              base_ns + static_cast<std::int64_t>(static_cast<double>(e.timestamp_us - base_ts) * 1000.0 / o.speed);
          if (wait_until(due, spin_ns)) {
            late_ns.push_back(mono_ns() - due);
            break;
          }
          if (g_quit.load()) break;
          // Paused: wait, then continue from this event as if it were the first.
          const std::int64_t paused_at = mono_ns();
          wait_paused(e.timestamp_us);
          base_ns += mono_ns() - paused_at;
          if (clock) {
            clock->rebase(base_ns, base_ts);
            clock->pause(false);
          }
        }
        if (g_quit.load()) break;
      } else {
        wait_paused(e.timestamp_us);
        if (clock) clock->pause(false);
        if (g_quit.load()) break;
      }
      pit->second.publish(e.data);
      if (clock) clock->event(e.timestamp_us);
      ++published;
      ++sent[e.channel];
      progress(e.timestamp_us, false);
    }
  } catch (const std::exception& ex) {
    std::cerr << "\nlcmx play: " << ex.what() << "\n";
    rc = 1;
  }
  input_done.store(true);
  input.join();
  if (tty_out) std::cerr << "\r\x1b[K";

  std::sort(late_ns.begin(), late_ns.end());
  auto pct = [&](double p) -> double {
    if (late_ns.empty()) return 0;
    const auto i = std::min(late_ns.size() - 1, static_cast<std::size_t>(p * static_cast<double>(late_ns.size())));
    return static_cast<double>(late_ns[i]) / 1000.0;
  };
  if (o.json) {
    std::ostringstream j;
    j << "{\"file\":" << json_str(o.file) << ",\"events\":" << events << ",\"published\":" << published
      << ",\"loops\":" << loops << ",\"duration_s\":" << fmt("%.6f", duration_s)
      << ",\"late_us\":{\"p50\":" << fmt("%.1f", pct(0.5)) << ",\"p99\":" << fmt("%.1f", pct(0.99))
      << ",\"max\":" << fmt("%.1f", late_ns.empty() ? 0.0 : static_cast<double>(late_ns.back()) / 1000.0)
      << "},\"channels\":[";
    bool first = true;
    for (const auto& [ch, ci] : info) {
      auto rit = remap.find(ch);
      j << (first ? "" : ",") << "{\"channel\":" << json_str(ch) << ",\"published_as\":"
        << json_str(rit == remap.end() ? ch : rit->second) << ",\"in_log\":" << ci.count
        << ",\"published\":" << (sent.count(ch) ? sent[ch] : 0) << ",\"fingerprint\":\""
        << hex64(ci.mixed ? 0 : ci.fingerprint) << "\""
        << "}";
      first = false;
    }
    j << "],\"damage\":[";
    for (std::size_t i = 0; i < damage.size(); ++i)
      j << (i ? "," : "") << "{\"kind\":\"" << eventlog::to_string(damage[i].kind) << "\",\"offset\":"
        << damage[i].offset << ",\"length\":" << damage[i].length << "}";
    j << "]";
    if (!stopped_at.empty()) j << ",\"stopped\":" << json_str(stopped_at);
    j << "}";
    std::cout << j.str() << std::endl;
  } else if (!o.quiet) {
    std::cout << "lcmx play: published " << published << " of " << events << " events";
    if (loops) std::cout << " (" << loops + 1 << " loops)";
    if (!o.fast && !late_ns.empty())
      std::cout << "; publish time vs due: p50 " << fmt("%.1f", pct(0.5)) << " us, p99 " << fmt("%.1f", pct(0.99))
                << " us";
    std::cout << "\n";
  }
  if (!stopped_at.empty()) std::cerr << "lcmx play: stopped: " << stopped_at << "\n";
  clock.reset();
  node.reset();
  pubs.clear();
  rt.reset();
  return rc;
}

}  // namespace lcmx::cli
