// owner_alive, shm_domain_id, OwnerWatch (see lcmx/shm/liveness.hpp).
#include "lcmx/shm/liveness.hpp"

#include <fcntl.h>
#include <sys/epoll.h>
#include <sys/inotify.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/timerfd.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <map>

#include "impl.hpp"

namespace lcmx::shm {

bool owner_alive(const std::string& segment_name) noexcept {
  if (segment_name.empty() || segment_name.find('/') != std::string::npos) return false;
  return detail::writer_lock_held(segment_name);
}

std::uint64_t shm_domain_id() noexcept {
  struct stat st {};
  if (::stat("/dev/shm", &st) != 0) return 0;
  // Device and inode: a container whose /dev/shm is a bind mount of another directory of the
  // same tmpfs has the same device but other files.
  const std::uint64_t id = (static_cast<std::uint64_t>(st.st_dev) * 0x9e3779b97f4a7c15ull) ^
                           static_cast<std::uint64_t>(st.st_ino);
  return id == 0 ? 1 : id;
}

namespace {
constexpr std::uint64_t kInotifyKey = 0;
constexpr std::uint64_t kTimerKey = 1;
constexpr int kRetries = 40;  // x 5 ms after an inotify event
}  // namespace

struct OwnerWatch::Impl {
  struct Entry {
    int file = -1;    // O_RDONLY description of the segment file (lock tests)
    int pidfd = -1;   // same pid namespace: readable when the Writer exits
    int wd = -1;      // otherwise: inotify watch
  };
  int ep = -1, ino = -1, timer = -1;
  std::uint64_t next_key = 2;
  std::map<std::uint64_t, Entry> entries;
  std::vector<std::uint64_t> pending;  // already known dead
  int retries = 0;

  void arm_timer(long ns, long interval_ns) {
    itimerspec t{};
    t.it_value.tv_nsec = ns;
    t.it_interval.tv_nsec = interval_ns;
    ::timerfd_settime(timer, 0, &t, nullptr);
  }
  void drop(std::uint64_t key) noexcept {
    auto it = entries.find(key);
    if (it == entries.end()) return;
    if (it->second.pidfd >= 0) ::close(it->second.pidfd);  // also leaves the epoll set
    if (it->second.wd >= 0) ::inotify_rm_watch(ino, it->second.wd);
    if (it->second.file >= 0) ::close(it->second.file);
    entries.erase(it);
  }
  ~Impl() {
    while (!entries.empty()) drop(entries.begin()->first);
    for (int f : {timer, ino, ep})
      if (f >= 0) ::close(f);
  }
};

OwnerWatch::OwnerWatch() : impl_(std::make_unique<Impl>()) {
  auto& m = *impl_;
  m.ep = ::epoll_create1(EPOLL_CLOEXEC);
  m.ino = ::inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
  m.timer = ::timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC);
  if (m.ep < 0 || m.ino < 0 || m.timer < 0) {
    throw Error(Errc::system, std::string("OwnerWatch: ") + std::strerror(errno));
  }
  epoll_event ev{};
  ev.events = EPOLLIN;
  ev.data.u64 = kInotifyKey;
  ::epoll_ctl(m.ep, EPOLL_CTL_ADD, m.ino, &ev);
  ev.data.u64 = kTimerKey;
  ::epoll_ctl(m.ep, EPOLL_CTL_ADD, m.timer, &ev);
}

OwnerWatch::~OwnerWatch() = default;

int OwnerWatch::fd() const noexcept { return impl_->ep; }

