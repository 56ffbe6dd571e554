#include "common.hpp"

#include <fcntl.h>
#include <sched.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>

#include <algorithm>
#include <cctype>
#include <cstdio>

#include <poll.h>
#include <sched.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <cstring>
#include <ctime>
#include <sstream>
#include <stdexcept>

namespace lcmxbench {

std::size_t parse_size(const std::string& text, std::size_t min_bytes) {
  std::size_t pos = 0;
  double v = 0;
  try {
    v = std::stod(text, &pos);
  } catch (const std::exception&) {
    throw std::invalid_argument("bad size '" + text + "'");
  }
  std::string unit = text.substr(pos);
  for (auto& c : unit) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  double mul = 1;
  if (unit == "K" || unit == "KB") mul = 1024;
  else if (unit == "M" || unit == "MB") mul = 1024.0 * 1024;
  else if (!unit.empty() && unit != "B") throw std::invalid_argument("bad size '" + text + "'");
  const auto bytes = static_cast<std::size_t>(v * mul);
  if (v < 0 || bytes < min_bytes || bytes > (64u << 20))
    throw std::invalid_argument("size '" + text + "' out of " + std::to_string(min_bytes) + " B..64 MB");
  return bytes;
}

void LineReader::pump() {
  char tmp[65536];
  const ssize_t n = ::read(fd, tmp, sizeof tmp);
  if (n < 0 && (errno == EINTR || errno == EAGAIN)) return;
  if (n <= 0) {
    eof = true;
    return;
  }
  buf.append(tmp, static_cast<std::size_t>(n));
  std::size_t start = 0;
  for (auto pos = buf.find('\n'); pos != std::string::npos; pos = buf.find('\n', start)) {
    lines.push_back(buf.substr(start, pos - start));
    start = pos + 1;
  }
  buf.erase(0, start);
}

bool LineReader::has(const std::string& prefix) const {
  return std::any_of(lines.begin(), lines.end(), [&](const std::string& l) { return l.rfind(prefix, 0) == 0; });
}

bool pump_until(const std::vector<LineReader*>& readers, std::int64_t deadline,
                const std::function<bool()>& until, const std::atomic<int>& stop) {
  std::vector<pollfd> p;
  for (;;) {
    if (stop.load() != 0) return false;
    if (until()) return true;
    p.clear();
    for (auto* r : readers)
      if (!r->eof) p.push_back({r->fd, POLLIN, 0});
    if (p.empty()) return true;
    const std::int64_t left = deadline - now_ns();
    if (left <= 0) return false;
    if (::poll(p.data(), p.size(), static_cast<int>(std::min<std::int64_t>(left / 1'000'000 + 1, 100))) <= 0)
      continue;
    for (auto* r : readers)
      for (const auto& q : p)
        if (q.fd == r->fd && q.revents) r->pump();
  }
}

int reap_child(pid_t pid, int timeout_ms, const std::atomic<int>& stop, bool* killed) {
  int status = 0;
  const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(timeout_ms) * 1'000'000;
  if (killed) *killed = false;
  for (;;) {
    const pid_t r = ::waitpid(pid, &status, WNOHANG);
    if (r == pid || (r < 0 && errno != EINTR)) return status;
    if (now_ns() > deadline || stop.load() != 0) {
      ::kill(pid, SIGKILL);
      if (killed) *killed = true;
      while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {}
      return status;
    }
    pollfd none{-1, 0, 0};
    ::poll(&none, 0, 5);  // children of ours exit within ms after "done"
  }
}

std::vector<std::string> taskset(int cpu, std::vector<std::string> argv) {
  if (cpu < 0) return argv;
  argv.insert(argv.begin(), {"taskset", "-c", std::to_string(cpu)});
  return argv;
}

std::string self_exe() {
  char buf[4096];
  const ssize_t n = ::readlink("/proc/self/exe", buf, sizeof buf - 1);
  if (n <= 0) return "/proc/self/exe";
  buf[n] = 0;
  return buf;
}

Pipe::Pipe() {
  int fds[2];
  if (::pipe2(fds, O_CLOEXEC) != 0) throw std::runtime_error(std::string("pipe: ") + std::strerror(errno));
  r = fds[0];
  w = fds[1];
}
void Pipe::close_r() {
  if (r >= 0) ::close(r);
  r = -1;
}
void Pipe::close_w() {
  if (w >= 0) ::close(w);
  w = -1;
}

pid_t spawn_child(const std::vector<std::string>& argv, const std::vector<int>& fds, int cpu, int netns_fd) {
  std::vector<char*> cargv;
  for (const auto& a : argv) cargv.push_back(const_cast<char*>(a.c_str()));
  cargv.push_back(nullptr);
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid < 0) throw std::runtime_error(std::string("fork: ") + std::strerror(errno));
  if (pid == 0) {
    // child: async-signal-safe calls only until exec
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (::getppid() != parent) ::_exit(127);
    for (int s : {SIGINT, SIGTERM, SIGHUP, SIGPIPE}) ::signal(s, SIG_DFL);
    if (netns_fd >= 0 && ::setns(netns_fd, CLONE_NEWNET) != 0) ::_exit(125);
    if (cpu >= 0) {
      cpu_set_t set;
      CPU_ZERO(&set);
      CPU_SET(cpu, &set);
      if (::sched_setaffinity(0, sizeof set, &set) != 0) ::_exit(126);
    }
    int high[8];
    for (std::size_t i = 0; i < fds.size() && i < 8; ++i)
      high[i] = fds[i] >= 0 ? ::fcntl(fds[i], F_DUPFD_CLOEXEC, 100) : -1;
    for (std::size_t i = 0; i < fds.size() && i < 8; ++i)
      if (high[i] >= 0 && ::dup2(high[i], 3 + static_cast<int>(i)) < 0) ::_exit(125);  // dup2 clears CLOEXEC
    ::execvp(cargv[0], cargv.data());
    ::_exit(127);
  }
  return pid;
}


