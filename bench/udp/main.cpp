// lcmx_bench_udp: one-way latency and loss between two emulated hosts (bench/harness/hosts.hpp),
// lcmx's UDP path (Publisher<bench_t> -> Subscriber<bench_t> on another host over the vehicle
// group) side by side with raw liblcm udpm between the same namespaces, in one run (DESIGN.md
// "Benchmarks", experiment 1, UDP row).
//
//  - ping-pong per size (the harness's protocol, bench/harness/pingpong.hpp): acks go through a
//    pipe (pipes do not care about network namespaces), so the link only carries the measured
//    traffic. The methods run in --rounds rounds, in alternating order (liblcm, lcmx / lcmx,
//    liblcm, ...), and each method's rounds are pooled: slow drifts of a shared machine hit both
//    alike.
//  - stream, two scenarios per method: "idle" (--stream-messages messages of --stream-size at
//    --stream-rate Hz to an idle receiving host) and "busy" (the same messages in bursts of
//    --stream-burst back to back per tick, like a camera's frame set, while --stream-hogs CPU
//    hog processes run in the receiving host's namespace at the same nice level, started before
//    the subscriber for both methods alike). No acks; loss = sent - received.
// Without --role this is the orchestrator: Markdown on stdout, progress on stderr. Root needed.
#include <unistd.h>

#include <fstream>
#include <iostream>
#include <sstream>

#include "harness/hosts.hpp"
#include "harness/options.hpp"
#include "harness/report.hpp"
#include "udp/roles.hpp"