std::uint64_t OwnerWatch::watch(const std::string& segment_name) {
  using namespace detail;
  auto& m = *impl_;
  if (segment_name.empty() || segment_name.find('/') != std::string::npos) {
    throw Error(Errc::invalid_argument, "OwnerWatch: bad segment name '" + segment_name + "'");
  }
  Impl::Entry e;
  e.file = ::shm_open(("/" + segment_name).c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW, 0);
  if (e.file < 0) {
    throw Error(errno == ENOENT ? Errc::not_found : Errc::system,
                "OwnerWatch: " + segment_name + ": " + std::strerror(errno));
  }
  const std::uint64_t key = m.next_key++;
  if (!locked_by_other(e.file, kWriterLockByte)) {  // already gone
    ::close(e.file);
    m.pending.push_back(key);
    m.arm_timer(1, 0);  // make fd() readable
    return key;
  }
  const auto info = peek_segment(segment_name, nullptr);
  const std::uint64_t ns = self_pidns();
  if (info && ns != 0 && info->owner_pidns == ns) {
    const int pfd = static_cast<int>(::syscall(SYS_pidfd_open, info->owner_pid, 0));
    // The pid named the Writer when we opened the pidfd if its start time still matches.
    if (pfd >= 0 && process_start_time(info->owner_pid) == info->owner_start_time) {
      e.pidfd = pfd;
    } else if (pfd >= 0) {
      ::close(pfd);
    }
  }
  if (e.pidfd >= 0) {
    epoll_event ev{};
    ev.events = EPOLLIN;
    ev.data.u64 = key;
    ::epoll_ctl(m.ep, EPOLL_CTL_ADD, e.pidfd, &ev);
  } else {
    e.wd = ::inotify_add_watch(m.ino, ("/dev/shm/" + segment_name).c_str(),
                               IN_CLOSE_WRITE | IN_DELETE_SELF | IN_ATTRIB);
    if (e.wd < 0) {
      const int err = errno;
      ::close(e.file);
      throw Error(Errc::system, "OwnerWatch: inotify " + segment_name + ": " + std::strerror(err));
    }
  }
  m.entries.emplace(key, e);
  // Lost race: it died between the test above and the watch.
  if (!locked_by_other(e.file, kWriterLockByte)) m.arm_timer(1, 0);
  return key;
}

void OwnerWatch::unwatch(std::uint64_t key) noexcept { impl_->drop(key); }

std::vector<std::uint64_t> OwnerWatch::take_dead() {
  using namespace detail;
  auto& m = *impl_;
  std::vector<std::uint64_t> dead = std::move(m.pending);
  m.pending.clear();
  epoll_event evs[32];
  bool recheck = false, inotified = false;
  for (;;) {
    const int n = ::epoll_wait(m.ep, evs, 32, 0);
    if (n <= 0) break;
    for (int i = 0; i < n; ++i) {
      const std::uint64_t k = evs[i].data.u64;
      if (k == kInotifyKey) {
        alignas(inotify_event) char buf[4096];
        while (::read(m.ino, buf, sizeof buf) > 0) {
        }
        recheck = inotified = true;
      } else if (k == kTimerKey) {
        std::uint64_t ticks = 0;
        if (::read(m.timer, &ticks, sizeof ticks) < 0) ticks = 0;
        recheck = true;
        if (m.retries > 0 && --m.retries == 0) m.arm_timer(0, 0);
      } else if (m.entries.count(k) != 0) {
        dead.push_back(k);  // pidfd readable: the process exited
        m.drop(k);
      }
    }
    if (n < 32) break;
  }
  if (recheck) {
    bool still = false;
    for (auto it = m.entries.begin(); it != m.entries.end();) {
      const auto k = it->first;
      ++it;
      const auto& e = m.entries.at(k);
      if (e.wd < 0 && e.pidfd >= 0) continue;
      if (!locked_by_other(e.file, kWriterLockByte)) {
        dead.push_back(k);
        m.drop(k);
      } else {
        still = true;
      }
    }
    // The close event comes just before the kernel drops the lock: look again shortly.
    if (inotified && still) {
      m.retries = kRetries;
      m.arm_timer(5'000'000, 5'000'000);
    }
  }
  return dead;
}

}  // namespace lcmx::shm
