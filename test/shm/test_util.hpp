// Helpers for lcmx::shm tests: unique names, RAII cleanup of /dev/shm, a watchdog, fork()ed
// children with pipes, waits with deadlines (never sleep to synchronise).
#pragma once

#include <dirent.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sched.h>
#include <sys/mman.h>
#include <sys/mount.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "lcmx/shm/segment.hpp"

namespace lcmx::shm::test {

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

// "lcmx_t<pid>_<test>_<n>": unique per process and per call.
inline std::string unique_base(const std::string& test) {
  static std::atomic<int> counter{0};
  return "lcmx_t" + std::to_string(::getpid()) + "_" + test + "_" + std::to_string(counter++);
}

inline std::string test_prefix() { return "lcmx_t" + std::to_string(::getpid()) + "_"; }

inline std::vector<std::string> shm_names(const std::string& prefix) {
  std::vector<std::string> out;
  if (DIR* d = ::opendir("/dev/shm")) {
    while (const dirent* e = ::readdir(d)) {
      std::string n = e->d_name;
      if (n.compare(0, prefix.size(), prefix) == 0) out.push_back(n);
    }
    ::closedir(d);
  }
  return out;
}

inline bool shm_exists(const std::string& name) {
  return ::access(("/dev/shm/" + name).c_str(), F_OK) == 0;
}

// Removes "<base>" and "<base>_*" from /dev/shm on destruction (also on test failure).
struct ShmGuard {
  std::string base;
  explicit ShmGuard(std::string b) : base(std::move(b)) {}
  ShmGuard(const ShmGuard&) = delete;
  ShmGuard& operator=(const ShmGuard&) = delete;
  ~ShmGuard() {
    for (const auto& n : shm_names(base)) {
      if (n == base || n.compare(0, base.size() + 1, base + "_") == 0) {
        ::shm_unlink(("/" + n).c_str());
      }
    }
  }
};

// Writes raw bytes as /dev/shm/<name> (for corrupt/foreign file tests).
inline void write_shm_file(const std::string& name, const void* data, std::size_t n) {
  int fd = ::shm_open(("/" + name).c_str(), O_CREAT | O_RDWR | O_TRUNC, 0600);
  if (fd < 0) std::abort();
  if (n != 0 && ::write(fd, data, n) != static_cast<ssize_t>(n)) std::abort();
  ::close(fd);
}

inline std::vector<unsigned char> read_shm_file(const std::string& name) {
  std::vector<unsigned char> out;
  int fd = ::shm_open(("/" + name).c_str(), O_RDONLY, 0);
  if (fd < 0) return out;
  unsigned char buf[4096];
  ssize_t k;
  while ((k = ::read(fd, buf, sizeof buf)) > 0) out.insert(out.end(), buf, buf + k);
  ::close(fd);
  return out;
}

// Fails the whole run fast (kills children, removes this process's segments) if a test hangs.
class Watchdog {
 public:
  explicit Watchdog(std::chrono::milliseconds limit, std::string what = "test")
      : what_(std::move(what)), thread_([this, limit] { run(limit); }) {}
  Watchdog(const Watchdog&) = delete;
  Watchdog& operator=(const Watchdog&) = delete;
  ~Watchdog() {
    {
      std::lock_guard<std::mutex> l(m_);
      done_ = true;
    }
    cv_.notify_all();
    thread_.join();
  }
  void watch_child(pid_t pid) {
    std::lock_guard<std::mutex> l(m_);
    children_.push_back(pid);
  }

