// lcmx_bench_latency: one-way latency publisher -> subscriber in another process, by method
// and message size, all methods in one run (DESIGN.md "Benchmarks", experiment 1, one host).
//
// Without --role this is the orchestrator: it runs each method's subscriber and publisher as
// children (fork/exec of this binary with a hidden --role), reads their report lines, and
// prints a Markdown table on stdout (progress on stderr). See bench/README.md.
#include <dirent.h>
#include <fcntl.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/utsname.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <fstream>
#include <iostream>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "common.hpp"
#include "lcmx/shm/segment.hpp"

namespace lcmxbench {
namespace {

// ---------------------------------------------------------------- signals and children

std::atomic<int> g_signal{0};
constexpr int kMaxChildren = 8;
std::atomic<pid_t> g_children[kMaxChildren];

void on_signal(int sig) {
  g_signal.store(sig);
  for (auto& c : g_children) {
    const pid_t p = c.load();
    if (p > 0) ::kill(p, SIGKILL);
  }
}

void install_signal_handlers() {
  struct sigaction sa{};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sa.sa_flags = 0;  // no SA_RESTART: blocking calls return EINTR and loops check g_signal
  for (int s : {SIGINT, SIGTERM, SIGHUP}) ::sigaction(s, &sa, nullptr);
  ::signal(SIGPIPE, SIG_IGN);
}

struct Interrupted {};
void check_signal() {
  if (g_signal.load() != 0) throw Interrupted{};
}

void track(pid_t pid) {
  for (auto& c : g_children) {
    pid_t expected = 0;
    if (c.compare_exchange_strong(expected, pid)) return;
  }
}
void untrack(pid_t pid) {
  for (auto& c : g_children) {
    pid_t expected = pid;
    c.compare_exchange_strong(expected, 0);
  }
}

// Starts argv with fds as 3.. (see spawn_child) and tracks it for the signal handler.
pid_t spawn(const std::vector<std::string>& argv, const std::vector<int>& fds, int cpu) {
  const pid_t pid = spawn_child(argv, fds, cpu);
  track(pid);
  return pid;
}

// Waits for pid up to timeout_ms, then SIGKILLs it. Returns the wait status.
int reap(pid_t pid, int timeout_ms) {
  const int status = reap_child(pid, timeout_ms, g_signal);
  untrack(pid);
  return status;
}

bool run_cmd(const std::vector<std::string>& argv) {
  const pid_t pid = spawn(argv, {}, -1);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {}
  untrack(pid);
  return WIFEXITED(status) && WEXITSTATUS(status) == 0;
}

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
      std::cerr << "[bench] removing stale network namespace " << n << "\n";
      run_cmd({"ip", "netns", "del", n});
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

// The liblcm pair's network namespace: loopback up, multicast routed to lo. Deleted by the
// destructor (every exit path but SIGKILL; the next run's sweep_stale() handles that one).
class NetNs {
 public:
  explicit NetNs(std::string name) : name_(std::move(name)) {}
  NetNs(const NetNs&) = delete;
  ~NetNs() {
    if (created_) run_cmd({"ip", "netns", "del", name_});
  }
  // Returns an error text, or nothing on success.
  std::optional<std::string> create() {
    if (!run_cmd({"ip", "netns", "add", name_})) return "ip netns add " + name_ + " failed (root needed)";
    created_ = true;
    if (!run_cmd({"ip", "-n", name_, "link", "set", "lo", "up"})) return "ip link set lo up failed";
    if (!run_cmd({"ip", "-n", name_, "route", "add", "224.0.0.0/4", "dev", "lo"}))
      return "ip route add 224.0.0.0/4 dev lo failed";
    return std::nullopt;
  }
  const std::string& name() const { return name_; }

