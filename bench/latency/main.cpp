// lcmx_bench_latency: one-way latency publisher -> subscriber in another process, by method
// and message size, all methods in one run (DESIGN.md "Benchmarks", experiment 1, one host).
//
// Without --role this is the orchestrator: it runs each method's pair of children with the
// harness's ping-pong protocol (bench/harness/pingpong.hpp), and prints a Markdown table with
// the ratios and targets on stdout (progress on stderr). The liblcm pair runs in a network
// namespace of this run (liblcm joins its group where the default route points, which is not
// ours to change); everything else stays on loopback. See bench/README.md.
#include <dirent.h>
#include <signal.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "harness/options.hpp"
#include "harness/pingpong.hpp"
#include "harness/report.hpp"
#include "lcmx/shm/segment.hpp"
#include "latency/roles.hpp"

namespace lcmxbench {
namespace {

const char* const kProgram = "lcmx_bench_latency";
void say(const std::string& s) { progress("bench", s); }

// ---------------------------------------------------------------- the liblcm pair's namespace

bool pid_alive(long pid) { return pid > 0 && (::kill(static_cast<pid_t>(pid), 0) == 0 || errno == EPERM); }

// Removes namespaces and shm files of earlier runs of this bench whose process is dead.
void sweep_stale() {
  auto pid_of = [](const std::string& n) -> long {
    const std::string prefix = "lcmxbench_";
    if (n.rfind(prefix, 0) != 0) return -1;
    return std::strtol(n.c_str() + prefix.size(), nullptr, 10);
  };
  if (DIR* d = ::opendir("/run/netns")) {
    std::vector<std::string> stale;
    while (dirent* e = ::readdir(d)) {
      const long pid = pid_of(e->d_name);
      if (pid > 0 && !pid_alive(pid)) stale.emplace_back(e->d_name);
    }
    ::closedir(d);
    for (const auto& n : stale) {
      say("removing stale network namespace " + n);
      run_command({"ip", "netns", "del", n});
    }
  }
  if (DIR* d = ::opendir("/dev/shm")) {
    while (dirent* e = ::readdir(d)) {
      const long pid = pid_of(e->d_name);
      if (pid > 0 && !pid_alive(pid)) ::unlinkat(::dirfd(d), e->d_name, 0);
    }
    ::closedir(d);
  }
}

// Loopback up, multicast routed to lo. Deleted by the destructor (every exit path but SIGKILL;
// the next run's sweep_stale() handles that one).
class LoopbackNamespace {
 public:
  explicit LoopbackNamespace(std::string name) : name_(std::move(name)) {}
  LoopbackNamespace(const LoopbackNamespace&) = delete;
  LoopbackNamespace& operator=(const LoopbackNamespace&) = delete;
  ~LoopbackNamespace() {
    if (created_) run_command({"ip", "netns", "del", name_});
  }
  // Returns an error text, or nothing on success.
  std::optional<std::string> create() {
    if (!run_command({"ip", "netns", "add", name_})) return "ip netns add " + name_ + " failed (root needed)";
    created_ = true;
    if (!run_command({"ip", "-n", name_, "link", "set", "lo", "up"})) return "ip link set lo up failed";
    if (!run_command({"ip", "-n", name_, "route", "add", "224.0.0.0/4", "dev", "lo"}))
      return "ip route add 224.0.0.0/4 dev lo failed";
    return std::nullopt;
  }
  const std::string& name() const { return name_; }

