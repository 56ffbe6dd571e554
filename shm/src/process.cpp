// Process identity: pid + start time (guards against pid reuse), pid namespace.
// Liveness of segment owners and Readers is NOT judged from pids (see locks.cpp); pids are
// used only for pidfd-based death notification inside one pid namespace (owner_watch.cpp).
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <random>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "impl.hpp"

namespace lcmx::shm::detail {
namespace {

struct Stat {
  char state = '?';
  std::uint64_t start_time = 0;
};

// Parses /proc/<pid>/stat. The comm field (2) may contain spaces and ')': fields after it
// start after the LAST ')'. Returns nullopt and sets *err to errno if unreadable.
std::optional<Stat> read_stat(pid_t pid, int* err) {
  char path[64];
  std::snprintf(path, sizeof path, "/proc/%d/stat", static_cast<int>(pid));
  std::FILE* f = std::fopen(path, "re");
  if (f == nullptr) {
    *err = errno;
    return std::nullopt;
  }
  char buf[1024];
  std::size_t n = std::fread(buf, 1, sizeof buf - 1, f);
  std::fclose(f);
  buf[n] = '\0';
  const char* p = std::strrchr(buf, ')');
  if (p == nullptr) {
    *err = EINVAL;
    return std::nullopt;
  }
  ++p;
  Stat s;
  // After ')': field 3 (state) is the first token; field 22 is the 20th token.
  int field = 2;
  while (*p != '\0') {
    while (*p == ' ') ++p;
    if (*p == '\0') break;
    ++field;
    if (field == 3) s.state = *p;
    if (field == 22) {
      s.start_time = std::strtoull(p, nullptr, 10);
      return s;
    }
    while (*p != ' ' && *p != '\0') ++p;
  }
  *err = EINVAL;
  return std::nullopt;
}

}  // namespace

std::optional<std::uint64_t> process_start_time(pid_t pid) {
  int err = 0;
  auto s = read_stat(pid, &err);
  if (!s) return std::nullopt;
  return s->start_time;
}

std::uint64_t self_start_time() { return process_start_time(::getpid()).value_or(0); }

bool process_alive(std::int32_t pid, std::uint64_t start_time) {
  if (pid <= 0) return false;
  if (::kill(pid, 0) != 0 && errno != EPERM) return false;  // ESRCH: no such process
  int err = 0;
  auto s = read_stat(pid, &err);
  if (!s) return err != ENOENT && err != ESRCH;  // vanished => dead; unreadable => assume alive
  if (s->state == 'Z' || s->state == 'X') return false;  // killed, not yet reaped
  return s->start_time == start_time;
}

std::uint64_t self_pidns() noexcept {
  struct stat st {};
  if (::stat("/proc/self/ns/pid", &st) != 0) return 0;
  return static_cast<std::uint64_t>(st.st_ino);
}

}  // namespace lcmx::shm::detail

namespace lcmx::shm {

std::string process_tag() {
  char buf[64];
  std::uint64_t ns = detail::self_pidns();
  if (ns == 0) {  // no /proc: a random component instead, stable per process
    static std::atomic<std::uint64_t> random_tag{0};
    static std::atomic<pid_t> random_pid{0};
    if (random_pid.load() != ::getpid()) {
      std::random_device rd;
      random_tag.store((std::uint64_t{rd()} << 32) | rd());
      random_pid.store(::getpid());
    }
    ns = random_tag.load();
  }
  std::snprintf(buf, sizeof buf, "%dn%llx", static_cast<int>(::getpid()),
                static_cast<unsigned long long>(ns));
  return buf;
}

}  // namespace lcmx::shm
