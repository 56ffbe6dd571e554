// Child processes for tests and benches: stdout captured line by line, killed and reaped on
// destruction. Used by lcmx::test::Emulation::spawn (child inside a host's network namespace)
// and by lcmx::test::spawn (child in the caller's namespaces).
#pragma once

#include <sys/types.h>

#include <chrono>
#include <csignal>
#include <optional>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace lcmx::test {

// A setup step failed: the message names the command (or system call) and carries its stderr.
class SetupError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

using Env = std::vector<std::pair<std::string, std::string>>;

// A running child process in its own process group. Move-only.
// Its stdout is a pipe read by read_line(); stderr and stdin are inherited / /dev/null.
// The child gets SIGKILL when the *thread* that spawned it exits (PR_SET_PDEATHSIG), so spawn
// from a long-lived thread. Not thread-safe: one thread uses a Child at a time.
class Child {
 public:
  using Clock = std::chrono::steady_clock;

  Child(Child&& other) noexcept;
  Child& operator=(Child&& other) noexcept;
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;
  // Stops the child if it still runs: SIGTERM (and SIGCONT) to its process group, SIGKILL if
  // it has not exited within kStopGrace; then reaps it.
  ~Child();
  static constexpr std::chrono::milliseconds kStopGrace{1000};

  pid_t pid() const { return pid_; }

  // Next line of stdout without its '\n'; nullopt at the deadline or at EOF (see eof()).
  std::optional<std::string> read_line(Clock::time_point deadline);
  std::optional<std::string> read_line(std::chrono::milliseconds timeout) {
    return read_line(Clock::now() + timeout);
  }
  // Reads lines until one starts with `prefix` and returns it; nullopt at the deadline or EOF.
  std::optional<std::string> expect(const std::string& prefix, std::chrono::milliseconds timeout);
  // True once stdout reached end of file.
  bool eof() const { return eof_; }

  // Sends `sig` to the child's whole process group (no-op once reaped).
  void kill(int sig = SIGKILL);
  // Waits until the child exits: returns its exit code, or 128 + signal number if a signal
  // killed it; nullopt if it is still running at the deadline.
  std::optional<int> wait(std::chrono::milliseconds timeout);

 private:
  friend Child spawn_child(const std::vector<std::string>& argv, const Env& env, int netns_fd,
                           const std::string& netns_name);
  Child(pid_t pid, int pidfd, int out) : pid_(pid), pidfd_(pidfd), out_(out) {}
  void release() noexcept;

  pid_t pid_ = -1;
  int pidfd_ = -1;
  int out_ = -1;
  bool eof_ = false;
  std::optional<int> status_;
  std::string buf_;
};

// Starts argv (argv[0] is searched in PATH when it has no '/') in the caller's namespaces, with
// `env` added to (or overriding) the current environment. Throws SetupError if it cannot start
// (including exec failure, e.g. no such program).
Child spawn(std::vector<std::string> argv, Env env = {});

// Internal: starts a child; if netns_fd >= 0 the child first joins that network namespace and
// gets a private mount namespace with /sys remounted for it (like `ip netns exec`).
Child spawn_child(const std::vector<std::string>& argv, const Env& env, int netns_fd,
                  const std::string& netns_name);

}  // namespace lcmx::test