 private:
  std::string name_;
  bool created_ = false;
};

// ---------------------------------------------------------------- the run

struct Options {
  std::vector<std::string> sizes{"1K", "10K", "100K", "1M", "2M", "6M"};
  int messages = 0;  // 0: per-size default
  int warmup = -1;   // -1: per-size default
  std::vector<std::string> methods{"floor", "liblcm", "lcmx-intra", "lcmx-shm", "lcmx-loan"};
  std::string pin = "none";
  std::string wait = "block";  // the library default (ExecutorOptions)
  int timeout_ms = 200;
  std::string lcm_url = "udpm://239.255.77.201:17701?ttl=0";
  std::string discovery_url = "udpm://239.255.77.202:17702?ttl=0&iface=lo";  // root namespace: lo only
  std::string csv, markdown;
};

struct Run {
  Options opt;
  std::vector<SizePlan> plan;
  std::string name;  // lcmxbench_<pid>
  std::string exe;
  Pinning cpus;
  const LoopbackNamespace* netns = nullptr;
  std::optional<std::string> netns_error;
};

std::vector<std::string> role_args(const Run& run, const std::string& role, bool in_netns) {
  std::vector<std::string> a;
  if (in_netns) a = {"ip", "netns", "exec", run.netns->name()};
  const bool liblcm = role.rfind("liblcm", 0) == 0;
  std::vector<std::string> r = {
      run.exe, "--role", role, "--plan", plan_to_string(run.plan), "--name", run.name,
      "--url", liblcm ? run.opt.lcm_url : run.opt.discovery_url, "--wait", run.opt.wait,
      "--timeout-ms", std::to_string(run.opt.timeout_ms),
      "--pub-cpu", std::to_string(run.cpus.pub), "--sub-cpu", std::to_string(run.cpus.sub)};
  a.insert(a.end(), r.begin(), r.end());
  return a;
}

int method_deadline_ms(const Run& run) {
  std::int64_t ms = 45'000;  // start-up, matching (15 s each side), teardown
  for (const auto& p : run.plan)
    ms += static_cast<std::int64_t>(p.warmup + p.messages) * (run.opt.timeout_ms + 50);
  return static_cast<int>(std::min<std::int64_t>(ms, 1'800'000));
}

MethodResult run_method(const Run& run, const std::string& method) {
  say(method + ": starting");
  const std::int64_t t0 = now_ns();
  Pair pair;
  pair.method = method;
  pair.deadline_ms = method_deadline_ms(run);
  PairOutcome out;
  const bool liblcm = method == "liblcm";
  if (liblcm && run.netns_error) {
    out.result.method = method;
    out.result.errors.push_back("network namespace: " + *run.netns_error);
  } else {
    if (method == "lcmx-intra") {
      // one process: publisher thread on pub_cpu, subscriber thread on sub_cpu (see lcmx.cpp)
      pair.sub_argv = role_args(run, "lcmx-intra", false);
      pair.sub_cpu = run.cpus.sub;
    } else {
      pair.sub_argv = role_args(run, method + "-sub", liblcm);  // floor-sub, liblcm-sub, lcmx-shm-sub, ...
      pair.pub_argv = role_args(run, method + "-pub", liblcm);
      pair.sub_cpu = run.cpus.sub;
      pair.pub_cpu = run.cpus.pub;
    }
    out = run_pair(pair);
  }
  MethodResult& res = out.result;
  if (out.killed && method.rfind("lcmx", 0) == 0) {
    const auto rep = lcmx::shm::reclaim_orphans();  // segments of the children we killed
    if (rep.removed) say(method + ": reclaimed " + std::to_string(rep.removed) + " orphaned lcmx shm segments");
  }
  ::shm_unlink(("/" + run.name + "_floor").c_str());
  progress_of("bench", res, run.plan);
  char t[64];
  std::snprintf(t, sizeof t, "%.1f s", static_cast<double>(now_ns() - t0) / 1e9);
  say(method + ": finished in " + t);
  return res;
}

// ---------------------------------------------------------------- report

const MethodResult* find(const std::vector<MethodResult>& rs, const std::string& m) {
  for (const auto& r : rs)
    if (r.method == m) return &r;
  return nullptr;
}

// p50 of a method at a size, if measured with at least one message delivered.
std::optional<double> p50(const std::vector<MethodResult>& rs, const std::string& m, std::size_t size) {
  const MethodResult* r = find(rs, m);
  if (!r) return std::nullopt;
  const Cell c = cell_of(*r, size);
  if (!c.ok || c.st.n == 0) return std::nullopt;
  return c.st.p50;
}

std::string targets(const Run& run, const std::vector<MethodResult>& rs) {
  const std::size_t kb1 = 1024, mb6 = 6u << 20;
  auto has = [&](std::size_t s) {
    return std::any_of(run.plan.begin(), run.plan.end(), [&](const SizePlan& p) { return p.size == s; });
  };
  std::string out = "**Targets** (p50; differences under 1.3x are noise on this machine):\n";
  // 1. typed shm within 1.3x of the floor at every size
  {
    std::string t = "- Typed shared-memory path within 1.3x of the floor at every size: ";
    if (!find(rs, "lcmx-shm") || !find(rs, "floor")) t += "not measured (needs lcmx-shm and floor)";
    else {
      double worst = 0;
      std::size_t worst_size = 0;
      bool all = true;
      for (const auto& p : run.plan) {
        const auto a = p50(rs, "lcmx-shm", p.size), b = p50(rs, "floor", p.size);
        if (!a || !b) {
          all = false;
          continue;
        }
        if (*a / *b > worst) worst = *a / *b, worst_size = p.size;
      }
      if (!all) t += "**FAILS** (lcmx-shm or floor has no result at some size)";
      else t += verdict(worst <= 1.3) + " (worst " + fmt_ratio(worst) + " at " + size_label(worst_size) + ")";
    }
    out += t + "\n";
  }
  // 2. at least 5x faster than liblcm at 1 KB and 3x at 6 MB
  auto vs_liblcm = [&](std::size_t size, double need) {
    if (!has(size)) return std::string("not measured (size not in --sizes)");
    const MethodResult* l = find(rs, "liblcm");
    const auto s = p50(rs, "lcmx-shm", size);
    if (!l || !find(rs, "lcmx-shm")) return std::string("not measured (needs liblcm and lcmx-shm)");
    if (!s) return std::string("**FAILS** (lcmx-shm has no result)");
    const Cell lc = cell_of(*l, size);
    if (!lc.ok) return std::string("not measured (liblcm failed)");
    if (lc.st.n == 0)
      return "**holds** only in the sense that liblcm delivered none of " + std::to_string(lc.sent) +
             " messages (no latency to compare)";
    const double r = lc.st.p50 / *s;
    std::string t = verdict(r >= need) + " (" + fmt_ratio(r) + ")";
    if (lc.lost) t += ", liblcm lost " + std::to_string(lc.lost) + "/" + std::to_string(lc.sent);
    return t;
  };
  out += "- At least 5x faster than liblcm at 1 KB: " + vs_liblcm(kb1, 5.0) + "\n";
  out += "- At least 3x faster than liblcm at 6 MB: " + vs_liblcm(mb6, 3.0) + "\n";
  // 3. loan at 6 MB within 3x of its 1 KB latency
  {
    std::string t = "- Loan at 6 MB within 3x of its 1 KB latency: ";
    if (!find(rs, "lcmx-loan")) t += "not measured (needs lcmx-loan)";
    else if (!has(kb1) || !has(mb6)) t += "not measured (needs 1 KB and 6 MB in --sizes)";
    else {
      const auto a = p50(rs, "lcmx-loan", mb6), b = p50(rs, "lcmx-loan", kb1);
      if (!a || !b) t += "**FAILS** (lcmx-loan has no result)";
      else t += verdict(*a / *b <= 3.0) + " (" + fmt_ratio(*a / *b) + ")";
    }
    out += t + "\n";
  }
  return out;
}

std::string markdown(const Run& run, const std::vector<MethodResult>& rs) {
  std::ostringstream md;
  md << "## lcmx one-way latency, one host (experiment 1)\n\n";
  md << "- " << machine_line() << "\n";
  md << "- pinning: `--pin " << run.opt.pin << "`";
  if (run.opt.pin == "same") md << " (publisher and subscriber on CPU 0)";
  else if (run.opt.pin == "split") md << " (publisher on CPU 0, subscriber on CPU 1)";
  else md << " (scheduler decides)";
  md << "; lcmx subscriber wait strategy: `--wait " << run.opt.wait
     << "` (floor and liblcm always sleep: futex / poll)\n";
  md << "- messages per size (warmup + measured): " << plan_text(run.plan)
     << "; ping-pong (next message only after the previous was acked or timed out after " << run.opt.timeout_ms
     << " ms = lost)\n";
  md << "- acks (not in the measured time): floor: a second futex word in its segment; liblcm and "
        "lcmx: a pipe side channel (8-byte seq) subscriber -> publisher\n";
  md << "- cells: p50 / p99 one-way latency in µs (nearest rank), publisher's CLOCK_MONOTONIC "
        "before encode/copy -> subscriber's after decode/copy; ratios use p50\n\n";

  auto has = [&](const char* m) { return find(rs, m) != nullptr; };
  const bool r1 = has("lcmx-shm") && has("floor"), r2 = has("liblcm") && has("lcmx-shm"), r3 = has("lcmx-loan");
  std::size_t loan_base = 0;
  for (const auto& p : run.plan)
    if (p.size == 1024) loan_base = 1024;
  if (!loan_base && !run.plan.empty()) loan_base = run.plan.front().size;
  std::vector<std::string> header{"size"};
  for (const auto& r : rs) header.push_back(r.method);
  if (r1) header.push_back("lcmx-shm/floor");
  if (r2) header.push_back("liblcm/lcmx-shm");
  if (r3) header.push_back("loan/loan@" + size_label(loan_base));
  Table table(header);
  auto ratio = [&](const char* a, std::size_t sa, const char* b, std::size_t sb) {
    const auto x = p50(rs, a, sa), y = p50(rs, b, sb);
    return x && y ? fmt_ratio(*x / *y) : std::string("—");
  };
  for (const auto& p : run.plan) {
    std::vector<std::string> row{size_label(p.size)};
    for (const auto& r : rs) row.push_back(cell_text(r, p.size));
    if (r1) row.push_back(ratio("lcmx-shm", p.size, "floor", p.size));
    if (r2) row.push_back(ratio("liblcm", p.size, "lcmx-shm", p.size));
    if (r3) row.push_back(ratio("lcmx-loan", p.size, "lcmx-loan", loan_base));
    table.row(row);
  }
  md << table.markdown() << "\n" << targets(run, rs);
  std::vector<std::pair<std::string, std::string>> failures, notes;
  for (const auto& r : rs) {
    for (const auto& e : r.errors) failures.emplace_back(r.method, e);
    for (const auto& n : r.notes) notes.emplace_back(r.method, n);
  }
  md << list_section("Failures", failures) << list_section("Notes", notes);
  return md.str();
}

void write_csv(const std::string& path, const Run& run, const std::vector<MethodResult>& rs) {
  Csv csv(path, "method,size_bytes,sent,received,lost,p50_us,p99_us,mean_us,min_us,max_us,pin,wait,status");
  for (const auto& r : rs)
    for (const auto& p : run.plan) {
      const Cell c = cell_of(r, p.size);
      const std::string status = c.ok ? "ok" : "failed";
      if (!c.ok) csv.row(r.method, p.size, "", "", "", "", "", "", "", "", run.opt.pin, run.opt.wait, status);
      else if (!c.st.n) csv.row(r.method, p.size, c.sent, c.st.n, c.lost, "", "", "", "", "", run.opt.pin, run.opt.wait, status);
      else
        csv.row(r.method, p.size, c.sent, c.st.n, c.lost, c.st.p50, c.st.p99, c.st.mean, c.st.min, c.st.max,
                run.opt.pin, run.opt.wait, status);
    }
  csv.close();
}

int orchestrate(const Options& opt) {
  Run run;
  run.opt = opt;
  try {
    run.plan = make_plan(opt.sizes, {{20, 10, 5}, {200, 100, 50}}, opt.messages, opt.warmup);
  } catch (const std::exception& e) {
    return bad_options(kProgram, e.what());
  }
  if (opt.pin == "split")
    if (const auto why = split_unavailable()) return bad_options(kProgram, *why);
  run.name = "lcmxbench_" + std::to_string(::getpid());
  run.exe = self_exe();
  run.cpus = pinning(opt.pin);
  on_stop_signals(OnStop::kill_children);
  sweep_stale();

  std::vector<MethodResult> results;
  {
    LoopbackNamespace ns(run.name);
    run.netns = &ns;
    if (std::find(opt.methods.begin(), opt.methods.end(), "liblcm") != opt.methods.end()) {
      run.netns_error = ns.create();
      if (run.netns_error) say("liblcm: cannot set up its network namespace: " + *run.netns_error);
      else say("liblcm runs in network namespace " + ns.name() + " (lo, 224.0.0.0/4 via lo)");
    }
    for (const auto& m : opt.methods) {
      if (stopped()) break;
      results.push_back(run_method(run, m));
    }
  }  // the namespace is removed here
  if (stopped()) {
    std::cerr << kProgram << ": interrupted by signal " << stop_flag().load() << "; cleaned up\n";
    return 128 + stop_flag().load();
  }
  int rc = print_report(kProgram, markdown(run, results), opt.markdown, [&] {
    if (!opt.csv.empty()) write_csv(opt.csv, run, results);
  }) ? 0 : 1;
  for (const auto& r : results)
    if (r.failed()) rc = 1;
  return rc;
}

int run_role(const RoleConfig& cfg) {
  if (cfg.role == "floor-sub") return run_floor_sub(cfg);
  if (cfg.role == "floor-pub") return run_floor_pub(cfg);
  if (cfg.role == "liblcm-sub") return run_liblcm_sub(cfg);
  if (cfg.role == "liblcm-pub") return run_liblcm_pub(cfg);
  if (cfg.role == "lcmx-shm-sub") return run_lcmx_sub(cfg, false);
  if (cfg.role == "lcmx-shm-pub") return run_lcmx_pub(cfg, false);
  if (cfg.role == "lcmx-loan-sub") return run_lcmx_sub(cfg, true);
  if (cfg.role == "lcmx-loan-pub") return run_lcmx_pub(cfg, true);
  if (cfg.role == "lcmx-intra") return run_lcmx_intra(cfg);
  report_error("unknown role " + cfg.role);
  return 2;
}

}  // namespace
}  // namespace lcmxbench