namespace lcmxbench::udp {
namespace {

const char* const kProgram = "lcmx_bench_udp";
void say(const std::string& s) { progress("bench-udp", s); }

constexpr const char* kDiscoveryUrl = "udpm://239.255.77.221:17721?ttl=0";  // each host's own lo
constexpr const char* kVehicleUrl = "udpm://239.255.77.222:17722?ttl=1&iface=eth";
constexpr const char* kLcmUrl = "udpm://239.255.77.223:17723?ttl=1";  // liblcm: the 224/4 route (eth)

struct Options {
  std::vector<std::string> sizes{"1K", "10K", "100K", "1M", "2M", "6M"};
  int messages = 0, warmup = -1, timeout_ms = 200;
  std::string stream_size = "100K";
  double stream_rate = 30;
  int stream_messages = 150;
  int stream_burst = 4, stream_hogs = 2;  // "busy" scenario
  int rounds = 3;
  bool no_stream = false;
  LinkOptions link;  // rate: tc tbf on the link ("" = none)
  std::string pin = "none";
  std::string markdown;
};

struct Run {
  Options opt;
  std::vector<SizePlan> plan, stream_plan;
  lcmx::test::Emulation* emu = nullptr;
  std::string exe;
  Pinning cpus;
  int serial = 0;
};

// Stream scenario: messages per tick and CPU hogs on the receiving host.
struct Scenario {
  std::string name = "idle";
  int burst = 1, hogs = 0;
};

// method: "liblcm" | "lcmx-udp" (ping-pong), "liblcm-stream" | "lcmx-udp-stream".
MethodResult run_method(Run& run, const std::string& method, const Scenario& sc = {}) {
  const bool stream = method.find("stream") != std::string::npos;
  const bool liblcm = method.rfind("liblcm", 0) == 0;
  const auto& plan = stream ? run.stream_plan : run.plan;
  say(method + ": starting");
  const std::int64_t t0 = now_ns();
  std::int64_t budget_ms = 40'000;
  for (const auto& p : plan)
    budget_ms += stream ? static_cast<std::int64_t>(p.messages * 1000 / run.opt.stream_rate) + 5000
                        : static_cast<std::int64_t>(p.warmup + p.messages) * (run.opt.timeout_ms + 50);
  const std::string name = "UDP_" + std::to_string(::getpid()) + "_" + std::to_string(++run.serial);
  auto args = [&](const std::string& role) {
    return std::vector<std::string>{
        run.exe, "--role", role, "--plan", plan_to_string(plan), "--name", name, "--url",
        liblcm ? kLcmUrl : kDiscoveryUrl, "--vehicle-url", kVehicleUrl, "--timeout-ms",
        std::to_string(run.opt.timeout_ms), "--stream-rate", std::to_string(run.opt.stream_rate),
        "--stream-burst", std::to_string(sc.burst)};
  };
  const std::string base = liblcm ? "liblcm" : "lcmx-udp";
  Pair pair;
  pair.method = method;
  pair.sub_argv = args(base + (stream ? "-stream-sub" : "-sub"));
  pair.pub_argv = args(base + (stream ? "-stream-pub" : "-pub"));
  pair.sub_netns = run.emu->ns_fd(1);
  pair.pub_netns = run.emu->ns_fd(0);
  pair.sub_cpu = run.cpus.sub;
  pair.pub_cpu = run.cpus.pub;
  pair.deadline_ms = static_cast<int>(budget_ms);
  // Hogs first, unpinned, so the subscriber starts on an already busy host.
  std::vector<pid_t> hogs;
  for (int i = 0; i < sc.hogs; ++i) hogs.push_back(spawn_child({run.exe, "--role", "hog"}, {}, -1, run.emu->ns_fd(1)));
  MethodResult res = run_pair(pair).result;
  for (auto p : hogs) reap_child(p, 0);  // SIGKILLed and reaped
  progress_of("bench-udp", res, plan);
  char t[64];
  std::snprintf(t, sizeof t, "%.1f s", static_cast<double>(now_ns() - t0) / 1e9);
  say(method + ": finished in " + t);
  return res;
}

struct StreamResult {
  Scenario sc;
  MethodResult lcm, lx;
};

// Reads a one-number /proc/sys file ("?" if unreadable).
std::string sysctl(const char* path) {
  std::ifstream in(path);
  std::string v;
  return in >> v ? v : "?";
}

std::string report(const Run& run, const MethodResult& lcm, const MethodResult& lx,
                   const std::vector<StreamResult>& streams) {
  std::ostringstream md;
  md << "## lcmx UDP vs raw liblcm udpm between two emulated hosts\n\n";
  md << "- " << machine_line() << "; pinning `--pin " << run.opt.pin << "`\n";
  md << "- 2 network namespaces joined by a veth/bridge link"
     << (run.opt.link.rate.empty() ? " (no rate limit)" : " shaped to " + run.opt.link.rate + " (tbf)")
     << "; publisher on host 0, subscriber on host 1\n";
  md << "- lcmx: Publisher<bench_t> -> Subscriber<bench_t>, vehicle group `" << kVehicleUrl
     << "` (path udp; messages > udp_limit make the topic large and go as LC03 fragments), receive "
        "buffer 4 MiB (GroupConfig default, SO_RCVBUFFORCE), subscriber node `block`; liblcm: "
        "lcm_publish -> lcm_handle on `" << kLcmUrl << "`, kernel default receive buffer "
        "(net.core.rmem_default " << sysctl("/proc/sys/net/core/rmem_default") << ", rmem_max "
     << sysctl("/proc/sys/net/core/rmem_max") << ")\n";
  md << "- ping-pong rounds: " << run.opt.rounds
     << " per method, alternating order (liblcm first in odd rounds, lcmx first in even ones), "
        "pooled\n";
  md << "- ping-pong: next message after the ack (pipe side channel, not on the link) or after "
     << run.opt.timeout_ms << " ms = lost; messages per size (warmup + measured): " << plan_text(run.plan);
  md << "\n- cells: p50 / p99 one-way µs (send_ns before encode -> after decode, shared "
        "CLOCK_MONOTONIC), lost/sent; ratio = lcmx p50 / liblcm p50\n\n";
  Table table({"size", "liblcm udpm", "lcmx UDP", "lcmx/liblcm"});
  double worst = 0;
  std::size_t worst_size = 0;
  bool compared = false, missing = false;
  for (const auto& p : run.plan) {
    const Cell a = cell_of(lcm, p.size), b = cell_of(lx, p.size);
    std::string ratio = "—";
    if (a.ok && b.ok && a.st.n && b.st.n) {
      ratio = fmt_ratio(b.st.p50 / a.st.p50);
      if (a.lost == 0) {
        compared = true;
        if (b.st.p50 / a.st.p50 > worst) worst = b.st.p50 / a.st.p50, worst_size = p.size;
      }
    } else if (a.ok && a.lost == 0) {
      missing = true;
    }
    table.row({size_label(p.size), cell_text(lcm, p.size, true), cell_text(lx, p.size, true), ratio});
  }
  md << table.markdown();
  md << "\n**Targets**\n";
  md << "- lcmx UDP within 1.1x of raw liblcm at every size where liblcm loses nothing: ";
  if (!compared) md << "not measured (no size where both delivered and liblcm lost nothing)";
  else md << verdict(worst <= 1.1 && !missing) << " (worst " << fmt_ratio(worst) << " at " << size_label(worst_size)
          << (missing ? "; lcmx has no result at a size where liblcm lost nothing" : "") << ")";
  md << "\n";
  if (!streams.empty()) {
    const auto& sp = run.stream_plan.front();
    Table table({"scenario", "liblcm udpm", "lcmx UDP"});
    for (const auto& r : streams) {
      table.row({r.sc.name + ": " + std::to_string(r.sc.burst) + " message" + (r.sc.burst > 1 ? "s" : "") +
                     " per tick, " + std::to_string(r.sc.hogs) + " CPU hog" + (r.sc.hogs == 1 ? "" : "s") +
                     " on the receiving host",
                 cell_text(r.lcm, sp.size, true), cell_text(r.lx, sp.size, true)});
      const Cell a = cell_of(r.lcm, sp.size), b = cell_of(r.lx, sp.size);
      md << "- no loss at " << size_label(sp.size) << " and " << run.opt.stream_rate << " Hz where liblcm "
         << "with default buffers loses some (" << r.sc.name << "): ";
      if (!a.ok || !b.ok) md << "not measured (a stream run failed)";
      else if (b.lost > 0) md << "**FAILS** (lcmx lost " << b.lost << "/" << b.sent << ", liblcm " << a.lost << "/" << a.sent << ")";
      else if (a.lost == 0) md << "lcmx lost nothing; liblcm lost nothing either in this run (no contrast)";
      else md << "**holds** (lcmx lost 0/" << b.sent << ", liblcm lost " << a.lost << "/" << a.sent << ")";
      md << "\n";
    }
    md << "\nStream: " << sp.messages << " messages of " << size_label(sp.size) << ", " << run.opt.stream_rate
       << " ticks/s, no acks; cells: p50 / p99 one-way µs (lost/sent)\n\n"
       << table.markdown() << "\n";
  } else {
    md << "- stream target: not measured (--no-stream)\n";
  }
  md << "- (differences under 1.3x are noise on this 2-vCPU machine, DESIGN.md \"Measuring\")\n";
  std::vector<const MethodResult*> all = {&lcm, &lx};
  for (const auto& r : streams) all.push_back(&r.lcm), all.push_back(&r.lx);
  std::vector<std::pair<std::string, std::string>> failures, notes;
  for (const MethodResult* m : all) {
    for (const auto& e : m->errors) failures.emplace_back(m->method, e);
    for (const auto& n : m->notes) notes.emplace_back(m->method, n);
  }
  md << list_section("Failures", failures) << list_section("Notes", notes);
  return md.str();
}

int orchestrate(const Options& opt) {
  Run run;
  run.opt = opt;
  try {
    run.plan = make_plan(opt.sizes, {{10, 5, 3}, {100, 50, 30}}, opt.messages, opt.warmup);
    run.stream_plan.push_back({parse_size(opt.stream_size, 16), 0, opt.stream_messages});
  } catch (const std::exception& e) {
    return bad_options(kProgram, e.what());
  }
  if (const auto why = bad_link_options(opt.link)) return bad_options(kProgram, *why);
  if (opt.pin == "split")
    if (const auto why = split_unavailable()) return bad_options(kProgram, *why);
  run.cpus = pinning(opt.pin);
  if (const auto why = hosts_unavailable()) {
    std::cerr << kProgram << ": " << *why << "\n";
    return 1;
  }
  on_stop_signals(OnStop::flag);
  run.exe = self_exe();
  LinkOptions link = opt.link;
  link.tcp_congestion = "cubic";
  auto emu = emulate_hosts(link);
  run.emu = &emu;
  say("hosts: " + hosts_line(emu));
  MethodResult lcm{"liblcm", {}, {}, {}}, lx{"lcmx-udp", {}, {}, {}};
  for (int r = 0; r < opt.rounds && !stopped(); ++r) {
    say("round " + std::to_string(r + 1) + " of " + std::to_string(opt.rounds));
    if (r % 2 == 0) {
      merge(lcm, run_method(run, "liblcm"));
      merge(lx, run_method(run, "lcmx-udp"));
    } else {
      merge(lx, run_method(run, "lcmx-udp"));
      merge(lcm, run_method(run, "liblcm"));
    }
  }
  std::vector<StreamResult> streams;
  if (!opt.no_stream && !stopped()) {
    for (const Scenario& sc : {Scenario{"idle", 1, 0}, Scenario{"busy", opt.stream_burst, opt.stream_hogs}}) {
      say("stream scenario " + sc.name);
      StreamResult r{sc, run_method(run, "liblcm-stream", sc), run_method(run, "lcmx-udp-stream", sc)};
      streams.push_back(std::move(r));
    }
  }
  if (stopped()) {
    std::cerr << kProgram << ": interrupted\n";
    return 128 + stop_flag().load();
  }
  bool ok = print_report(kProgram, report(run, lcm, lx, streams), opt.markdown);
  ok = ok && lx.errors.empty() && lcm.errors.empty();
  for (const auto& r : streams) ok = ok && r.lcm.errors.empty() && r.lx.errors.empty();
  return ok ? 0 : 1;
}

}  // namespace
}  // namespace lcmxbench::udp

