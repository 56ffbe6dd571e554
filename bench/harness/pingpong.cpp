#include "pingpong.hpp"

#include <poll.h>
#include <sched.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <memory>
#include <sstream>
#include <stdexcept>

#include "options.hpp"
#include "report.hpp"

namespace lcmxbench {

// ---- the plan ----

std::vector<SizePlan> make_plan(const std::vector<std::string>& sizes, const PlanDefaults& d, int messages,
                                int warmup) {
  std::vector<SizePlan> plan;
  for (const auto& s : sizes) {
    SizePlan p;
    p.size = parse_size(s, 16);
    const int cls = p.size <= 100 * 1024 ? 0 : p.size <= 2 * 1024 * 1024 ? 1 : 2;
    p.warmup = warmup >= 0 ? warmup : d.warmup[cls];
    p.messages = messages > 0 ? messages : d.messages[cls];
    plan.push_back(p);
  }
  return plan;
}

std::string plan_to_string(const std::vector<SizePlan>& plan) {
  std::string s;
  for (const auto& p : plan) {
    if (!s.empty()) s += ',';
    s += std::to_string(p.size) + ':' + std::to_string(p.warmup) + ':' + std::to_string(p.messages);
  }
  return s;
}

std::vector<SizePlan> plan_from_string(const std::string& text) {
  std::vector<SizePlan> plan;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) {
    SizePlan p;
    char c1 = 0, c2 = 0;
    std::stringstream is(item);
    if (!(is >> p.size >> c1 >> p.warmup >> c2 >> p.messages) || c1 != ':' || c2 != ':' ||
        p.size < 16 || p.warmup < 0 || p.messages < 1)
      throw std::invalid_argument("bad plan item '" + item + "'");
    plan.push_back(p);
  }
  if (plan.empty()) throw std::invalid_argument("empty plan");
  return plan;
}

std::size_t max_size(const std::vector<SizePlan>& plan) {
  std::size_t m = 0;
  for (const auto& p : plan) m = std::max(m, p.size);
  return m;
}

std::string plan_text(const std::vector<SizePlan>& plan) {
  std::string s;
  for (const auto& p : plan)
    s += (s.empty() ? "" : ", ") + size_label(p.size) + " " + std::to_string(p.warmup) + "+" + std::to_string(p.messages);
  return s;
}

// ---- the children's side ----

bool pin_thread(int cpu) {
  if (cpu < 0) return true;
  cpu_set_t set;
  CPU_ZERO(&set);
  CPU_SET(cpu, &set);
  return ::sched_setaffinity(0, sizeof set, &set) == 0;
}

Recorder::Recorder(const std::vector<SizePlan>& plan) : plan_(plan), lat_(plan.size()) {
  for (std::size_t i = 0; i < plan.size(); ++i)
    lat_[i].reserve(static_cast<std::size_t>(plan[i].messages) + 16);
}

void Recorder::record(std::size_t size, std::int64_t seq, std::int64_t latency_ns) noexcept {
  if (!seq_measured(seq)) return;
  for (std::size_t i = 0; i < plan_.size(); ++i) {
    if (plan_[i].size != size) continue;
    if (lat_[i].size() < lat_[i].capacity()) lat_[i].push_back(latency_ns);  // never allocates
    return;
  }
}

void Recorder::report() const {
  for (std::size_t i = 0; i < plan_.size(); ++i) {
    std::string line = "lat " + std::to_string(plan_[i].size) + ' ' + std::to_string(lat_[i].size());
    for (auto v : lat_[i]) line += ' ' + std::to_string(v);
    report_line(line);
  }
}

void send_ack(int fd, std::int64_t seq) noexcept {
  // 8 bytes <= PIPE_BUF: one atomic write; a full pipe cannot happen in ping-pong.
  ssize_t n;
  do n = ::write(fd, &seq, sizeof seq);
  while (n < 0 && errno == EINTR);
}

