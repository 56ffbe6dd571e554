// Child processes of a benchmark, and how a run stops (bench/harness; bench/README.md "The harness").
//
// Process model of every orchestrating benchmark: the orchestrator (the binary without --role)
// starts its roles as children (fork/exec of itself with a hidden --role, or another program),
// never publishes or subscribes itself, and talks to them over pipes that are not part of what
// is measured. A child writes text lines on fd 3 (kReportFd, one write() per line); roles that
// take commands read them on fd 4 (kCmdFd). Every wait is bounded; nothing sleeps to synchronise.
//
// Signals: on_stop_signals() makes SIGINT, SIGTERM and SIGHUP set the stop flag (and, if asked,
// SIGKILL every child spawn_child() started and reap_child() has not reaped yet), so the
// orchestrator's loops end, its RAII owners (namespaces, files) clean up, and it exits with
// 128 + the signal.
#pragma once

#include <sys/types.h>

#include <atomic>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

namespace lcmxbench {

// CLOCK_MONOTONIC in ns. Processes of one machine share it (network namespaces too), so a
// one-way latency is receive - send.
std::int64_t now_ns();

// ---- stopping ----

enum class OnStop {
  flag,            // set the flag only (the run stops its children itself, e.g. with SIGTERM)
  kill_children,   // also SIGKILL every live child of spawn_child() at once
};
// Installs the handlers of SIGINT, SIGTERM and SIGHUP (no SA_RESTART: blocking calls return
// EINTR and loops check the flag) and ignores SIGPIPE. Call once, in the orchestrator.
void on_stop_signals(OnStop what);
// The flag those handlers set: the signal's number, 0 while none came.
const std::atomic<int>& stop_flag();
inline bool stopped() { return stop_flag().load() != 0; }

// ---- starting and ending children ----

// This binary's path (/proc/self/exe), to start its roles.
std::string self_exe();

// A close-on-exec pipe; both ends closed on destruction.
struct Pipe {
  int r = -1, w = -1;
  Pipe();  // throws std::runtime_error
  Pipe(const Pipe&) = delete;
  Pipe& operator=(const Pipe&) = delete;
  ~Pipe() { close_r(), close_w(); }
  void close_r();
  void close_w();
};

// Exit codes of a child that could not become its program (see spawn_child).
inline constexpr int kExitSetupFailed = 125;  // setns or dup2 failed
inline constexpr int kExitPinFailed = 126;    // sched_setaffinity failed
inline constexpr int kExitExecFailed = 127;   // exec failed

// Starts argv (argv[0] searched in PATH when it has no '/') with fds[i] as fd 3 + i (-1: left
// closed; at most 8), pinned to `cpu` (-1: not pinned), inside network namespace `netns_fd`
// (-1: ours). The child gets SIGKILL if this process dies, and is remembered for
// OnStop::kill_children until reap_child() reaps it. Throws std::runtime_error if fork fails;
// failures in the child show as its exit code (kExitSetupFailed, kExitPinFailed, kExitExecFailed).
pid_t spawn_child(const std::vector<std::string>& argv, const std::vector<int>& fds, int cpu,
                  int netns_fd = -1);

// Waits for child `pid` to exit; SIGKILLs it once `timeout_ms` passed or `stop` is set.
// Returns its wait status; *killed (if given) tells whether it had to be killed.
int reap_child(pid_t pid, int timeout_ms, const std::atomic<int>& stop = stop_flag(), bool* killed = nullptr);

// Runs argv (no extra fds) to its end; true if it exited 0.
bool run_command(const std::vector<std::string>& argv);

// Why a child's wait status is a failure ("" when it exited 0): "could not start (exit 127)",
// "exited with 3", "died of signal 9".
std::string exit_failure(int status);

// ---- reading children's lines ----

// Lines a child writes to a pipe (its report fd), read without blocking: call pump() when
// poll() says `fd` is readable. Complete lines go to `lines`; `eof` once the child closed it.
struct LineReader {
  int fd = -1;
  std::string buf;
  bool eof = false;
  std::vector<std::string> lines;
  void pump();
  bool has(const std::string& prefix) const;  // a line starting with prefix arrived
};

// Polls the readers until every one is at EOF or until() holds (true), or the deadline passes
// or `stop` is set (false).
bool pump_until(const std::vector<LineReader*>& readers, std::int64_t deadline,
                const std::function<bool()>& until, const std::atomic<int>& stop = stop_flag());

// A role of this binary (or any program) started with a report pipe on fd 3 and a command pipe
// on fd 4 (kCmdFd). Killed and reaped on destruction if still running.
class RoleProcess {
 public:
  RoleProcess(std::string name, const std::vector<std::string>& argv, int cpu = -1, int netns_fd = -1);
  RoleProcess(const RoleProcess&) = delete;
  RoleProcess& operator=(const RoleProcess&) = delete;
  ~RoleProcess();

  const std::string& name() const { return name_; }
  LineReader& out() { return out_; }
  std::vector<std::string>& lines() { return out_.lines; }
  bool eof() const { return out_.eof; }
  // Writes one command line (fd 4 of the child); false if the child is gone.
  bool command(const std::string& line);
  void close_commands();  // the child reads EOF: "quit" for every role
  // Waits for the exit (killing it at the deadline). Returns a failure text or "".
  std::string reap(int timeout_ms);

 private:
  std::string name_;
  pid_t pid_ = -1;
  int cmd_ = -1;
  bool reaped_ = false;
  LineReader out_;
};

// `argv` run under `taskset -c cpu` (for starters that take an argv, e.g. Emulation::spawn);
// unchanged when cpu < 0.
std::vector<std::string> taskset(int cpu, std::vector<std::string> argv);

// ---- the child's side ----

inline constexpr int kReportFd = 3;  // child -> orchestrator: text lines
inline constexpr int kCmdFd = 4;     // orchestrator -> child: command lines (RoleProcess)

// One line on kReportFd, in one write() (a gone orchestrator is ignored).
void report_line(const std::string& line);
// "error <text>" (newlines folded into spaces).
void report_error(const std::string& text);

// Command lines a role reads from kCmdFd. next() waits up to timeout_ms (-1: forever); nullopt
// on timeout; "quit" at EOF (the orchestrator closed it, or is gone).
class CommandReader {
 public:
  std::optional<std::string> next(int timeout_ms);

 private:
  std::string buf_;
  bool eof_ = false;
};

// lcmx and the roles log through spdlog's default logger, which writes to stdout; a role's
// stdout may be its report, so its logs go to stderr with the role's name in front, from
// `level` up ("" keeps spdlog's level).
void log_to_stderr(const std::string& role, const std::string& level = "warn");

}  // namespace lcmxbench