std::int64_t now_ns() {
  timespec ts{};
  ::clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
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

std::string size_label(std::size_t bytes) {
  if (bytes >= (1u << 20) && bytes % (1u << 20) == 0) return std::to_string(bytes >> 20) + " MB";
  if (bytes >= 1024 && bytes % 1024 == 0) return std::to_string(bytes >> 10) + " KB";
  return std::to_string(bytes) + " B";
}

std::size_t max_size(const std::vector<SizePlan>& plan) {
  std::size_t m = 0;
  for (const auto& p : plan) m = std::max(m, p.size);
  return m;
}

std::string fmt_us(double us) {
  char b[32];
  std::snprintf(b, sizeof b, us < 100 ? "%.1f" : "%.0f", us);
  return b;
}

void report_line(const std::string& line) {
  std::string l = line + '\n';
  const char* p = l.data();
  std::size_t left = l.size();
  while (left > 0) {
    const ssize_t n = ::write(kReportFd, p, left);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return;  // parent gone: nothing to report to
    p += n;
    left -= static_cast<std::size_t>(n);
  }
}

void report_error(const std::string& text) {
  std::string t = text;
  for (auto& c : t)
    if (c == '\n') c = ' ';
  report_line("error " + t);
}

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

bool wait_ack(int fd, std::int64_t seq, int timeout_ms) {
  const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(timeout_ms) * 1'000'000;
  for (;;) {
    const std::int64_t left_ns = deadline - now_ns();
    if (left_ns <= 0) return false;
    pollfd p{fd, POLLIN, 0};
    const int r = ::poll(&p, 1, static_cast<int>((left_ns + 999'999) / 1'000'000));
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) return false;
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
    const std::int64_t left_ns = deadline - now_ns();
    if (left_ns <= 0) return false;
    pollfd p{fd, POLLIN, 0};
    const int r = ::poll(&p, 1, static_cast<int>((left_ns + 999'999) / 1'000'000));
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) return false;
    char c = 0;
    const ssize_t n = ::read(fd, &c, 1);
    if (n < 0 && errno == EINTR) continue;
    return true;  // 'E' or EOF (publisher gone): either way the run is over
  }
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
      report_error("no warmup message was received at " + size_label(p.size) + " (" +
                   std::to_string(p.warmup) + " sent, each waited " +
                   std::to_string(cfg.timeout_ms) + " ms)");
      return false;
    }
    first = false;
    int timeouts = 0;
    for (int i = 0; i < p.messages; ++i) {
      const std::int64_t seq = make_seq(++k, true);
      d.send(seq, p.size);
      if (!d.wait_ack(seq, cfg.timeout_ms)) ++timeouts;
    }
    report_line("sent " + std::to_string(p.size) + ' ' + std::to_string(p.messages) + ' ' +
                std::to_string(timeouts));
  }
  return true;
}

}  // namespace lcmxbench
