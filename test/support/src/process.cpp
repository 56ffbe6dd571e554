#include "lcmx/test/process.hpp"

#include <fcntl.h>
#include <poll.h>
#include <sched.h>
#include <sys/mount.h>
#include <sys/prctl.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdlib>
#include <cstring>

#include "registry.hpp"

extern char** environ;

namespace lcmx::test {
namespace {

std::string find_in_path(const std::string& prog) {
  if (prog.find('/') != std::string::npos) return prog;
  const char* path = std::getenv("PATH");
  std::string p = path != nullptr ? path : "/usr/local/bin:/usr/bin:/bin";
  std::size_t start = 0;
  for (int guard = 0; guard < 1000 && start <= p.size(); ++guard) {
    const auto end = std::min(p.find(':', start), p.size());
    std::string dir = p.substr(start, end - start);
    if (dir.empty()) dir = ".";
    const std::string cand = dir + "/" + prog;
    if (::access(cand.c_str(), X_OK) == 0) return cand;
    start = end + 1;
  }
  throw SetupError("spawn: '" + prog + "' not found in PATH");
}

// What the forked child reports through the error pipe before _exit(127).
struct ChildFailure {
  int stage;
  int err;
};
constexpr const char* kStages[] = {"setns(CLONE_NEWNET)", "unshare(CLONE_NEWNS)",
                                   "mount --make-rslave /", "mount sysfs on /sys", "dup2",
                                   "execve"};

[[noreturn]] void child_fail(int fd, int stage) {
  const ChildFailure f{stage, errno};
  [[maybe_unused]] auto n = ::write(fd, &f, sizeof f);
  ::_exit(127);
}

}  // namespace

Child spawn_child(const std::vector<std::string>& argv, const Env& env, int netns_fd,
                  const std::string& netns_name) {
  if (argv.empty()) throw SetupError("spawn: empty argv");
  // Everything the child needs is prepared before fork: after fork only system calls.
  const std::string exe = find_in_path(argv[0]);
  std::vector<char*> cargv;
  for (const auto& a : argv) cargv.push_back(const_cast<char*>(a.c_str()));
  cargv.push_back(nullptr);
  std::vector<std::string> envs;
  for (char** e = environ; e != nullptr && *e != nullptr; ++e) {
    const std::string kv = *e;
    const auto key = kv.substr(0, kv.find('='));
    if (std::none_of(env.begin(), env.end(), [&](const auto& p) { return p.first == key; }))
      envs.push_back(kv);
  }
  for (const auto& [k, v] : env) envs.push_back(k + "=" + v);
  std::vector<char*> cenv;
  for (auto& e : envs) cenv.push_back(e.data());
  cenv.push_back(nullptr);

  int out[2];
  int err[2];
  if (::pipe2(out, O_CLOEXEC) != 0) throw SetupError(std::string("spawn: pipe: ") + std::strerror(errno));
  if (::pipe2(err, O_CLOEXEC) != 0) {
    const int e = errno;
    ::close(out[0]);
    ::close(out[1]);
    throw SetupError(std::string("spawn: pipe: ") + std::strerror(e));
  }
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid < 0) {
    const int e = errno;
    for (int fd : {out[0], out[1], err[0], err[1]}) ::close(fd);
    throw SetupError(std::string("spawn: fork: ") + std::strerror(e));
  }
  if (pid == 0) {
    ::setpgid(0, 0);
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (::getppid() != parent) ::_exit(127);
    sigset_t all;
    sigemptyset(&all);
    ::sigprocmask(SIG_SETMASK, &all, nullptr);
    if (netns_fd >= 0) {
      if (::setns(netns_fd, CLONE_NEWNET) != 0) child_fail(err[1], 0);
      // Like `ip netns exec`: a private mount namespace where /sys shows the new namespace.
      if (::unshare(CLONE_NEWNS) != 0) child_fail(err[1], 1);
      if (::mount("", "/", nullptr, MS_SLAVE | MS_REC, nullptr) != 0) child_fail(err[1], 2);
      ::umount2("/sys", MNT_DETACH);
      if (::mount(netns_name.c_str(), "/sys", "sysfs", 0, nullptr) != 0) child_fail(err[1], 3);
    }
    const int devnull = ::open("/dev/null", O_RDONLY);
    if (devnull < 0 || ::dup2(devnull, 0) < 0 || ::dup2(out[1], 1) < 0) child_fail(err[1], 4);
    ::execve(exe.c_str(), cargv.data(), cenv.data());
    child_fail(err[1], 5);
  }
  ::setpgid(pid, pid);  // also from here, so kill(-pid) works at once (may fail after exec: fine)
  detail::register_child(pid);
  ::close(out[1]);
  ::close(err[1]);
  ChildFailure f{};
  ssize_t n = -1;
  for (int guard = 0; guard < 100; ++guard) {
    n = ::read(err[0], &f, sizeof f);
    if (n >= 0 || errno != EINTR) break;
  }
  ::close(err[0]);
  if (n == static_cast<ssize_t>(sizeof f)) {
    ::close(out[0]);
    int status = 0;
    ::waitpid(pid, &status, 0);
    detail::unregister_child(pid);
    const int stage = f.stage >= 0 && f.stage < 6 ? f.stage : 5;
    throw SetupError("spawn " + exe + (netns_fd >= 0 ? " in netns " + netns_name : std::string()) +
                     ": " + kStages[stage] + ": " + std::strerror(f.err));
  }
  const int pidfd = static_cast<int>(::syscall(SYS_pidfd_open, pid, 0));
  return Child(pid, pidfd, out[0]);
}