 private:
  std::string name_;
  bool created_ = false;
};

// ---------------------------------------------------------------- results

struct SizeResult {
  std::optional<int> sent;        // from the publisher's "sent" line
  int ack_timeouts = 0;
  std::optional<std::vector<std::int64_t>> lat;  // from the subscriber's "lat" line
};

struct MethodResult {
  std::string method;
  std::vector<std::string> errors;
  std::vector<std::string> notes;
  std::map<std::size_t, SizeResult> sizes;
  bool failed() const { return !errors.empty(); }
};

struct Stats {
  std::size_t n = 0;
  double p50 = 0, p99 = 0, mean = 0, min = 0, max = 0;  // µs
};

Stats stats_of(std::vector<std::int64_t> v) {
  Stats s;
  s.n = v.size();
  if (v.empty()) return s;
  std::sort(v.begin(), v.end());
  auto rank = [&](double q) {  // nearest rank
    std::size_t k = static_cast<std::size_t>(std::ceil(q * static_cast<double>(v.size())));
    return static_cast<double>(v[std::clamp<std::size_t>(k, 1, v.size()) - 1]) / 1000.0;
  };
  s.p50 = rank(0.50);
  s.p99 = rank(0.99);
  double sum = 0;
  for (auto x : v) sum += static_cast<double>(x);
  s.mean = sum / static_cast<double>(v.size()) / 1000.0;
  s.min = static_cast<double>(v.front()) / 1000.0;
  s.max = static_cast<double>(v.back()) / 1000.0;
  return s;
}

// A size measured completely: the publisher said how many it sent, the subscriber reported.
struct Cell {
  bool ok = false;
  Stats st;
  int sent = 0;
  int lost = 0;
};

Cell cell_of(const MethodResult& m, std::size_t size) {
  Cell c;
  const auto it = m.sizes.find(size);
  if (it == m.sizes.end() || !it->second.sent || !it->second.lat) return c;
  c.ok = true;
  c.sent = *it->second.sent;
  c.st = stats_of(*it->second.lat);
  c.lost = std::max(0, c.sent - static_cast<int>(c.st.n));
  return c;
}

void parse_line(MethodResult& r, const std::string& line) {
  std::istringstream in(line);
  std::string kind;
  in >> kind;
  auto rest = [&] {
    std::string s;
    std::getline(in, s);
    if (!s.empty() && s[0] == ' ') s.erase(0, 1);
    return s;
  };
  if (kind == "error") {
    r.errors.push_back(rest());
  } else if (kind == "note") {
    r.notes.push_back(rest());
  } else if (kind == "sent") {
    std::size_t size = 0;
    int n = 0, to = 0;
    if (in >> size >> n >> to) {
      r.sizes[size].sent = n;
      r.sizes[size].ack_timeouts = to;
    }
  } else if (kind == "lat") {
    std::size_t size = 0, n = 0;
    if (in >> size >> n) {
      std::vector<std::int64_t> v;
      v.reserve(n);
      std::int64_t x;
      while (v.size() < n && in >> x) v.push_back(x);
      r.sizes[size].lat = std::move(v);
    }
  }
}

// Polls the children's report lines (see lcmxbench::pump_until); throws Interrupted on a signal.
bool pump_until(const std::vector<LineReader*>& rs, std::int64_t deadline, const std::function<bool()>& until) {
  const bool ok = lcmxbench::pump_until(rs, deadline, until, g_signal);
  check_signal();
  return ok;
}

// ---------------------------------------------------------------- orchestration

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

std::size_t parse_size(const std::string& text) {
  std::size_t pos = 0;
  const double v = std::stod(text, &pos);
  std::string unit = text.substr(pos);
  for (auto& c : unit) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  double mul = 1;
  if (unit == "K" || unit == "KB" || unit == "KIB") mul = 1024;
  else if (unit == "M" || unit == "MB" || unit == "MIB") mul = 1024.0 * 1024;
  else if (!unit.empty() && unit != "B") throw std::invalid_argument("bad size '" + text + "'");
  const auto bytes = static_cast<std::size_t>(v * mul);
  if (bytes < 16 || bytes > (64u << 20)) throw std::invalid_argument("size '" + text + "' out of 16 B..64 MB");
  return bytes;
}

std::vector<SizePlan> make_plan(const Options& o) {
  std::vector<SizePlan> plan;
  for (const auto& s : o.sizes) {
    SizePlan p;
    p.size = parse_size(s);
    if (p.size <= 100 * 1024) p.warmup = 20, p.messages = 200;
    else if (p.size <= 2 * 1024 * 1024) p.warmup = 10, p.messages = 100;
    else p.warmup = 5, p.messages = 50;
    if (o.messages > 0) p.messages = o.messages;
    if (o.warmup >= 0) p.warmup = o.warmup;
    plan.push_back(p);
  }
  return plan;
}

struct Run {
  Options opt;
  std::vector<SizePlan> plan;
  std::string name;  // lcmxbench_<pid>
  std::string exe;
  int pub_cpu = -1, sub_cpu = -1;
  NetNs* netns = nullptr;
  std::optional<std::string> netns_error;
};

std::vector<std::string> role_args(const Run& run, const std::string& role, bool netns) {
  std::vector<std::string> a;
  if (netns) a = {"ip", "netns", "exec", run.netns->name()};
  const bool liblcm = role.rfind("liblcm", 0) == 0;
  std::vector<std::string> r = {
      run.exe, "--role", role, "--plan", plan_to_string(run.plan), "--name", run.name,
      "--url", liblcm ? run.opt.lcm_url : run.opt.discovery_url, "--wait", run.opt.wait,
      "--timeout-ms", std::to_string(run.opt.timeout_ms),
      "--pub-cpu", std::to_string(run.pub_cpu), "--sub-cpu", std::to_string(run.sub_cpu)};
  a.insert(a.end(), r.begin(), r.end());
  return a;
}

int method_deadline_ms(const Run& run) {
  std::int64_t ms = 45'000;  // start-up, matching (15 s each side), teardown
  for (const auto& p : run.plan)
    ms += static_cast<std::int64_t>(p.warmup + p.messages) * (run.opt.timeout_ms + 50);
  return static_cast<int>(std::min<std::int64_t>(ms, 1'800'000));
}

void progress(const std::string& s) { std::cerr << "[bench] " << s << std::endl; }

MethodResult run_method(const Run& run, const std::string& method) {
  MethodResult res;
  res.method = method;
  progress(method + ": starting");
  const std::int64_t t0 = now_ns();
  const std::int64_t deadline = t0 + static_cast<std::int64_t>(method_deadline_ms(run)) * 1'000'000;
  std::vector<pid_t> pids;
  std::vector<std::unique_ptr<LineReader>> readers;
  bool timed_out = false;

  try {
    if (method == "lcmx-intra") {
      Pipe rep;
      // one process, publisher thread on pub_cpu, subscriber thread on sub_cpu (both: see lcmx.cpp)
      const int cpu = run.sub_cpu;
      pids.push_back(spawn(role_args(run, "lcmx-intra", false), {rep.w}, cpu));
      rep.close_w();
      auto r = std::make_unique<LineReader>();
      r->fd = rep.r;
      rep.r = -1;
      readers.push_back(std::move(r));
    } else {
      const bool liblcm = method == "liblcm";
      if (liblcm && run.netns_error) throw std::runtime_error("network namespace: " + *run.netns_error);
      std::string sub_role, pub_role;
      if (method == "floor") sub_role = "floor-sub", pub_role = "floor-pub";
      else if (liblcm) sub_role = "liblcm-sub", pub_role = "liblcm-pub";
      else if (method == "lcmx-shm") sub_role = "lcmx-shm-sub", pub_role = "lcmx-shm-pub";
      else sub_role = "lcmx-loan-sub", pub_role = "lcmx-loan-pub";
      Pipe rep_sub, rep_pub, ack, ctl;
      pids.push_back(spawn(role_args(run, sub_role, liblcm), {rep_sub.w, ack.w, ctl.r}, run.sub_cpu));
      rep_sub.close_w();
      ack.close_w();
      ctl.close_r();
      auto rs = std::make_unique<LineReader>();
      rs->fd = rep_sub.r;
      rep_sub.r = -1;
      LineReader* sub = rs.get();
      readers.push_back(std::move(rs));
      // never sleep to synchronise: wait for the subscriber's "ready" line (or its failure)
      const std::int64_t ready_deadline = std::min(deadline, now_ns() + 20'000'000'000);
      auto is_ready = [&] {
        return std::any_of(sub->lines.begin(), sub->lines.end(), [](const std::string& l) {
          return l == "ready" || l.rfind("error", 0) == 0;
        });
      };
      if (!pump_until({sub}, ready_deadline, is_ready) || !is_ready()) {
        for (const auto& l : sub->lines) parse_line(res, l);
        throw std::runtime_error(sub->eof ? "subscriber exited before it was ready"
                                          : "subscriber not ready within 20 s");
      }
      if (std::none_of(sub->lines.begin(), sub->lines.end(), [](const std::string& l) { return l == "ready"; })) {
        // it reported an error instead; collect it below
      } else {
        progress(method + ": subscriber ready, starting publisher");
        pids.push_back(spawn(role_args(run, pub_role, liblcm), {rep_pub.w, ack.r, ctl.w}, run.pub_cpu));
      }
      rep_pub.close_w();
      ack.close_r();
      ctl.close_w();
      auto rp = std::make_unique<LineReader>();
      rp->fd = rep_pub.r;
      rep_pub.r = -1;
      readers.push_back(std::move(rp));
    }
    std::vector<LineReader*> rs;
    for (auto& r : readers) rs.push_back(r.get());
    timed_out = !pump_until(rs, deadline, [] { return false; });
  } catch (const Interrupted&) {
    for (auto p : pids) reap(p, 0);
    for (auto& r : readers) ::close(r->fd);
    throw;
  } catch (const std::exception& e) {
    res.errors.push_back(e.what());
  }

  bool killed = false;
  for (auto p : pids) {
    const int st = reap(p, timed_out ? 0 : 5000);
    if (WIFSIGNALED(st)) {
      killed = true;
      if (!timed_out) res.errors.push_back("a child died of signal " + std::to_string(WTERMSIG(st)));
    } else if (WIFEXITED(st) && WEXITSTATUS(st) == 126) {
      res.errors.push_back("could not pin a child (sched_setaffinity)");
    } else if (WIFEXITED(st) && WEXITSTATUS(st) == 127) {
      res.errors.push_back("could not start a child (exec failed)");
    }
  }
  for (auto& r : readers) {
    for (const auto& l : r->lines)
      if (l != "ready" && l != "done") parse_line(res, l);
    ::close(r->fd);
  }
  if (timed_out) {
    res.errors.push_back("timed out after " + std::to_string(method_deadline_ms(run) / 1000) +
                         " s; children killed");
    killed = true;
  }
  if (killed && method.rfind("lcmx", 0) == 0) {
    const auto rep = lcmx::shm::reclaim_orphans();  // segments of the children we killed
    if (rep.removed) progress(method + ": reclaimed " + std::to_string(rep.removed) + " orphaned lcmx shm segments");
  }
  ::shm_unlink(("/" + run.name + "_floor").c_str());

  for (const auto& p : run.plan) {
    const Cell c = cell_of(res, p.size);
    if (c.ok) {
      char buf[256];
      std::snprintf(buf, sizeof buf, "%s %s: p50 %.1f us, p99 %.1f us, mean %.1f us, received %zu/%d",
                    method.c_str(), size_label(p.size).c_str(), c.st.p50, c.st.p99, c.st.mean, c.st.n, c.sent);
      progress(buf);
    }
  }
  for (const auto& e : res.errors) progress(method + ": FAILED: " + e);
  for (const auto& n : res.notes) progress(method + ": " + n);
  char t[64];
  std::snprintf(t, sizeof t, "%.1f s", static_cast<double>(now_ns() - t0) / 1e9);
  progress(method + ": finished in " + t);
  return res;
}

// ---------------------------------------------------------------- report

std::string fmt_ratio(double r) {
  char b[32];
  std::snprintf(b, sizeof b, "%.2fx", r);
  return b;
}

const MethodResult* find(const std::vector<MethodResult>& rs, const std::string& m) {
  for (const auto& r : rs)
    if (r.method == m) return &r;
  return nullptr;
}

std::string cell_text(const MethodResult& m, std::size_t size) {
  const Cell c = cell_of(m, size);
  if (!c.ok) return m.failed() ? "failed" : "—";
  std::string s = c.st.n ? fmt_us(c.st.p50) + " / " + fmt_us(c.st.p99) : "—";
  if (c.lost) s += " (lost " + std::to_string(c.lost) + "/" + std::to_string(c.sent) + ")";
  return s;
}

// p50 of a method at a size, if measured with at least one message delivered.
std::optional<double> p50(const std::vector<MethodResult>& rs, const std::string& m, std::size_t size) {
  const MethodResult* r = find(rs, m);
  if (!r) return std::nullopt;
  const Cell c = cell_of(*r, size);
  if (!c.ok || c.st.n == 0) return std::nullopt;
  return c.st.p50;
}

std::string targets_line(const Run& run, const std::vector<MethodResult>& rs) {
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
      else t += std::string(worst <= 1.3 ? "**holds**" : "**FAILS**") + " (worst " + fmt_ratio(worst) +
                " at " + size_label(worst_size) + ")";
    }
    out += t + "\n";
  }
  // 2. at least 5x faster than liblcm at 1 KB and 3x at 6 MB
  auto vs_liblcm = [&](std::size_t size, double need) {
    std::string t;
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
    t = std::string(r >= need ? "**holds**" : "**FAILS**") + " (" + fmt_ratio(r) + ")";
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
      else t += std::string(*a / *b <= 3.0 ? "**holds**" : "**FAILS**") + " (" + fmt_ratio(*a / *b) + ")";
    }
    out += t + "\n";
  }
  return out;
}