 private:
  void run(std::chrono::milliseconds limit) {
    std::unique_lock<std::mutex> l(m_);
    if (cv_.wait_for(l, limit, [this] { return done_; })) return;
    std::fprintf(stderr, "WATCHDOG: %s exceeded %lld ms, aborting\n", what_.c_str(),
                 static_cast<long long>(limit.count()));
    for (pid_t c : children_) ::kill(c, SIGKILL);
    for (const auto& n : shm_names(test_prefix())) ::shm_unlink(("/" + n).c_str());
    std::_Exit(99);
  }
  std::string what_;
  std::mutex m_;
  std::condition_variable cv_;
  bool done_ = false;
  std::vector<pid_t> children_;
  std::thread thread_;
};

// One-byte messages over a pipe, with deadlines.
struct Pipe {
  int fd[2] = {-1, -1};
  Pipe() {
    if (::pipe2(fd, O_CLOEXEC) != 0) std::abort();
  }
  ~Pipe() {
    for (int f : fd) {
      if (f >= 0) ::close(f);
    }
  }
  Pipe(const Pipe&) = delete;
  Pipe& operator=(const Pipe&) = delete;
  void send(char c) const {
    if (::write(fd[1], &c, 1) != 1) std::abort();
  }
  // Returns the byte, or 0 on timeout / EOF.
  char recv(std::chrono::milliseconds timeout) const {
    pollfd p{fd[0], POLLIN, 0};
    const auto deadline = Clock::now() + timeout;
    for (;;) {
      auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
      if (left.count() < 0) return 0;
      int rc = ::poll(&p, 1, static_cast<int>(left.count()));
      if (rc < 0 && errno == EINTR) continue;
      if (rc <= 0) return 0;
      char c = 0;
      return ::read(fd[0], &c, 1) == 1 ? c : 0;
    }
  }
};

// A fork()ed child running fn (returning its exit code); killed -9 and reaped on destruction.
class Child {
 public:
  // clone_flags: 0 = fork(). CLONE_NEWPID and/or CLONE_NEWNS emulate a container: the child
  // is pid 1 of a new pid namespace (killing it kills the namespace) and, with CLONE_NEWNS,
  // gets a private mount tree with its own /proc ("unshare --pid --fork --mount-proc").
  // `setup` runs in the child before fn (e.g. mount a private /dev/shm); nonzero = exit code.
  explicit Child(const std::function<int()>& fn, int clone_flags = 0,
                 const std::function<int()>& setup = {}) {
    if (clone_flags == 0) {
      pid_ = ::fork();
    } else {
      pid_ = static_cast<pid_t>(::syscall(SYS_clone, clone_flags | SIGCHLD, nullptr, nullptr,
                                          nullptr, nullptr));
    }
    if (pid_ < 0) {
      error_ = errno;
      return;
    }
    if (pid_ == 0) {
      if ((clone_flags & CLONE_NEWNS) != 0) {
        if (::mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0) std::_Exit(97);
        if ((clone_flags & CLONE_NEWPID) != 0 &&
            ::mount("proc", "/proc", "proc", MS_NOSUID | MS_NODEV | MS_NOEXEC, nullptr) != 0) {
          std::_Exit(98);
        }
      }
      if (setup) {
        if (int rc = setup(); rc != 0) std::_Exit(rc);
      }
      int rc = 1;
      try {
        rc = fn();
      } catch (const std::exception& e) {
        std::fprintf(stderr, "child %d: exception: %s\n", ::getpid(), e.what());
        rc = 2;
      } catch (...) {
        rc = 3;
      }
      std::_Exit(rc);  // no destructors/atexit of the parent's objects in the child
    }
  }
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;
  ~Child() {
    if (pid_ > 0 && !reaped_) {
      ::kill(pid_, SIGKILL);
      ::waitpid(pid_, nullptr, 0);
    }
  }
  pid_t pid() const { return pid_; }
  bool started() const { return pid_ > 0; }
  int error() const { return error_; }  // errno of a failed fork/clone
  void kill9() {
    if (pid_ > 0) ::kill(pid_, SIGKILL);
  }
  // Waits for the child's exit (pidfd + poll, deadline). Returns the raw wait status, or -1
  // on timeout.
  int wait(std::chrono::milliseconds timeout) {
    if (pid_ <= 0) return -1;
    if (reaped_) return status_;
    int pfd = static_cast<int>(::syscall(SYS_pidfd_open, pid_, 0));
    if (pfd >= 0) {
      pollfd p{pfd, POLLIN, 0};
      int rc;
      do {
        rc = ::poll(&p, 1, static_cast<int>(timeout.count()));
      } while (rc < 0 && errno == EINTR);
      ::close(pfd);
      if (rc == 0) return -1;
    }
    if (::waitpid(pid_, &status_, 0) != pid_) return -1;
    reaped_ = true;
    return status_;
  }

 private:
  pid_t pid_ = -1;
  int error_ = 0;
  bool reaped_ = false;
  int status_ = 0;
};

inline bool exited_ok(int status) { return status >= 0 && WIFEXITED(status) && WEXITSTATUS(status) == 0; }
inline bool killed_by(int status, int sig) {
  return status >= 0 && WIFSIGNALED(status) && WTERMSIG(status) == sig;
}

// Deterministic message content: [u64 index][u32 size][u32 checksum][bytes...].
inline std::uint32_t fnv1a(const unsigned char* p, std::size_t n) {
  std::uint32_t h = 2166136261u;
  for (std::size_t i = 0; i < n; ++i) h = (h ^ p[i]) * 16777619u;
  return h;
}

inline void fill_message(unsigned char* p, std::size_t size, std::uint64_t index) {
  if (size < 16) std::abort();  // test bug: messages carry a 16-byte header
  std::uint64_t x = index * 0x9E3779B97F4A7C15ull + 1;
  for (std::size_t i = 16; i < size; ++i) {
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
    p[i] = static_cast<unsigned char>(x);
  }
  const std::uint32_t sz = static_cast<std::uint32_t>(size);
  const std::uint32_t ck = fnv1a(p + 16, size > 16 ? size - 16 : 0);
  std::memcpy(p, &index, 8);
  std::memcpy(p + 8, &sz, 4);
  std::memcpy(p + 12, &ck, 4);
}

// True if p[0, size) is an intact message; *index receives its index.
inline bool check_message(const std::byte* bp, std::size_t size, std::uint64_t* index) {
  const auto* p = reinterpret_cast<const unsigned char*>(bp);
  if (size < 16) return false;
  std::uint32_t sz = 0, ck = 0;
  std::memcpy(index, p, 8);
  std::memcpy(&sz, p + 8, 4);
  std::memcpy(&ck, p + 12, 4);
  return sz == size && ck == fnv1a(p + 16, size - 16);
}

inline double thread_cpu_ms() {
  timespec ts{};
  ::clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec / 1e6;
}

#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
inline constexpr bool kSanitized = true;
#else
inline constexpr bool kSanitized = false;
#endif

// Writer options for tests: `slots` slots, `subs` readers, 4 KiB slots growing to 1 MiB.
inline WriterOptions opts(std::uint32_t slots = 8, std::uint32_t subs = 8) {
  WriterOptions o;
  o.slot_count = slots;
  o.max_subscribers = subs;
  o.initial_slot_size = 4096;
  o.max_message_size = 1 << 20;
  return o;
}

// Writes test message `index` (fill_message) of `size` bytes; returns its sequence number.
inline std::uint64_t write_msg(Writer& w, std::uint64_t index, std::size_t size) {
  std::vector<unsigned char> buf(size);
  fill_message(buf.data(), size, index);
  return w.write(buf.data(), size);
}

// Child side: blocks until the parent kills it (bounded so a lost parent cannot leak it).
[[noreturn]] inline void park(const Pipe& from_parent) {
  from_parent.recv(60s);
  std::_Exit(0);
}

}  // namespace lcmx::shm::test