int main(int argc, char** argv) {
  using namespace lcmxbench;
  CLI::App app{
      "lcmx one-way latency benchmark (experiment 1, one host): publisher -> subscriber in\n"
      "another process, by method and size, all methods in one run. Markdown table on stdout,\n"
      "progress on stderr. Needs root for the liblcm network namespace."};
  Options opt;
  app.add_option("--sizes", opt.sizes, "message sizes (K = 1024, M = 1024*1024)")
      ->delimiter(',')->capture_default_str();
  app.add_option("--messages", opt.messages,
                 "measured messages per size (default: 200 up to 100 KB, 100 up to 2 MB, 50 above)")
      ->check(CLI::PositiveNumber);
  app.add_option("--warmup", opt.warmup, "unmeasured messages per size first (default: 20 / 10 / 5)")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--methods", opt.methods, "methods, in run order")
      ->delimiter(',')
      ->check(CLI::IsMember({"floor", "liblcm", "lcmx-intra", "lcmx-shm", "lcmx-loan"}))
      ->capture_default_str();
  add_pin_option(app, opt.pin, {"none", "same", "split"},
                 "CPU pinning: none, same (both on CPU 0), split (pub CPU 0, sub CPU 1)");
  add_wait_option(app, opt.wait,
                  "lcmx subscriber node's WaitStrategy: block, spin (spin_then_block), adaptive, busy (busy_poll)");
  app.add_option("--timeout-ms", opt.timeout_ms, "receive timeout per message; then it counts as lost")
      ->check(CLI::Range(10, 10000))->capture_default_str();
  app.add_option("--lcm-url", opt.lcm_url, "liblcm udpm URL (inside the bench's namespace)")->capture_default_str();
  app.add_option("--discovery-url", opt.discovery_url, "lcmx discovery URL (never the default group)")
      ->capture_default_str();
  app.add_option("--csv", opt.csv, "also write per method/size results as CSV");
  app.add_option("--markdown", opt.markdown, "also write the Markdown report to this file");

  // The children (bench/python/bench_python.py starts the lcmx roles too).
  RoleConfig cfg;
  std::string plan;
  add_hidden(app, "--role", cfg.role);
  add_hidden(app, "--plan", plan);
  add_hidden(app, "--name", cfg.name);
  add_hidden(app, "--url", cfg.url);
  add_hidden(app, "--pub-cpu", cfg.pub_cpu);
  add_hidden(app, "--sub-cpu", cfg.sub_cpu);
  CLI11_PARSE(app, argc, argv);

  if (!cfg.role.empty()) {
    try {
      cfg.plan = plan_from_string(plan);
    } catch (const std::exception& e) {
      report_error(e.what());
      return 2;
    }
    cfg.wait = opt.wait;
    cfg.timeout_ms = opt.timeout_ms;
    return run_role(cfg);
  }
  return orchestrate(opt);
}
