// lcmx_bench_wait (issue 15 item 5): what an executor's WaitStrategy costs and buys, on the
// demo's traffic, between two processes of one host over shared memory.
//
// For each strategy (block, adaptive, spin = spin_then_block; --waits) and each round, the
// orchestrator starts a subscriber child and a publisher child (both with that strategy on
// every node) and runs four phases back to back, measuring the subscriber process:
//   idle      nothing is published for --idle seconds (matched, quiet): CPU %
//   demo      the single-host demo's traffic for --seconds: a 1920x1080 rgb8 image_t (6 MB)
//             at 30 Hz and a pose_t at 100 Hz, from one publisher process: CPU %, one-way
//             latency p50/p99 per topic
//   stream    a pose_t at 1 kHz for --seconds (a message every 1 ms, longer than any spin
//             window): CPU %, latency; the case where a spin costs and buys nothing
//   pingpong  a pose_t "ping" answered by a "pong" from the subscriber's callback, the next
//             ping sent from the publisher's pong callback, --pings times: round trip
//             p50/p99 (a request/response exchange: both sides wait with the strategy)
// CPU % = (user + system time of the subscriber process over the phase) / wall time of the
// phase: every thread of that process (executors, discovery) counts.
//
// Children are this binary with a hidden --role; they talk to the orchestrator over pipes
// (bench/harness/process.hpp): each reports lines on fd 3, the orchestrator sends one control
// byte per phase on fd 5; nothing sleeps to synchronise (the publisher paces its traffic with
// sleep_until, as the demo does). Latencies are nearest-rank percentiles (bench/harness/stats.hpp).
#include <sys/resource.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <iostream>
#include <map>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "harness/options.hpp"
#include "harness/process.hpp"
#include "harness/report.hpp"
#include "harness/stats.hpp"
#include "lcmx/core.hpp"
#include "lcmx_examples/image_t.hpp"
#include "lcmx_examples/pose_t.hpp"

namespace {

using lcmxbench::now_ns;
constexpr int kPhaseFd = 5;  // orchestrator -> child: one control byte per phase
using Clock = std::chrono::steady_clock;

struct Options {
  std::vector<std::string> waits{"block", "adaptive", "spin"};
  int rounds = 2;
  double idle = 3, seconds = 3;
  int pings = 2000;
  int spin_us = 50;
  std::string url = "udpm://239.255.77.215:17715?ttl=0&iface=lo";
  // hidden, children only
  std::string role, name, wait;
};

lcmx::NodeOptions node_options(const Options& o) {
  lcmx::NodeOptions n;
  n.executor.wait = lcmxbench::wait_strategy(o.wait);
  n.executor.spin = std::chrono::microseconds(o.spin_us);
  return n;
}

lcmx::RuntimeOptions runtime_options(const Options& o) {
  lcmx::RuntimeOptions r;  // never from_env(): the bench never uses the default group
  r.discovery_url = o.url;
  return r;
}

std::string ch(const Options& o, const char* what) { return "LCMXWAIT_" + o.name + "_" + what; }

double cpu_seconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         static_cast<double>(u.ru_utime.tv_usec + u.ru_stime.tv_usec) * 1e-6;
}

// Reads one control byte from fd (blocking); 0 on EOF.
char read_ctl(int fd) {
  char c = 0;
  for (;;) {
    const auto n = ::read(fd, &c, 1);
    if (n == 1) return c;
    if (n == 0 || errno != EINTR) return 0;
  }
}
void write_ctl(int fd, char c) {
  while (::write(fd, &c, 1) < 0 && errno == EINTR) {
  }
}

// "<p50> <p99>" in µs of latencies in ns, "- -" when there are none.
std::string percentiles(const std::vector<std::int64_t>& v) {
  if (v.empty()) return "- -";
  const auto st = lcmxbench::stats_of_ns(v);
  char b[64];
  std::snprintf(b, sizeof b, "%.1f %.1f", st.p50, st.p99);
  return b;
}

