// lcmx_bench_udp: one-way latency and loss between two emulated hosts (network namespaces joined
// by lcmx::test::Emulation's bridge), lcmx's UDP path (Publisher<bench_t> -> Subscriber<bench_t>
// on another host over the vehicle group) side by side with raw liblcm udpm between the same
// namespaces, in one run (DESIGN.md "Benchmarks", experiment 1, UDP row).
//
//  - ping-pong per size: the publisher sends the next message only after the subscriber acked the
//    previous one (or after --timeout-ms: lost). Acks go through a pipe the orchestrator creates
//    and hands to both children (pipes do not care about network namespaces), so the link only
//    carries the measured traffic. Hosts share CLOCK_MONOTONIC: latency = receive - send.
//    The methods run in --rounds rounds, in alternating order (liblcm, lcmx / lcmx, liblcm, ...),
//    and each method's rounds are pooled: slow drifts of a shared machine hit both alike.
//  - stream, two scenarios per method: "idle" (--stream-messages messages of --stream-size at
//    --stream-rate Hz to an idle receiving host) and "busy" (the same messages in bursts of
//    --stream-burst back to back per tick, like a camera's frame set, while --stream-hogs CPU
//    hog processes run in the receiving host's namespace at the same nice level, started before
//    the subscriber for both methods alike). No acks; loss = sent - received.
//  - --keys: instead of liblcm, lcmx UDP three ways in one run: unkeyed, on a keyed vehicle
//    group authenticated, and encrypted (docs/keyed-groups.md), ping-pong rounds in rotating
//    order, then the idle stream for each with the CPU time of publisher + subscriber per MB.
// Without --role this is the orchestrator: Markdown on stdout, progress on stderr. Root needed.
#include <sched.h>
#include <signal.h>
#include <sodium.h>
#include <sys/prctl.h>
#include <sys/utsname.h>
#include <sys/wait.h>
#include <fcntl.h>
#include <poll.h>
#include <unistd.h>

#include <CLI/CLI.hpp>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <ctime>
#include <fstream>
#include <functional>
#include <chrono>
#include <iostream>
#include <map>
#include <optional>
#include <sstream>

#include "lcmx/test/netns.hpp"
#include "lcmx/udpm/keys.hpp"
#include "roles.hpp"