int main(int argc, char** argv) {
  using namespace lcmxbench;
  using namespace lcmxbench::udp;
  CLI::App app{
      "lcmx_bench_udp: one-way latency p50/p99 and loss between two emulated hosts (network\n"
      "namespaces), lcmx's UDP path vs raw liblcm udpm, ping-pong by size plus a fixed-rate\n"
      "stream, in one run. Markdown on stdout, progress on stderr. Needs root."};
  Options opt;
  app.add_option("--sizes", opt.sizes, "ping-pong sizes (K = 1024, M = 1024*1024)")->delimiter(',')->capture_default_str();
  app.add_option("--messages", opt.messages, "measured messages per size (default 100 up to 100 KB, 50 up to 2 MB, 30 above)")
      ->check(CLI::PositiveNumber);
  app.add_option("--warmup", opt.warmup, "unmeasured messages per size first (default 10 / 5 / 3)")->check(CLI::NonNegativeNumber);
  app.add_option("--timeout-ms", opt.timeout_ms, "ack timeout per message; then it counts as lost")
      ->check(CLI::Range(10, 10000))->capture_default_str();
  app.add_option("--stream-size", opt.stream_size, "stream message size")->capture_default_str();
  app.add_option("--stream-rate", opt.stream_rate, "stream rate in Hz")->check(CLI::Range(1.0, 100000.0))->capture_default_str();
  app.add_option("--stream-messages", opt.stream_messages, "stream messages")->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--stream-burst", opt.stream_burst, "busy stream scenario: messages sent back to back per tick")
      ->check(CLI::Range(1, 1000))->capture_default_str();
  app.add_option("--stream-hogs", opt.stream_hogs, "busy stream scenario: CPU hog processes on the receiving host")
      ->check(CLI::Range(0, 64))->capture_default_str();
  app.add_option("--rounds", opt.rounds, "ping-pong rounds per method, alternating order, pooled")
      ->check(CLI::Range(1, 100))->capture_default_str();
  app.add_flag("--no-stream", opt.no_stream, "skip the stream runs");
  add_link_options(app, opt.link, "shape the link with tc tbf (e.g. 10gbit, 1gbit); default: none", false);
  add_pin_option(app, opt.pin, {"none", "same", "split"}, "CPU pinning: none, same (both on CPU 0), split (pub 0, sub 1)");
  app.add_option("--markdown", opt.markdown, "also write the Markdown report to this file");
  // The children.
  UdpConfig u;
  std::string plan;
  add_hidden(app, "--role", u.base.role);
  add_hidden(app, "--plan", plan);
  add_hidden(app, "--name", u.base.name);
  add_hidden(app, "--url", u.base.url);
  add_hidden(app, "--vehicle-url", u.vehicle_url);
  CLI11_PARSE(app, argc, argv);
  if (u.base.role.empty()) return orchestrate(opt);
  if (u.base.role == "hog") return run_hog();
  try {
    u.base.plan = plan_from_string(plan);
  } catch (const std::exception& e) {
    report_error(e.what());
    return 2;
  }
  u.base.timeout_ms = opt.timeout_ms;
  u.rate_hz = opt.stream_rate;
  u.burst = opt.stream_burst;
  const auto& r = u.base.role;
  if (r == "liblcm-sub") return run_liblcm_sub(u.base);
  if (r == "liblcm-pub") return run_liblcm_pub(u.base);
  if (r == "lcmx-udp-sub") return run_lcmx_udp_sub(u, false);
  if (r == "lcmx-udp-pub") return run_lcmx_udp_pub(u, false);
  if (r == "lcmx-udp-stream-sub") return run_lcmx_udp_sub(u, true);
  if (r == "lcmx-udp-stream-pub") return run_lcmx_udp_pub(u, true);
  if (r == "liblcm-stream-sub") return run_liblcm_stream_sub(u);
  if (r == "liblcm-stream-pub") return run_liblcm_stream_pub(u);
  report_error("unknown role " + r);
  return 2;
}
