#include "process.hpp"

#include <fcntl.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <ctime>
#include <stdexcept>

namespace lcmxbench {
namespace {

std::atomic<int> g_stop{0};
std::atomic<bool> g_kill_children{false};

// Children spawn_child() started and reap_child() has not reaped (0: a free entry); read by the
// signal handler, so a fixed array of atomics.
constexpr int kMaxTracked = 64;
std::atomic<pid_t> g_children[kMaxTracked];

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

void on_signal(int sig) {
  g_stop.store(sig);
  if (!g_kill_children.load()) return;
  for (auto& c : g_children) {
    const pid_t p = c.load();
    if (p > 0) ::kill(p, SIGKILL);
  }
}

}  // namespace

std::int64_t now_ns() {
  timespec ts{};
  ::clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

void on_stop_signals(OnStop what) {
  g_kill_children.store(what == OnStop::kill_children);
  struct sigaction sa{};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sa.sa_flags = 0;  // no SA_RESTART
  for (int s : {SIGINT, SIGTERM, SIGHUP}) ::sigaction(s, &sa, nullptr);
  ::signal(SIGPIPE, SIG_IGN);
}

const std::atomic<int>& stop_flag() { return g_stop; }

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
    if (::getppid() != parent) ::_exit(kExitExecFailed);
    for (int s : {SIGINT, SIGTERM, SIGHUP, SIGPIPE}) ::signal(s, SIG_DFL);
    if (netns_fd >= 0 && ::setns(netns_fd, CLONE_NEWNET) != 0) ::_exit(kExitSetupFailed);
    if (cpu >= 0) {
      cpu_set_t set;
      CPU_ZERO(&set);
      CPU_SET(cpu, &set);
      if (::sched_setaffinity(0, sizeof set, &set) != 0) ::_exit(kExitPinFailed);
    }
    int high[8];
    for (std::size_t i = 0; i < fds.size() && i < 8; ++i)
      high[i] = fds[i] >= 0 ? ::fcntl(fds[i], F_DUPFD_CLOEXEC, 100) : -1;
    for (std::size_t i = 0; i < fds.size() && i < 8; ++i)
      if (high[i] >= 0 && ::dup2(high[i], 3 + static_cast<int>(i)) < 0) ::_exit(kExitSetupFailed);  // dup2 clears CLOEXEC
    ::execvp(cargv[0], cargv.data());
    ::_exit(kExitExecFailed);
  }
  track(pid);
  return pid;
}

int reap_child(pid_t pid, int timeout_ms, const std::atomic<int>& stop, bool* killed) {
  int status = 0;
  const std::int64_t deadline = now_ns() + static_cast<std::int64_t>(timeout_ms) * 1'000'000;
  if (killed) *killed = false;
  for (;;) {
    const pid_t r = ::waitpid(pid, &status, WNOHANG);
    if (r == pid || (r < 0 && errno != EINTR)) break;
    if (now_ns() > deadline || stop.load() != 0) {
      ::kill(pid, SIGKILL);
      if (killed) *killed = true;
      while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {}
      break;
    }
    pollfd none{-1, 0, 0};
    ::poll(&none, 0, 5);  // children of ours exit within ms after "done"
  }
  untrack(pid);
  return status;
}

bool run_command(const std::vector<std::string>& argv) {
  const pid_t pid = spawn_child(argv, {}, -1);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {}
  untrack(pid);
  return WIFEXITED(status) && WEXITSTATUS(status) == 0;
}

std::string exit_failure(int st) {
  if (WIFEXITED(st) && WEXITSTATUS(st) >= kExitSetupFailed)
    return "could not start (exit " + std::to_string(WEXITSTATUS(st)) + ")";
  if (WIFEXITED(st) && WEXITSTATUS(st) != 0) return "exited with " + std::to_string(WEXITSTATUS(st));
  if (WIFSIGNALED(st)) return "died of signal " + std::to_string(WTERMSIG(st));
  return "";
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

RoleProcess::RoleProcess(std::string name, const std::vector<std::string>& argv, int cpu, int netns_fd)
    : name_(std::move(name)) {
  Pipe rep, cmd;
  pid_ = spawn_child(argv, {rep.w, cmd.r}, cpu, netns_fd);  // fd 3 = kReportFd, fd 4 = kCmdFd
  out_.fd = std::exchange(rep.r, -1);
  cmd_ = std::exchange(cmd.w, -1);
}

RoleProcess::~RoleProcess() {
  close_commands();
  if (out_.fd >= 0) ::close(out_.fd);
  if (pid_ > 0 && !reaped_) reap_child(pid_, 0);
}

bool RoleProcess::command(const std::string& line) {
  if (cmd_ < 0) return false;
  const std::string l = line + '\n';
  ssize_t n;
  do n = ::write(cmd_, l.data(), l.size());
  while (n < 0 && errno == EINTR);
  return n == static_cast<ssize_t>(l.size());
}

void RoleProcess::close_commands() {
  if (cmd_ >= 0) ::close(cmd_);
  cmd_ = -1;
}

std::string RoleProcess::reap(int timeout_ms) {
  if (pid_ <= 0 || reaped_) return "";
  bool killed = false;
  const int st = reap_child(pid_, timeout_ms, stop_flag(), &killed);
  reaped_ = true;
  if (killed) return name_ + " did not exit within " + std::to_string(timeout_ms) + " ms (killed)";
  const std::string why = exit_failure(st);
  return why.empty() ? why : name_ + " " + why;
}

std::vector<std::string> taskset(int cpu, std::vector<std::string> argv) {
  if (cpu < 0) return argv;
  argv.insert(argv.begin(), {"taskset", "-c", std::to_string(cpu)});
  return argv;
}

void report_line(const std::string& line) {
  std::string l = line + '\n';
  const char* p = l.data();
  std::size_t left = l.size();
  while (left > 0) {
    const ssize_t n = ::write(kReportFd, p, left);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return;  // orchestrator gone: nothing to report to
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

std::optional<std::string> CommandReader::next(int timeout_ms) {
  for (;;) {
    if (const auto pos = buf_.find('\n'); pos != std::string::npos) {
      std::string line = buf_.substr(0, pos);
      buf_.erase(0, pos + 1);
      return line;
    }
    if (eof_) return std::string("quit");
    pollfd p{kCmdFd, POLLIN, 0};
    const int r = ::poll(&p, 1, timeout_ms);
    if (r < 0 && errno == EINTR) continue;
    if (r == 0) return std::nullopt;
    char tmp[4096];
    const ssize_t n = ::read(kCmdFd, tmp, sizeof tmp);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) eof_ = true;
    else buf_.append(tmp, static_cast<std::size_t>(n));
  }
}

void log_to_stderr(const std::string& role, const std::string& level) {
  spdlog::set_default_logger(spdlog::stderr_color_mt(role));
  if (!level.empty()) spdlog::set_level(spdlog::level::from_str(level));
}

}  // namespace lcmxbench