std::string markdown(const Run& run, const std::vector<MethodResult>& rs) {
  std::ostringstream md;
  char date[64];
  const std::time_t now = std::time(nullptr);
  std::strftime(date, sizeof date, "%Y-%m-%d %H:%M:%S %Z", std::localtime(&now));
  utsname u{};
  ::uname(&u);
  md << "## lcmx one-way latency, one host (experiment 1)\n\n";
  md << "- " << date << ", " << u.nodename << ", Linux " << u.release << ", "
     << ::sysconf(_SC_NPROCESSORS_ONLN) << " CPUs online\n";
  md << "- pinning: `--pin " << run.opt.pin << "`";
  if (run.opt.pin == "same") md << " (publisher and subscriber on CPU 0)";
  else if (run.opt.pin == "split") md << " (publisher on CPU 0, subscriber on CPU 1)";
  else md << " (scheduler decides)";
  md << "; lcmx subscriber wait strategy: `--wait " << run.opt.wait
     << "` (floor and liblcm always sleep: futex / poll)\n";
  md << "- messages per size (warmup + measured): ";
  for (std::size_t i = 0; i < run.plan.size(); ++i)
    md << (i ? ", " : "") << size_label(run.plan[i].size) << " " << run.plan[i].warmup << "+"
       << run.plan[i].messages;
  md << "; ping-pong (next message only after the previous was acked or timed out after "
     << run.opt.timeout_ms << " ms = lost)\n";
  md << "- acks (not in the measured time): floor: a second futex word in its segment; liblcm and "
        "lcmx: a pipe side channel (8-byte seq) subscriber -> publisher\n";
  md << "- cells: p50 / p99 one-way latency in µs (nearest rank), publisher's CLOCK_MONOTONIC "
        "before encode/copy -> subscriber's after decode/copy; ratios use p50\n\n";

  auto has = [&](const char* m) { return find(rs, m) != nullptr; };
  md << "| size |";
  for (const auto& r : rs) md << " " << r.method << " |";
  const bool r1 = has("lcmx-shm") && has("floor"), r2 = has("liblcm") && has("lcmx-shm"), r3 = has("lcmx-loan");
  std::size_t loan_base = 0;
  for (const auto& p : run.plan)
    if (p.size == 1024) loan_base = 1024;
  if (!loan_base && !run.plan.empty()) loan_base = run.plan.front().size;
  if (r1) md << " lcmx-shm/floor |";
  if (r2) md << " liblcm/lcmx-shm |";
  if (r3) md << " loan/loan@" << size_label(loan_base) << " |";
  md << "\n|---|";
  for (std::size_t i = 0; i < rs.size() + r1 + r2 + r3; ++i) md << "---|";
  md << "\n";
  auto ratio = [&](const char* a, std::size_t sa, const char* b, std::size_t sb) {
    const auto x = p50(rs, a, sa), y = p50(rs, b, sb);
    return x && y ? fmt_ratio(*x / *y) : std::string("—");
  };
  for (const auto& p : run.plan) {
    md << "| " << size_label(p.size) << " |";
    for (const auto& r : rs) md << " " << cell_text(r, p.size) << " |";
    if (r1) md << " " << ratio("lcmx-shm", p.size, "floor", p.size) << " |";
    if (r2) md << " " << ratio("liblcm", p.size, "lcmx-shm", p.size) << " |";
    if (r3) md << " " << ratio("lcmx-loan", p.size, "lcmx-loan", loan_base) << " |";
    md << "\n";
  }
  md << "\n" << targets_line(run, rs);
  bool any = false;
  for (const auto& r : rs)
    for (const auto& e : r.errors) {
      if (!any) md << "\n**Failures**\n";
      any = true;
      md << "- " << r.method << ": " << e << "\n";
    }
  any = false;
  for (const auto& r : rs)
    for (const auto& n : r.notes) {
      if (!any) md << "\n**Notes**\n";
      any = true;
      md << "- " << r.method << ": " << n << "\n";
    }
  return md.str();
}