Child spawn(std::vector<std::string> argv, Env env) { return spawn_child(argv, env, -1, {}); }

Child::Child(Child&& o) noexcept
    : pid_(std::exchange(o.pid_, -1)),
      pidfd_(std::exchange(o.pidfd_, -1)),
      out_(std::exchange(o.out_, -1)),
      eof_(o.eof_),
      status_(o.status_),
      buf_(std::move(o.buf_)) {}

Child& Child::operator=(Child&& o) noexcept {
  if (this != &o) {
    release();
    pid_ = std::exchange(o.pid_, -1);
    pidfd_ = std::exchange(o.pidfd_, -1);
    out_ = std::exchange(o.out_, -1);
    eof_ = o.eof_;
    status_ = o.status_;
    buf_ = std::move(o.buf_);
  }
  return *this;
}

Child::~Child() { release(); }

void Child::release() noexcept {
  if (pid_ > 0 && !status_) {
    // A clean stop first, so that the child removes what it made (registry slot, state file,
    // shared memory) as a program stopped by its user does; SIGCONT wakes a stopped one to
    // take it. SIGKILL after the grace (a child that ignores SIGTERM or hangs).
    kill(SIGTERM);
    kill(SIGCONT);
    if (!wait(kStopGrace)) {
      ::kill(-pid_, SIGKILL);
      ::kill(pid_, SIGKILL);
      int st = 0;
      for (int guard = 0; guard < 100; ++guard)
        if (::waitpid(pid_, &st, 0) >= 0 || errno != EINTR) break;
    }
  }
  if (pid_ > 0) detail::unregister_child(pid_);
  if (pidfd_ >= 0) ::close(pidfd_);
  if (out_ >= 0) ::close(out_);
  pid_ = pidfd_ = out_ = -1;
}

std::optional<std::string> Child::read_line(Clock::time_point deadline) {
  for (int guard = 0; guard < 1000000; ++guard) {
    if (const auto nl = buf_.find('\n'); nl != std::string::npos) {
      std::string line = buf_.substr(0, nl);
      buf_.erase(0, nl + 1);
      return line;
    }
    if (eof_ || out_ < 0) {
      if (buf_.empty()) return std::nullopt;
      return std::exchange(buf_, {});
    }
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
    if (left < 0) return std::nullopt;
    pollfd p{out_, POLLIN, 0};
    const int r = ::poll(&p, 1, static_cast<int>(std::min<long long>(left + 1, 1 << 30)));
    if (r < 0 && errno != EINTR) return std::nullopt;
    if (r <= 0) continue;
    char tmp[4096];
    const ssize_t n = ::read(out_, tmp, sizeof tmp);
    if (n > 0)
      buf_.append(tmp, static_cast<std::size_t>(n));
    else if (n == 0 || (errno != EINTR && errno != EAGAIN))
      eof_ = true;
  }
  return std::nullopt;
}

std::optional<std::string> Child::expect(const std::string& prefix,
                                         std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  for (int guard = 0; guard < 1000000; ++guard) {
    auto line = read_line(deadline);
    if (!line) return std::nullopt;
    if (line->rfind(prefix, 0) == 0) return line;
  }
  return std::nullopt;
}

void Child::kill(int sig) {
  if (pid_ <= 0 || status_) return;
  if (::kill(-pid_, sig) != 0) ::kill(pid_, sig);
}

std::optional<int> Child::wait(std::chrono::milliseconds timeout) {
  if (status_ || pid_ <= 0) return status_;
  const auto deadline = Clock::now() + timeout;
  for (int guard = 0; guard < 100000; ++guard) {
    int st = 0;
    const pid_t r = ::waitpid(pid_, &st, WNOHANG);
    if (r == pid_) {
      status_ = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
      return status_;
    }
    if (r < 0 && errno != EINTR) return std::nullopt;
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
    if (left < 0) return std::nullopt;
    if (pidfd_ >= 0) {
      pollfd p{pidfd_, POLLIN, 0};
      ::poll(&p, 1, static_cast<int>(left + 1));
    } else {
      ::usleep(1000);  // no pidfd (old kernel): poll the exit status
    }
  }
  return std::nullopt;
}

}  // namespace lcmx::test