// ---- subscriber child: reports "ready", then per control byte: 'P' phase start, 'Q' phase
// end (reports "cpu <percent> <camera count> <p50> <p99> <pose count> <p50> <p99>", µs), 'E' exit.
int run_sub(const Options& o) {
  auto rt = lcmx::Runtime::create(runtime_options(o));
  auto cam_node = rt.create_node("wait_cam", node_options(o));
  auto pose_node = rt.create_node("wait_pose", node_options(o));
  std::mutex mu;
  std::vector<std::int64_t> cam_lat, pose_lat;  // of the current phase
  auto record = [&](std::vector<std::int64_t>& lat, std::int64_t stamp) {
    const auto l = now_ns() - stamp;
    std::lock_guard lock(mu);
    lat.push_back(l);
  };
  auto pong = pose_node.advertise<lcmx_examples::pose_t>(ch(o, "PONG"));
  auto cam = cam_node.subscribe<lcmx_examples::image_t>(ch(o, "CAM"), [&](const lcmx_examples::image_t& m) { record(cam_lat, m.header.stamp_ns); });
  auto pose = pose_node.subscribe<lcmx_examples::pose_t>(ch(o, "POSE"), [&](const lcmx_examples::pose_t& m) { record(pose_lat, m.header.stamp_ns); });
  auto ping = pose_node.subscribe<lcmx_examples::pose_t>(ch(o, "PING"), [&](const lcmx_examples::pose_t& m) { pong.publish(m); });
  if (!pong.wait_for_subscribers(1, std::chrono::seconds(15)) || !ping.wait_for_publishers(1, std::chrono::seconds(15))) {
    lcmxbench::report_error("subscriber: publisher not matched within 15 s");
    return 1;
  }
  lcmxbench::report_line("ready");
  double cpu0 = 0;
  std::int64_t wall0 = 0;
  for (;;) {
    const char c = read_ctl(kPhaseFd);
    if (c == 'P') {
      std::lock_guard lock(mu);
      cam_lat.clear(), pose_lat.clear();
      cpu0 = cpu_seconds();
      wall0 = now_ns();
    } else if (c == 'Q') {
      const double pct = 100.0 * (cpu_seconds() - cpu0) / (static_cast<double>(now_ns() - wall0) * 1e-9);
      std::vector<std::int64_t> cams, poses;
      {
        std::lock_guard lock(mu);
        cams = cam_lat, poses = pose_lat;
      }
      char b[64];
      std::snprintf(b, sizeof b, "%.2f", pct);
      lcmxbench::report_line(std::string("cpu ") + b + " " + std::to_string(cams.size()) + " " + percentiles(cams) + " " +
                             std::to_string(poses.size()) + " " + percentiles(poses));
    } else {
      return 0;
    }
  }
}

// ---- publisher child: per control byte 'D' demo traffic, 'S' 1 kHz stream, 'G' ping-pong,
// 'E' exit; writes "done ..." after each.
int run_pub(const Options& o) {
  auto rt = lcmx::Runtime::create(runtime_options(o));
  auto node = rt.create_node("wait_pub", node_options(o));
  auto cam = node.advertise<lcmx_examples::image_t>(ch(o, "CAM"));
  auto pose = node.advertise<lcmx_examples::pose_t>(ch(o, "POSE"));
  auto ping = node.advertise<lcmx_examples::pose_t>(ch(o, "PING"));
  std::mutex mu;
  std::vector<std::int64_t> rtt;
  std::atomic<int> left{0};
  std::condition_variable done_cv;
  bool finished = false;  // under mu
  lcmx_examples::pose_t msg{};
  msg.header.frame_id = "base_link";
  msg.orientation[3] = 1.0;
  auto pong = node.subscribe<lcmx_examples::pose_t>(ch(o, "PONG"), [&](const lcmx_examples::pose_t& m) {
    {
      std::lock_guard lock(mu);
      rtt.push_back(now_ns() - m.header.stamp_ns);
    }
    if (left.fetch_sub(1) > 1) {
      lcmx_examples::pose_t next = m;
      next.header.seq = m.header.seq + 1;
      next.header.stamp_ns = now_ns();
      ping.publish(next);
    } else {
      std::lock_guard lock(mu);
      finished = true;
      done_cv.notify_all();
    }
  });
  if (!cam.wait_for_subscribers(1, std::chrono::seconds(15)) || !pose.wait_for_subscribers(1, std::chrono::seconds(15)) ||
      !ping.wait_for_subscribers(1, std::chrono::seconds(15)) || !pong.wait_for_publishers(1, std::chrono::seconds(15))) {
    lcmxbench::report_error("publisher: subscriber not matched within 15 s");
    return 1;
  }
  lcmx_examples::image_t frame;
  frame.width = 1920, frame.height = 1080, frame.stride = 1920 * 3, frame.encoding = "rgb8";
  frame.size = frame.stride * frame.height;
  frame.data.assign(static_cast<std::size_t>(frame.size), 0);
  frame.header.frame_id = "camera";
  const auto run = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(o.seconds));
  for (;;) {
    const char c = read_ctl(kPhaseFd);
    if (c == 'D' || c == 'S') {
      const auto start = Clock::now();
      const auto cam_period = std::chrono::microseconds(33'333);
      const auto pose_period = c == 'D' ? std::chrono::microseconds(10'000) : std::chrono::microseconds(1'000);
      auto next_cam = start, next_pose = start;
      std::int64_t n = 0;
      while (Clock::now() - start < run) {
        const auto now = Clock::now();
        if (c == 'D' && now >= next_cam) {
          frame.header.seq = n;
          frame.header.stamp_ns = now_ns();
          cam.publish(frame);
          next_cam += cam_period;
        }
        if (now >= next_pose) {
          msg.header.seq = n++;
          msg.header.stamp_ns = now_ns();
          pose.publish(msg);
          next_pose += pose_period;
        }
        std::this_thread::sleep_until(c == 'D' ? std::min(next_cam, next_pose) : next_pose);  // pacing
      }
      lcmxbench::report_line("done");
    } else if (c == 'G') {
      {
        std::lock_guard lock(mu);
        rtt.clear();
        finished = false;
      }
      left = o.pings;
      msg.header.seq = 0;
      msg.header.stamp_ns = now_ns();
      ping.publish(msg);
      // A lost ping would stall the chain: bounded wait, then report what came.
      std::vector<std::int64_t> copy;
      {
        std::unique_lock lock(mu);
        done_cv.wait_for(lock, std::chrono::seconds(30), [&] { return finished; });
        copy = rtt;
      }
      lcmxbench::report_line("done " + std::to_string(copy.size()) + " " + percentiles(copy));
    } else {
      return 0;
    }
  }
}