void write_csv(const std::string& path, const Run& run, const std::vector<MethodResult>& rs) {
  std::ofstream f(path);
  f << "method,size_bytes,sent,received,lost,p50_us,p99_us,mean_us,min_us,max_us,pin,wait,status\n";
  for (const auto& r : rs)
    for (const auto& p : run.plan) {
      const Cell c = cell_of(r, p.size);
      f << r.method << ',' << p.size << ',';
      if (c.ok) {
        f << c.sent << ',' << c.st.n << ',' << c.lost << ',';
        if (c.st.n) f << c.st.p50 << ',' << c.st.p99 << ',' << c.st.mean << ',' << c.st.min << ',' << c.st.max;
        else f << ",,,,";
      } else {
        f << ",,,,,,,";
      }
      f << ',' << run.opt.pin << ',' << run.opt.wait << ',' << (c.ok ? "ok" : "failed") << "\n";
    }
  if (!f) throw std::runtime_error("cannot write " + path);
}

int orchestrate(const Options& opt) {
  Run run;
  run.opt = opt;
  try {
    run.plan = make_plan(opt);
  } catch (const std::exception& e) {
    std::cerr << "lcmx_bench_latency: " << e.what() << "\n";
    return 2;
  }
  run.name = "lcmxbench_" + std::to_string(::getpid());
  run.exe = self_exe();
  if (opt.pin == "same") run.pub_cpu = 0, run.sub_cpu = 0;
  else if (opt.pin == "split") run.pub_cpu = 0, run.sub_cpu = 1;
  if (opt.pin == "split" && ::sysconf(_SC_NPROCESSORS_ONLN) < 2) {
    std::cerr << "lcmx_bench_latency: --pin split needs 2 CPUs\n";
    return 1;
  }
  install_signal_handlers();
  sweep_stale();

  std::vector<MethodResult> results;
  int rc = 0;
  try {
    NetNs ns(run.name);
    run.netns = &ns;
    if (std::find(opt.methods.begin(), opt.methods.end(), "liblcm") != opt.methods.end()) {
      run.netns_error = ns.create();
      if (run.netns_error) progress("liblcm: cannot set up its network namespace: " + *run.netns_error);
      else progress("liblcm runs in network namespace " + ns.name() + " (lo, 224.0.0.0/4 via lo)");
    }
    for (const auto& m : opt.methods) results.push_back(run_method(run, m));
  } catch (const Interrupted&) {
    std::cerr << "lcmx_bench_latency: interrupted by signal " << g_signal.load() << "; cleaned up\n";
    ::shm_unlink(("/" + run.name + "_floor").c_str());
    return 128 + g_signal.load();
  }
  const std::string md = markdown(run, results);
  std::cout << md << std::flush;
  try {
    if (!opt.markdown.empty()) {
      std::ofstream f(opt.markdown);
      f << md;
      if (!f) throw std::runtime_error("cannot write " + opt.markdown);
    }
    if (!opt.csv.empty()) write_csv(opt.csv, run, results);
  } catch (const std::exception& e) {
    std::cerr << "lcmx_bench_latency: " << e.what() << "\n";
    rc = 1;
  }
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
  app.add_option("--pin", opt.pin, "CPU pinning: none, same (both on CPU 0), split (pub CPU 0, sub CPU 1)")
      ->check(CLI::IsMember({"none", "same", "split"}))->capture_default_str();
  app.add_option("--wait", opt.wait, "lcmx subscriber node's WaitStrategy: block, spin (spin_then_block), adaptive, busy (busy_poll)")
      ->check(CLI::IsMember({"block", "spin", "adaptive", "busy"}))->capture_default_str();
  app.add_option("--timeout-ms", opt.timeout_ms, "receive timeout per message; then it counts as lost")
      ->check(CLI::Range(10, 10000))->capture_default_str();
  app.add_option("--lcm-url", opt.lcm_url, "liblcm udpm URL (inside the bench's namespace)")->capture_default_str();
  app.add_option("--discovery-url", opt.discovery_url, "lcmx discovery URL (never the default group)")
      ->capture_default_str();
  app.add_option("--csv", opt.csv, "also write per method/size results as CSV");
  app.add_option("--markdown", opt.markdown, "also write the Markdown report to this file");

  // Hidden: the child roles.
  RoleConfig cfg;
  std::string plan;
  app.add_option("--role", cfg.role)->group("");
  app.add_option("--plan", plan)->group("");
  app.add_option("--name", cfg.name)->group("");
  app.add_option("--url", cfg.url)->group("");
  app.add_option("--pub-cpu", cfg.pub_cpu)->group("");
  app.add_option("--sub-cpu", cfg.sub_cpu)->group("");
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