namespace lcmxbench::udp {
namespace {

std::atomic<int> g_signal{0};
void on_signal(int sig) { g_signal.store(sig); }

// Starts this binary's role `argv` inside network namespace `netns_fd` (see spawn_child).
pid_t spawn_in(int netns_fd, const std::vector<std::string>& argv, const std::vector<int>& fds, int cpu) {
  return spawn_child(argv, fds, cpu, netns_fd);
}



// ---- results ----

struct SizeResult {
  std::optional<int> sent;
  std::optional<std::vector<std::int64_t>> lat;
};
struct MethodResult {
  std::string method;
  std::vector<std::string> errors, notes;
  std::map<std::size_t, SizeResult> sizes;
  long long cpu_us = 0;  // "cpu pub|sub <µs>" lines, summed (publisher + subscriber processes)
};
struct Cell {
  bool ok = false;
  std::size_t n = 0;
  int sent = 0, lost = 0;
  double p50 = 0, p99 = 0;
};

Cell cell_of(const MethodResult& m, std::size_t size) {
  Cell c;
  const auto it = m.sizes.find(size);
  if (it == m.sizes.end() || !it->second.sent || !it->second.lat) return c;
  auto v = *it->second.lat;
  c.ok = true;
  c.sent = *it->second.sent;
  c.n = v.size();
  c.lost = std::max(0, c.sent - static_cast<int>(c.n));
  if (!v.empty()) {
    std::sort(v.begin(), v.end());
    auto rank = [&](double q) {
      const auto k = static_cast<std::size_t>(std::ceil(q * static_cast<double>(v.size())));
      return static_cast<double>(v[std::clamp<std::size_t>(k, 1, v.size()) - 1]) / 1000.0;
    };
    c.p50 = rank(0.5), c.p99 = rank(0.99);
  }
  return c;
}

void parse_line(MethodResult& r, const std::string& line) {
  std::istringstream in(line);
  std::string kind;
  in >> kind;
  auto rest = [&] {
    std::string s;
    std::getline(in, s);
    return s.empty() ? s : s.substr(1);
  };
  if (kind == "cpu") {
    std::string who;
    long long us = 0;
    if (in >> who >> us) r.cpu_us += us;
  } else if (kind == "error") r.errors.push_back(rest());
  else if (kind == "note") r.notes.push_back(rest());
  else if (kind == "sent") {
    std::size_t size = 0;
    int n = 0;
    if (in >> size >> n) r.sizes[size].sent = n;
  } else if (kind == "lat") {
    std::size_t size = 0, n = 0;
    if (in >> size >> n) {
      std::vector<std::int64_t> v;
      v.reserve(n);
      for (std::int64_t x; v.size() < n && in >> x;) v.push_back(x);
      r.sizes[size].lat = std::move(v);
    }
  }
}

// ---- orchestration ----

struct Options {
  std::vector<std::string> sizes{"1K", "10K", "100K", "1M", "2M", "6M"};
  int messages = 0, warmup = -1, timeout_ms = 200;
  std::string stream_size = "100K";
  double stream_rate = 30;
  int stream_messages = 150;
  int stream_burst = 4, stream_hogs = 2;  // "busy" scenario
  int rounds = 3;
  bool no_stream = false;
  std::string link_rate;  // tc tbf rate on the link ("" = none)
  std::string pin = "none";
  std::string markdown;
  bool keys = false;  // unkeyed / authenticated / encrypted lcmx instead of liblcm vs lcmx
};

std::size_t parse_size(const std::string& text) { return lcmxbench::parse_size(text, 16); }

void progress(const std::string& s) { std::cerr << "[bench-udp] " << s << std::endl; }

constexpr const char* kDiscoveryUrl = "udpm://239.255.77.221:17721?ttl=0";  // each host's own lo
constexpr const char* kVehicleUrl = "udpm://239.255.77.222:17722?ttl=1&iface=eth";
constexpr const char* kLcmUrl = "udpm://239.255.77.223:17723?ttl=1";  // liblcm: the 224/4 route (eth)

struct Run {
  Options opt;
  std::vector<SizePlan> plan, stream_plan;
  lcmx::test::Emulation* emu = nullptr;
  std::string exe;
  int pub_cpu = -1, sub_cpu = -1;
  int serial = 0;
  std::string key_file;  // --keys: the vehicle group key the keyed methods use
};

// method: "liblcm" | "lcmx-udp" (ping-pong), "liblcm-stream" | "lcmx-udp-stream".
// Stream scenario: messages per tick and CPU hogs on the receiving host.
struct Scenario {
  std::string name = "idle";
  int burst = 1, hogs = 0;
};

MethodResult run_method(Run& run, const std::string& method, const Scenario& sc = {}) {
  MethodResult res;
  res.method = method;
  const bool stream = method.find("stream") != std::string::npos;
  const bool liblcm = method.rfind("liblcm", 0) == 0;
  // lcmx on a keyed vehicle group: "lcmx-udp-auth[-stream]", "lcmx-udp-crypt[-stream]".
  const bool auth = method.find("-auth") != std::string::npos, crypt = method.find("-crypt") != std::string::npos;
  const auto& plan = stream ? run.stream_plan : run.plan;
  progress(method + ": starting");
  const std::int64_t t0 = now_ns();
  std::int64_t budget_ms = 40'000;
  for (const auto& p : plan)
    budget_ms += stream ? static_cast<std::int64_t>(p.messages * 1000 / run.opt.stream_rate) + 5000
                        : static_cast<std::int64_t>(p.warmup + p.messages) * (run.opt.timeout_ms + 50);
  const std::int64_t deadline = t0 + budget_ms * 1'000'000;
  const std::string name = "UDP_" + std::to_string(::getpid()) + "_" + std::to_string(++run.serial);
  auto args = [&](const std::string& role) {
    std::vector<std::string> a{
        run.exe, "--role", role, "--plan", plan_to_string(plan), "--name", name, "--url",
        liblcm ? kLcmUrl : kDiscoveryUrl, "--vehicle-url", kVehicleUrl, "--timeout-ms",
        std::to_string(run.opt.timeout_ms), "--stream-rate", std::to_string(run.opt.stream_rate),
        "--stream-burst", std::to_string(sc.burst)};
    if (auth || crypt) a.insert(a.end(), {"--key-file", run.key_file});
    if (crypt) a.push_back("--crypt");
    return a;
  };
  const std::string base = liblcm ? "liblcm" : "lcmx-udp";
  const std::string sub_role = base + (stream ? "-stream-sub" : "-sub");
  const std::string pub_role = base + (stream ? "-stream-pub" : "-pub");
  std::vector<pid_t> pids, hogs;
  LineReader sub, pub;
  bool timed_out = false;
  try {
    // Hogs first, unpinned, so the subscriber starts on an already busy host.
    for (int i = 0; i < sc.hogs; ++i) hogs.push_back(spawn_in(run.emu->ns_fd(1), {run.exe, "--role", "hog"}, {}, -1));
    Pipe rep_sub, rep_pub, ack, ctl;
    pids.push_back(spawn_in(run.emu->ns_fd(1), args(sub_role), {rep_sub.w, ack.w, ctl.r}, run.sub_cpu));
    rep_sub.close_w();
    sub.fd = std::exchange(rep_sub.r, -1);
    const auto ready = [&] { return sub.has("ready") || sub.has("error"); };
    if (!pump_until({&sub}, std::min(deadline, now_ns() + 20'000'000'000), ready, g_signal) || !sub.has("ready"))
      throw std::runtime_error("subscriber not ready (or failed) within 20 s");
    pids.push_back(spawn_in(run.emu->ns_fd(0), args(pub_role), {rep_pub.w, ack.r, ctl.w}, run.pub_cpu));
    rep_pub.close_w();
    ack.close_r(), ack.close_w(), ctl.close_r(), ctl.close_w();
    pub.fd = std::exchange(rep_pub.r, -1);
    timed_out = !pump_until({&sub, &pub}, deadline, [] { return false; }, g_signal);
  } catch (const std::exception& e) {
    res.errors.push_back(e.what());
  }
  for (auto p : hogs) reap_child(p, 0, g_signal);  // SIGKILLed and reaped
  for (auto p : pids) {
    const int st = reap_child(p, timed_out ? 0 : 5000, g_signal);
    if (WIFEXITED(st) && WEXITSTATUS(st) >= 125) res.errors.push_back("a child could not start (exit " + std::to_string(WEXITSTATUS(st)) + ")");
    else if (WIFSIGNALED(st) && !timed_out) res.errors.push_back("a child died of signal " + std::to_string(WTERMSIG(st)));
  }
  for (LineReader* r : {&sub, &pub}) {
    for (const auto& l : r->lines)
      if (l != "ready" && l != "done") parse_line(res, l);
    if (r->fd >= 0) ::close(r->fd);
  }
  if (timed_out) res.errors.push_back("timed out after " + std::to_string(budget_ms / 1000) + " s; children killed");
  for (const auto& p : plan) {
    const Cell c = cell_of(res, p.size);
    if (!c.ok) continue;
    char buf[200];
    std::snprintf(buf, sizeof buf, "%s %s: p50 %.1f us, p99 %.1f us, received %zu/%d", method.c_str(),
                  size_label(p.size).c_str(), c.p50, c.p99, c.n, c.sent);
    progress(buf);
  }
  for (const auto& e : res.errors) progress(method + ": FAILED: " + e);
  for (const auto& n : res.notes) progress(method + ": " + n);
  char t[64];
  std::snprintf(t, sizeof t, "%.1f s", static_cast<double>(now_ns() - t0) / 1e9);
  progress(method + ": finished in " + t);
  return res;
}

// Pools another round of the same method into `into`.
void merge(MethodResult& into, MethodResult&& more) {
  into.cpu_us += more.cpu_us;
  for (auto& e : more.errors) into.errors.push_back(std::move(e));
  for (auto& n : more.notes)
    if (std::find(into.notes.begin(), into.notes.end(), n) == into.notes.end()) into.notes.push_back(std::move(n));
  for (auto& [size, r] : more.sizes) {
    auto& t = into.sizes[size];
    if (r.sent) t.sent = t.sent.value_or(0) + *r.sent;
    if (r.lat) {
      if (!t.lat) t.lat.emplace();
      t.lat->insert(t.lat->end(), r.lat->begin(), r.lat->end());
    }
  }
}

std::string fmt_ratio(double r) {
  char b[32];
  std::snprintf(b, sizeof b, "%.2fx", r);
  return b;
}
std::string cell_text(const MethodResult& m, std::size_t size) {
  const Cell c = cell_of(m, size);
  if (!c.ok) return m.errors.empty() ? "—" : "failed";
  std::string s = c.n ? fmt_us(c.p50) + " / " + fmt_us(c.p99) : "—";
  s += " (lost " + std::to_string(c.lost) + "/" + std::to_string(c.sent) + ")";
  return s;
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
  char date[64];
  const std::time_t now = std::time(nullptr);
  std::strftime(date, sizeof date, "%Y-%m-%d %H:%M:%S %Z", std::localtime(&now));
  utsname u{};
  ::uname(&u);
  md << "## lcmx UDP vs raw liblcm udpm between two emulated hosts\n\n";
  md << "- " << date << ", " << u.nodename << ", Linux " << u.release << ", "
     << ::sysconf(_SC_NPROCESSORS_ONLN) << " CPUs online; pinning `--pin " << run.opt.pin << "`\n";
  md << "- 2 network namespaces joined by a veth/bridge link"
     << (run.opt.link_rate.empty() ? " (no rate limit)" : " shaped to " + run.opt.link_rate + " (tbf)")
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
     << run.opt.timeout_ms << " ms = lost; messages per size (warmup + measured): ";
  for (std::size_t i = 0; i < run.plan.size(); ++i)
    md << (i ? ", " : "") << size_label(run.plan[i].size) << " " << run.plan[i].warmup << "+" << run.plan[i].messages;
  md << "\n- cells: p50 / p99 one-way µs (send_ns before encode -> after decode, shared "
        "CLOCK_MONOTONIC), lost/sent; ratio = lcmx p50 / liblcm p50\n\n";
  md << "| size | liblcm udpm | lcmx UDP | lcmx/liblcm |\n|---|---|---|---|\n";
  double worst = 0;
  std::size_t worst_size = 0;
  bool compared = false, missing = false;
  for (const auto& p : run.plan) {
    const Cell a = cell_of(lcm, p.size), b = cell_of(lx, p.size);
    std::string ratio = "—";
    if (a.ok && b.ok && a.n && b.n) {
      ratio = fmt_ratio(b.p50 / a.p50);
      if (a.lost == 0) {
        compared = true;
        if (b.p50 / a.p50 > worst) worst = b.p50 / a.p50, worst_size = p.size;
      }
    } else if (a.ok && a.lost == 0) {
      missing = true;
    }
    md << "| " << size_label(p.size) << " | " << cell_text(lcm, p.size) << " | " << cell_text(lx, p.size)
       << " | " << ratio << " |\n";
  }
  md << "\n**Targets**\n";
  md << "- lcmx UDP within 1.1x of raw liblcm at every size where liblcm loses nothing: ";
  if (!compared) md << "not measured (no size where both delivered and liblcm lost nothing)";
  else md << (worst <= 1.1 && !missing ? "**holds**" : "**FAILS**") << " (worst " << fmt_ratio(worst) << " at "
          << size_label(worst_size) << (missing ? "; lcmx has no result at a size where liblcm lost nothing" : "")
          << ")";
  md << "\n";
  if (!streams.empty()) {
    const auto& sp = run.stream_plan.front();
    std::ostringstream table;
    table << "\nStream: " << sp.messages << " messages of " << size_label(sp.size) << ", "
          << run.opt.stream_rate << " ticks/s, no acks; cells: p50 / p99 one-way µs (lost/sent)\n\n"
          << "| scenario | liblcm udpm | lcmx UDP |\n|---|---|---|\n";
    for (const auto& r : streams) {
      table << "| " << r.sc.name << ": " << r.sc.burst << " message" << (r.sc.burst > 1 ? "s" : "")
            << " per tick, " << r.sc.hogs << " CPU hog" << (r.sc.hogs == 1 ? "" : "s")
            << " on the receiving host | " << cell_text(r.lcm, sp.size) << " | " << cell_text(r.lx, sp.size) << " |\n";
      const Cell a = cell_of(r.lcm, sp.size), b = cell_of(r.lx, sp.size);
      md << "- no loss at " << size_label(sp.size) << " and " << run.opt.stream_rate << " Hz where liblcm "
         << "with default buffers loses some (" << r.sc.name << "): ";
      if (!a.ok || !b.ok) md << "not measured (a stream run failed)";
      else if (b.lost > 0) md << "**FAILS** (lcmx lost " << b.lost << "/" << b.sent << ", liblcm " << a.lost << "/" << a.sent << ")";
      else if (a.lost == 0) md << "lcmx lost nothing; liblcm lost nothing either in this run (no contrast)";
      else md << "**holds** (lcmx lost 0/" << b.sent << ", liblcm lost " << a.lost << "/" << a.sent << ")";
      md << "\n";
    }
    md << table.str() << "\n";
  } else {
    md << "- stream target: not measured (--no-stream)\n";
  }
  md << "- (differences under 1.3x are noise on this 2-vCPU machine, DESIGN.md \"Measuring\")\n";
  bool any = false;
  std::vector<const MethodResult*> all = {&lcm, &lx};
  for (const auto& r : streams) all.push_back(&r.lcm), all.push_back(&r.lx);
  for (const MethodResult* m : all) {
    for (const auto& e : m->errors) {
      if (!any) md << "\n**Failures**\n";
      any = true;
      md << "- " << m->method << ": " << e << "\n";
    }
  }
  any = false;
  for (const MethodResult* m : all) {
    for (const auto& n : m->notes) {
      if (!any) md << "\n**Notes**\n";
      any = true;
      md << "- " << m->method << ": " << n << "\n";
    }
  }
  return md.str();
}

// --keys: the three lcmx modes side by side.
std::string report_keys(const Run& run, const std::vector<MethodResult>& pp, const std::vector<MethodResult>& st) {
  std::ostringstream md;
  char date[64];
  const std::time_t now = std::time(nullptr);
  std::strftime(date, sizeof date, "%Y-%m-%d %H:%M:%S %Z", std::localtime(&now));
  utsname u{};
  ::uname(&u);
  md << "## lcmx UDP unkeyed, authenticated and encrypted (keyed groups) between two emulated hosts\n\n";
  md << "- " << date << ", " << u.nodename << ", Linux " << u.release << ", " << ::sysconf(_SC_NPROCESSORS_ONLN)
     << " CPUs online; pinning `--pin " << run.opt.pin << "`\n";
  md << "- Publisher<bench_t> on host 0 -> Subscriber<bench_t> on host 1 over the vehicle group `" << kVehicleUrl
     << "`; keyed: XChaCha20-Poly1305 (libsodium) per datagram, authenticated (tag over header and datagram) or "
        "encrypted (payload encrypted, header authenticated)\n";
  md << "- ping-pong rounds: " << run.opt.rounds << " per mode, rotating order, pooled; messages per size (warmup + "
        "measured): ";
  for (std::size_t i = 0; i < run.plan.size(); ++i)
    md << (i ? ", " : "") << size_label(run.plan[i].size) << " " << run.plan[i].warmup << "+" << run.plan[i].messages;
  md << "\n- cells: p50 / p99 one-way µs (lost/sent); ratios: keyed p50 / unkeyed p50\n\n";
  md << "| size | unkeyed | authenticated | encrypted | auth/unkeyed | crypt/unkeyed |\n|---|---|---|---|---|---|\n";
  auto ratio = [&](const MethodResult& a, const MethodResult& b, std::size_t size) -> std::pair<std::string, double> {
    const Cell x = cell_of(a, size), y = cell_of(b, size);
    if (!x.ok || !y.ok || !x.n || !y.n) return {"—", 0};
    return {fmt_ratio(y.p50 / x.p50), y.p50 / x.p50};
  };
  for (const auto& p : run.plan)
    md << "| " << size_label(p.size) << " | " << cell_text(pp[0], p.size) << " | " << cell_text(pp[1], p.size) << " | "
       << cell_text(pp[2], p.size) << " | " << ratio(pp[0], pp[1], p.size).first << " | "
       << ratio(pp[0], pp[2], p.size).first << " |\n";
  md << "\n**Targets**\n";
  const std::size_t k1 = 1024;
  if (std::any_of(run.plan.begin(), run.plan.end(), [&](const SizePlan& p) { return p.size == k1; })) {
    const auto a = ratio(pp[0], pp[1], k1), c = ratio(pp[0], pp[2], k1);
    md << "- 1 KB p50 authenticated within 3 % of unkeyed: " << (a.second == 0 ? "not measured" : a.second <= 1.03 ? "**holds**" : "**FAILS**")
       << " (" << a.first << ")\n";
    md << "- 1 KB p50 encrypted within 10 % of unkeyed: " << (c.second == 0 ? "not measured" : c.second <= 1.10 ? "**holds**" : "**FAILS**")
       << " (" << c.first << ")\n";
  }
  if (!st.empty()) {
    const auto& sp = run.stream_plan.front();
    const double mb = static_cast<double>(sp.size) * sp.messages / 1e6;
    md << "- " << size_label(sp.size) << " at " << run.opt.stream_rate << " Hz with 0 lost in all three: ";
    bool all = true, measured = true;
    for (const auto& m : st) {
      const Cell c = cell_of(m, sp.size);
      measured = measured && c.ok;
      all = all && c.ok && c.lost == 0;
    }
    md << (!measured ? "not measured" : all ? "**holds**" : "**FAILS**") << "\n";
    md << "\nStream: " << sp.messages << " messages of " << size_label(sp.size) << " at " << run.opt.stream_rate
       << " Hz, no acks; CPU: user + system time of the publisher and subscriber processes (whole run, start-up "
          "and discovery included) per MB of payload\n\n";
    md << "| mode | p50 / p99 one-way µs (lost/sent) | CPU ms (pub + sub) | CPU ms per MB |\n|---|---|---|---|\n";
    const char* names[3] = {"unkeyed", "authenticated", "encrypted"};
    for (std::size_t i = 0; i < st.size(); ++i) {
      char cpu[64], per[64];
      std::snprintf(cpu, sizeof cpu, "%.0f", static_cast<double>(st[i].cpu_us) / 1000.0);
      std::snprintf(per, sizeof per, "%.2f", static_cast<double>(st[i].cpu_us) / 1000.0 / mb);
      md << "| " << names[i] << " | " << cell_text(st[i], sp.size) << " | " << cpu << " | " << per << " |\n";
    }
  }
  md << "- (differences of a few per cent are within the noise of this 2-vCPU machine, DESIGN.md \"Measuring\"; "
        "more --rounds narrow them)\n";
  bool any = false;
  for (const auto* v : {&pp, &st})
    for (const auto& m : *v)
      for (const auto& e : m.errors) {
        if (!any) md << "\n**Failures**\n";
        any = true;
        md << "- " << m.method << ": " << e << "\n";
      }
  return md.str();
}

// --seal-micro: what each candidate primitive costs per datagram, in this process (no network):
// the choice of docs/keyed-groups.md "Wire form". Median of 7 runs of N calls each.
int seal_micro() {
  if (::sodium_init() < 0) return 1;
  unsigned char key[32], nonce[24] = {}, tag[64], out[64], none = 0;
  ::randombytes_buf(key, sizeof key);
  std::cout << "| per datagram | 1 KB (ns) | 64 KB (ns) |\n|---|---|---|\n";
  struct Row {
    const char* name;
    std::function<void(std::vector<unsigned char>&, std::vector<unsigned char>&, std::size_t)> f;
  };
  const std::vector<Row> rows = {
      {"XChaCha20-Poly1305, empty message, datagram as AD (authenticated)",
       [&](auto& m, auto&, std::size_t n) {
         ::crypto_aead_xchacha20poly1305_ietf_encrypt_detached(&none, tag, nullptr, &none, 0, m.data(), n + 28, nullptr,
                                                               nonce, key);
       }},
      {"XChaCha20-Poly1305 encrypt, 28-byte header as AD (encrypted)",
       [&](auto& m, auto& c, std::size_t n) {
         ::crypto_aead_xchacha20poly1305_ietf_encrypt_detached(c.data(), tag, nullptr, m.data() + 28, n, m.data(), 28,
                                                               nullptr, nonce, key);
       }},
      {"crypto_auth (HMAC-SHA-512-256)", [&](auto& m, auto&, std::size_t n) { ::crypto_auth(out, m.data(), n + 28, key); }},
      {"crypto_generichash keyed (BLAKE2b-128)",
       [&](auto& m, auto&, std::size_t n) { ::crypto_generichash(out, 16, m.data(), n + 28, key, sizeof key); }},
      {"AES-256-GCM, empty message, datagram as AD (x86-64 AES-NI only)",
       [&](auto& m, auto&, std::size_t n) {
         if (::crypto_aead_aes256gcm_is_available())
           ::crypto_aead_aes256gcm_encrypt_detached(&none, tag, nullptr, &none, 0, m.data(), n + 28, nullptr, nonce, key);
       }},
  };
  for (const auto& row : rows) {
    std::cout << "| " << row.name;
    for (const std::size_t size : {std::size_t{1024}, std::size_t{65000}}) {
      std::vector<unsigned char> m(size + 28), c(size + 64);
      ::randombytes_buf(m.data(), m.size());
      const int n = size == 1024 ? 20000 : 400;
      std::vector<double> runs;
      for (int r = 0; r < 7; ++r) {
        const auto t0 = std::chrono::steady_clock::now();
        for (int i = 0; i < n; ++i) {
          nonce[0] = static_cast<unsigned char>(i);
          row.f(m, c, size);
        }
        runs.push_back(std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - t0).count() / n);
      }
      std::sort(runs.begin(), runs.end());
      const bool gcm = std::string(row.name).rfind("AES", 0) == 0;
      if (gcm && !::crypto_aead_aes256gcm_is_available()) std::cout << " | not available";
      else std::cout << " | " << static_cast<long long>(runs[3]);
    }
    std::cout << " |\n";
  }
  return 0;
}

int orchestrate(const Options& opt) {
  Run run;
  run.opt = opt;
  try {
    for (const auto& s : opt.sizes) {
      SizePlan p;
      p.size = parse_size(s);
      if (p.size <= 100 * 1024) p.warmup = 10, p.messages = 100;
      else if (p.size <= 2 * 1024 * 1024) p.warmup = 5, p.messages = 50;
      else p.warmup = 3, p.messages = 30;
      if (opt.messages > 0) p.messages = opt.messages;
      if (opt.warmup >= 0) p.warmup = opt.warmup;
      run.plan.push_back(p);
    }
    run.stream_plan.push_back({parse_size(opt.stream_size), 0, opt.stream_messages});
  } catch (const std::exception& e) {
    std::cerr << "lcmx_bench_udp: " << e.what() << "\n";
    return 2;
  }
  if (opt.pin == "same") run.pub_cpu = 0, run.sub_cpu = 0;
  else if (opt.pin == "split") run.pub_cpu = 0, run.sub_cpu = 1;
  std::string why;
  if (!lcmx::test::netns_available(&why)) {
    std::cerr << "lcmx_bench_udp: cannot emulate hosts: " << why << "\n";
    return 1;
  }
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  for (int s : {SIGINT, SIGTERM, SIGHUP}) ::sigaction(s, &sa, nullptr);
  ::signal(SIGPIPE, SIG_IGN);
  run.exe = self_exe();
  lcmx::test::LinkSpec link;
  link.name = "eth";
  if (!opt.link_rate.empty()) link.rate = opt.link_rate;
  auto emu = lcmx::test::Emulation::create({.hosts = 2, .links = {link}});
  run.emu = &emu;
  progress("hosts: " + emu.ns(0) + " (" + emu.address(0, "eth") + ") -> " + emu.ns(1) + " (" +
           emu.address(1, "eth") + ")");
  if (opt.keys) {
    // A key file for the keyed modes, in a directory of our own (removed at the end).
    std::string dir = "/tmp/lcmx_bench_keys_XXXXXX";
    if (::mkdtemp(dir.data()) == nullptr) {
      std::cerr << "lcmx_bench_udp: mkdtemp: " << std::strerror(errno) << "\n";
      return 1;
    }
    run.key_file = dir + "/vehicle.key";
    lcmx::udpm::GroupKeys k;
    k.keys.push_back(lcmx::udpm::generate_key());
    lcmx::udpm::write_key_file(run.key_file, k, false);
    const std::vector<std::string> modes = {"lcmx-udp", "lcmx-udp-auth", "lcmx-udp-crypt"};
    std::vector<MethodResult> pp;
    for (const auto& m : modes) pp.push_back(MethodResult{m, {}, {}, {}, 0});
    for (int r = 0; r < opt.rounds && !g_signal.load(); ++r) {
      progress("round " + std::to_string(r + 1) + " of " + std::to_string(opt.rounds));
      for (std::size_t i = 0; i < modes.size(); ++i) {
        const std::size_t k2 = (i + static_cast<std::size_t>(r)) % modes.size();  // rotating order
        merge(pp[k2], run_method(run, modes[k2]));
      }
    }
    std::vector<MethodResult> st;
    if (!opt.no_stream)
      for (const auto& m : modes) {
        if (g_signal.load()) break;
        st.push_back(run_method(run, m + "-stream", Scenario{"idle", 1, 0}));
      }
    ::unlink(run.key_file.c_str());
    ::rmdir(dir.c_str());
    if (g_signal.load()) return 128 + g_signal.load();
    const std::string md = report_keys(run, pp, st);
    std::cout << md << std::flush;
    if (!opt.markdown.empty()) std::ofstream(opt.markdown) << md;
    bool ok = true;
    for (const auto* v : {&pp, &st})
      for (const auto& m : *v) ok = ok && m.errors.empty();
    return ok ? 0 : 1;
  }
  MethodResult lcm{"liblcm", {}, {}, {}, 0}, lx{"lcmx-udp", {}, {}, {}, 0};
  for (int r = 0; r < opt.rounds && !g_signal.load(); ++r) {
    progress("round " + std::to_string(r + 1) + " of " + std::to_string(opt.rounds));
    if (r % 2 == 0) {
      merge(lcm, run_method(run, "liblcm"));
      merge(lx, run_method(run, "lcmx-udp"));
    } else {
      merge(lx, run_method(run, "lcmx-udp"));
      merge(lcm, run_method(run, "liblcm"));
    }
  }
  std::vector<StreamResult> streams;
  if (!opt.no_stream && !g_signal.load()) {
    for (const Scenario& sc : {Scenario{"idle", 1, 0}, Scenario{"busy", opt.stream_burst, opt.stream_hogs}}) {
      progress("stream scenario " + sc.name);
      StreamResult r{sc, run_method(run, "liblcm-stream", sc), run_method(run, "lcmx-udp-stream", sc)};
      streams.push_back(std::move(r));
    }
  }
  if (g_signal.load()) {
    std::cerr << "lcmx_bench_udp: interrupted\n";
    return 128 + g_signal.load();
  }
  const std::string md = report(run, lcm, lx, streams);
  std::cout << md << std::flush;
  if (!opt.markdown.empty()) std::ofstream(opt.markdown) << md;
  bool ok = lx.errors.empty() && lcm.errors.empty();
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
  app.add_option("--link-rate", opt.link_rate, "shape the link with tc tbf (e.g. 10gbit, 1gbit); default: none");
  app.add_option("--pin", opt.pin, "CPU pinning: none, same (both on CPU 0), split (pub 0, sub 1)")
      ->check(CLI::IsMember({"none", "same", "split"}))->capture_default_str();
  app.add_option("--markdown", opt.markdown, "also write the Markdown report to this file");
  bool micro = false;
  app.add_flag("--seal-micro", micro, "print what sealing one datagram costs per primitive (keyed groups), then exit");
  app.add_flag("--keys", opt.keys,
               "keyed groups: lcmx UDP unkeyed, authenticated and encrypted side by side (no liblcm), the idle "
               "stream with CPU per MB (docs/keyed-groups.md)");
  // Hidden: child roles.
  UdpConfig u;
  std::string plan;
  app.add_option("--role", u.base.role)->group("");
  app.add_option("--plan", plan)->group("");
  app.add_option("--name", u.base.name)->group("");
  app.add_option("--url", u.base.url)->group("");
  app.add_option("--vehicle-url", u.vehicle_url)->group("");
  app.add_option("--key-file", u.key_file)->group("");
  app.add_flag("--crypt", u.crypt)->group("");
  CLI11_PARSE(app, argc, argv);
  if (micro) return seal_micro();
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
  // Keyed modes run the same roles with --key-file (and --crypt).
  if (r == "lcmx-udp-sub") return run_lcmx_udp_sub(u, false);
  if (r == "lcmx-udp-pub") return run_lcmx_udp_pub(u, false);
  if (r == "lcmx-udp-stream-sub") return run_lcmx_udp_sub(u, true);
  if (r == "lcmx-udp-stream-pub") return run_lcmx_udp_pub(u, true);
  if (r == "liblcm-stream-sub") return run_liblcm_stream_sub(u);
  if (r == "liblcm-stream-pub") return run_liblcm_stream_pub(u);
  report_error("unknown role " + r);
  return 2;
}