struct Row {
  std::string wait;
  double idle_cpu = 0, demo_cpu = 0, stream_cpu = 0;
  std::string cam_lat, demo_pose_lat, stream_lat, pingpong;
};

// One round of one strategy. Throws std::runtime_error on a child failure.
Row run_round(const Options& o, const std::string& wait, int round) {
  const std::string name = std::to_string(getpid()) + "_" + wait + "_" + std::to_string(round);
  const std::string exe = lcmxbench::self_exe();
  std::vector<std::string> common{"--url", o.url, "--name", name, "--wait", wait, "--spin-us", std::to_string(o.spin_us),
                                  "--pings", std::to_string(o.pings), "--seconds", std::to_string(o.seconds)};
  auto argv = [&](const char* role) {
    std::vector<std::string> a{exe, "--role", role};
    a.insert(a.end(), common.begin(), common.end());
    return a;
  };
  lcmxbench::Pipe sub_rep, sub_ctl, pub_rep, pub_ctl;
  const pid_t sub = lcmxbench::spawn_child(argv("sub"), {sub_rep.w, -1, sub_ctl.r}, -1);
  const pid_t pub = lcmxbench::spawn_child(argv("pub"), {pub_rep.w, -1, pub_ctl.r}, -1);
  sub_rep.close_w(), sub_ctl.close_r(), pub_rep.close_w(), pub_ctl.close_r();
  lcmxbench::LineReader sr, pr;
  sr.fd = sub_rep.r, pr.fd = pub_rep.r;
  auto fail = [&](const std::string& why) {
    write_ctl(sub_ctl.w, 'E'), write_ctl(pub_ctl.w, 'E');
    sub_ctl.close_w(), pub_ctl.close_w();
    lcmxbench::reap_child(sub, 3000), lcmxbench::reap_child(pub, 3000);
    std::string detail;
    for (auto* r : {&sr, &pr})
      for (auto& l : r->lines) detail += " [" + l + "]";
    throw std::runtime_error(wait + ": " + why + detail);
  };
  auto lines = [](lcmxbench::LineReader& r, const std::string& prefix) {
    return static_cast<std::size_t>(std::count_if(r.lines.begin(), r.lines.end(), [&](auto& l) { return l.rfind(prefix, 0) == 0; }));
  };
  auto wait_for = [&](lcmxbench::LineReader& r, const std::string& prefix, std::size_t count, int seconds) {
    if (!lcmxbench::pump_until({&sr, &pr}, now_ns() + seconds * 1'000'000'000LL, [&] { return lines(r, prefix) >= count || lines(sr, "error") || lines(pr, "error"); }) ||
        lines(r, prefix) < count)
      fail("no '" + prefix + "' line in time");
  };
  wait_for(sr, "ready", 1, 20);
  auto last_cpu = [&] {
    std::string l;
    for (auto& x : sr.lines)
      if (x.rfind("cpu ", 0) == 0) l = x;
    std::istringstream in(l.substr(4));
    double pct = 0;
    std::size_t nc = 0, np = 0;
    std::string c50, c99, p50, p99;
    in >> pct >> nc >> c50 >> c99 >> np >> p50 >> p99;
    return std::tuple{pct, c50 + " / " + c99 + " (" + std::to_string(nc) + ")", p50 + " / " + p99 + " (" + std::to_string(np) + ")"};
  };
  Row row;
  row.wait = wait;
  // idle
  write_ctl(sub_ctl.w, 'P');
  std::this_thread::sleep_for(std::chrono::duration<double>(o.idle));  // the phase itself, not a synchronisation
  write_ctl(sub_ctl.w, 'Q');
  wait_for(sr, "cpu", 1, 10);
  row.idle_cpu = std::get<0>(last_cpu());
  // demo, stream
  std::size_t cpus = 1, dones = 0;
  for (char phase : {'D', 'S'}) {
    write_ctl(sub_ctl.w, 'P');
    write_ctl(pub_ctl.w, phase);
    wait_for(pr, "done", ++dones, static_cast<int>(o.seconds) + 20);
    write_ctl(sub_ctl.w, 'Q');
    wait_for(sr, "cpu", ++cpus, 10);
    const auto [pct, cam_lat, pose_lat] = last_cpu();
    if (phase == 'D') row.demo_cpu = pct, row.cam_lat = cam_lat, row.demo_pose_lat = pose_lat;
    else row.stream_cpu = pct, row.stream_lat = pose_lat;
  }
  write_ctl(pub_ctl.w, 'G');
  wait_for(pr, "done", ++dones, 40);
  {
    std::istringstream in(pr.lines.back().substr(5));
    std::size_t n = 0;
    std::string p50, p99;
    in >> n >> p50 >> p99;
    if (static_cast<int>(n) != o.pings) fail("ping-pong: " + std::to_string(n) + " of " + std::to_string(o.pings) + " round trips");
    row.pingpong = p50 + " / " + p99;
  }
  write_ctl(sub_ctl.w, 'E'), write_ctl(pub_ctl.w, 'E');
  sub_ctl.close_w(), pub_ctl.close_w();
  lcmxbench::reap_child(sub, 5000), lcmxbench::reap_child(pub, 5000);
  return row;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lcmx_bench_wait: CPU and latency of executor wait strategies on the demo's traffic (issue 15)"};
  Options o;
  app.add_option("--waits", o.waits, "strategies, run in this order each round: block, adaptive, spin, busy")
      ->delimiter(',')->check(CLI::IsMember({"block", "adaptive", "spin", "busy"}))->capture_default_str();
  app.add_option("--rounds", o.rounds, "rounds (strategies alternate within each)")->check(CLI::Range(1, 20))->capture_default_str();
  app.add_option("--idle", o.idle, "idle phase, seconds")->check(CLI::Range(0.5, 60.0))->capture_default_str();
  app.add_option("--seconds", o.seconds, "demo and stream phases, seconds each")->check(CLI::Range(0.5, 60.0))->capture_default_str();
  app.add_option("--pings", o.pings, "ping-pong round trips")->check(CLI::Range(10, 1000000))->capture_default_str();
  app.add_option("--spin-us", o.spin_us, "ExecutorOptions::spin (spin and adaptive window), µs")->check(CLI::Range(1, 100000))->capture_default_str();
  app.add_option("--url", o.url, "lcmx discovery URL (never the default group)")->capture_default_str();
  lcmxbench::add_hidden(app, "--role", o.role);
  lcmxbench::add_hidden(app, "--name", o.name);
  lcmxbench::add_hidden(app, "--wait", o.wait);
  CLI11_PARSE(app, argc, argv);
  try {
    if (!o.role.empty()) lcmxbench::log_to_stderr(o.role, "");  // stdout is the orchestrator's report
    if (o.role == "sub") return run_sub(o);
    if (o.role == "pub") return run_pub(o);
    if (!o.role.empty()) {
      std::cerr << "unknown role " << o.role << "\n";
      return 2;
    }
    std::vector<Row> rows;
    for (int r = 0; r < o.rounds; ++r)
      for (auto& w : o.waits) {
        std::cerr << "round " << r + 1 << "/" << o.rounds << ": " << w << "\n";
        rows.push_back(run_round(o, w, r));
      }
    std::printf("lcmx_bench_wait: %d round(s), idle %.1f s, demo and 1 kHz stream %.1f s each, %d ping-pongs, spin %d µs; "
                "subscriber process CPU %% (all its threads); latency p50 / p99 µs\n\n",
                o.rounds, o.idle, o.seconds, o.pings, o.spin_us);
    lcmxbench::Table table({"wait", "idle CPU %", "demo CPU %", "demo camera 6 MB", "demo pose", "1 kHz pose CPU %",
                            "1 kHz pose", "ping-pong round trip"},
                           "lrrllrll");
    auto pct = [](double v) {
      char b[32];
      std::snprintf(b, sizeof b, "%.2f", v);
      return std::string(b);
    };
    for (auto& r : rows)
      table.row({r.wait, pct(r.idle_cpu), pct(r.demo_cpu), r.cam_lat, r.demo_pose_lat, pct(r.stream_cpu), r.stream_lat,
                 r.pingpong});
    std::fputs(table.markdown().c_str(), stdout);
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "lcmx_bench_wait: " << e.what() << "\n";
    return 1;
  }
}