namespace {

// Waits until `fd` is readable or CLOCK_MONOTONIC passes `deadline` (ns): true if readable.
bool readable_before(int fd, std::int64_t deadline) {
  for (;;) {
    const std::int64_t left_ns = deadline - now_ns();
    if (left_ns <= 0) return false;
    pollfd p{fd, POLLIN, 0};
    const int r = ::poll(&p, 1, static_cast<int>((left_ns + 999'999) / 1'000'000));
    if (r < 0 && errno == EINTR) continue;
    return r > 0;
  }
}

}  // namespace

bool wait_ack(int fd, std::int64_t seq, int timeout_ms) {
  const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(timeout_ms) * 1'000'000;
  for (;;) {
    if (!readable_before(fd, deadline)) return false;
    std::int64_t got = 0;
    const ssize_t n = ::read(fd, &got, sizeof got);
    if (n < 0 && errno == EINTR) continue;
    if (n != static_cast<ssize_t>(sizeof got)) return false;  // EOF: subscriber gone
    if (got == seq) return true;
    // older ack of a message that was already counted lost, or a matched record: skip
  }
}

bool wait_end(int fd, int timeout_ms) {
  const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(timeout_ms) * 1'000'000;
  for (;;) {
    if (!readable_before(fd, deadline)) return false;
    char c = 0;
    const ssize_t n = ::read(fd, &c, 1);
    if (n < 0 && errno == EINTR) continue;
    return true;  // 'E' or EOF (publisher gone): either way the run is over
  }
}

void send_end() {
  const char e = 'E';
  (void)!::write(kCtlFd, &e, 1);
}

bool run_driver(const RoleConfig& cfg, const Driver& d) {
  std::int64_t k = 0;
  bool first = true;
  for (const auto& p : cfg.plan) {
    d.prepare(p.size);
    int warm_acked = 0;
    for (int i = 0; i < p.warmup; ++i) {
      const std::int64_t seq = make_seq(++k, false);
      d.send(seq, p.size);
      if (d.wait_ack(seq, cfg.timeout_ms)) ++warm_acked;
    }
    if (first && p.warmup > 0 && warm_acked == 0) {
      report_error("no warmup message was received at " + size_label(p.size) + " (" + std::to_string(p.warmup) +
                   " sent, each waited " + std::to_string(cfg.timeout_ms) + " ms)");
      return false;
    }
    first = false;
    int timeouts = 0;
    for (int i = 0; i < p.messages; ++i) {
      const std::int64_t seq = make_seq(++k, true);
      d.send(seq, p.size);
      if (!d.wait_ack(seq, cfg.timeout_ms)) ++timeouts;
    }
    report_line("sent " + std::to_string(p.size) + ' ' + std::to_string(p.messages) + ' ' + std::to_string(timeouts));
  }
  return true;
}

// ---- the orchestrator's side ----

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
      for (std::int64_t x; v.size() < n && in >> x;) v.push_back(x);
      r.sizes[size].lat = std::move(v);
    }
  }
}

void merge(MethodResult& into, MethodResult&& more) {
  for (auto& e : more.errors) into.errors.push_back(std::move(e));
  for (auto& n : more.notes)
    if (std::find(into.notes.begin(), into.notes.end(), n) == into.notes.end()) into.notes.push_back(std::move(n));
  for (auto& [size, r] : more.sizes) {
    auto& t = into.sizes[size];
    if (r.sent) t.sent = t.sent.value_or(0) + *r.sent;
    t.ack_timeouts += r.ack_timeouts;
    if (r.lat) {
      if (!t.lat) t.lat.emplace();
      t.lat->insert(t.lat->end(), r.lat->begin(), r.lat->end());
    }
  }
}

Cell cell_of(const MethodResult& m, std::size_t size) {
  Cell c;
  const auto it = m.sizes.find(size);
  if (it == m.sizes.end() || !it->second.sent || !it->second.lat) return c;
  c.ok = true;
  c.sent = *it->second.sent;
  c.st = stats_of_ns(*it->second.lat);
  c.lost = std::max(0, c.sent - static_cast<int>(c.st.n));
  return c;
}

std::string cell_text(const MethodResult& m, std::size_t size, bool always_lost) {
  const Cell c = cell_of(m, size);
  if (!c.ok) return m.failed() ? "failed" : "—";
  std::string s = c.st.n ? fmt_us(c.st.p50) + " / " + fmt_us(c.st.p99) : "—";
  if (c.lost || always_lost) s += " (lost " + std::to_string(c.lost) + "/" + std::to_string(c.sent) + ")";
  return s;
}

PairOutcome run_pair(const Pair& pair) {
  PairOutcome out;
  MethodResult& res = out.result;
  res.method = pair.method;
  const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(pair.deadline_ms) * 1'000'000;
  std::vector<pid_t> pids;
  std::vector<std::unique_ptr<LineReader>> readers;
  auto reader_of = [&](Pipe& p) {
    auto r = std::make_unique<LineReader>();
    r->fd = std::exchange(p.r, -1);
    readers.push_back(std::move(r));
    return readers.back().get();
  };
  bool timed_out = false;
  try {
    if (pair.pub_argv.empty()) {
      Pipe rep;
      pids.push_back(spawn_child(pair.sub_argv, {rep.w}, pair.sub_cpu, pair.sub_netns));
      rep.close_w();
      reader_of(rep);
    } else {
      Pipe rep_sub, rep_pub, ack, ctl;
      pids.push_back(spawn_child(pair.sub_argv, {rep_sub.w, ack.w, ctl.r}, pair.sub_cpu, pair.sub_netns));
      rep_sub.close_w();
      ack.close_w();
      ctl.close_r();
      LineReader* sub = reader_of(rep_sub);
      // Never sleep to synchronise: wait for the subscriber's "ready" line (or its failure).
      const std::int64_t ready_deadline = std::min(deadline, now_ns() + 20'000'000'000);
      auto answered = [&] { return sub->has("ready") || sub->has("error"); };
      if (!pump_until({sub}, ready_deadline, answered) || !answered())
        throw std::runtime_error(stopped()  ? "interrupted"
                                 : sub->eof ? "subscriber exited before it was ready"
                                            : "subscriber not ready within 20 s");
      if (sub->has("ready"))
        pids.push_back(spawn_child(pair.pub_argv, {rep_pub.w, ack.r, ctl.w}, pair.pub_cpu, pair.pub_netns));
      // else it reported an error instead; collected below
      rep_pub.close_w();
      ack.close_r();
      ctl.close_w();
      reader_of(rep_pub);
    }
    std::vector<LineReader*> rs;
    for (auto& r : readers) rs.push_back(r.get());
    timed_out = !pump_until(rs, deadline, [] { return false; });
  } catch (const std::exception& e) {
    res.errors.push_back(e.what());
  }
  const bool interrupted = stopped();
  for (auto p : pids) {
    const int st = reap_child(p, timed_out || interrupted ? 0 : 5000);
    if (WIFSIGNALED(st)) {
      out.killed = true;
      if (!timed_out && !interrupted) res.errors.push_back("a child died of signal " + std::to_string(WTERMSIG(st)));
    } else if (WIFEXITED(st) && WEXITSTATUS(st) == kExitPinFailed) {
      res.errors.push_back("could not pin a child (sched_setaffinity)");
    } else if (WIFEXITED(st) && WEXITSTATUS(st) >= kExitSetupFailed) {
      res.errors.push_back("a child could not start (exit " + std::to_string(WEXITSTATUS(st)) + ")");
    }
  }
  for (auto& r : readers) {
    for (const auto& l : r->lines) parse_line(res, l);
    ::close(r->fd);
  }
  if (timed_out && !interrupted) {
    res.errors.push_back("timed out after " + std::to_string(pair.deadline_ms / 1000) + " s; children killed");
    out.killed = true;
  }
  return out;
}

void progress_of(const std::string& tag, const MethodResult& r, const std::vector<SizePlan>& plan) {
  for (const auto& p : plan) {
    const Cell c = cell_of(r, p.size);
    if (!c.ok) continue;
    char buf[256];
    std::snprintf(buf, sizeof buf, "%s %s: p50 %.1f us, p99 %.1f us, mean %.1f us, received %zu/%d", r.method.c_str(),
                  size_label(p.size).c_str(), c.st.p50, c.st.p99, c.st.mean, c.st.n, c.sent);
    progress(tag, buf);
  }
  for (const auto& e : r.errors) progress(tag, r.method + ": FAILED: " + e);
  for (const auto& n : r.notes) progress(tag, r.method + ": " + n);
}

}  // namespace lcmxbench
