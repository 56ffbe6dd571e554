// OFD locks: who is alive, across pid namespaces.
//
// Open file description locks (F_OFD_SETLK) belong to an open file description, not to a
// pid: the kernel drops them when the last reference to the description goes (the holder
// closed it or died, whatever its pid namespace). Any process that can open the file can
// test them (F_OFD_GETLK). A pid read from shared memory means nothing in another pid
// namespace and can be reused; a lock cannot be faked by a dead process.
//
// fork(): a child shares its parent's open file descriptions, so it would keep the parent's
// locks alive after the parent died. pthread_atfork closes every LockFd in the child (the
// description then belongs to the parent alone), and mappings are made through a separate
// description (segment_file.cpp), so a child's inherited mapping holds no lock either.
// exec(): the descriptors are O_CLOEXEC.
#include <fcntl.h>
#include <pthread.h>
#include <unistd.h>

#include <algorithm>
#include <mutex>
#include <vector>

#include "impl.hpp"

namespace lcmx::shm::detail {
namespace {

std::mutex g_fds_mu;
std::vector<int>* g_fds = nullptr;  // leaked on purpose (used until exit)
std::once_flag g_atfork_once;

void atfork_prepare() { g_fds_mu.lock(); }
void atfork_parent() { g_fds_mu.unlock(); }
void atfork_child() {
  // Only this thread exists now. Close the parent's lock descriptors; the LockFd objects
  // in our copy of memory see pid_ != getpid() and never touch them again.
  if (g_fds != nullptr) {
    for (int fd : *g_fds) ::close(fd);
    g_fds->clear();
  }
  g_fds_mu.unlock();
}

void track(int fd) {
  std::call_once(g_atfork_once, [] {
    g_fds = new std::vector<int>();
    ::pthread_atfork(atfork_prepare, atfork_parent, atfork_child);
  });
  std::lock_guard lock(g_fds_mu);
  g_fds->push_back(fd);
}

void untrack(int fd) {
  std::lock_guard lock(g_fds_mu);
  if (g_fds == nullptr) return;
  auto it = std::find(g_fds->begin(), g_fds->end(), fd);
  if (it != g_fds->end()) g_fds->erase(it);
}

struct flock one_byte(short type, std::uint64_t byte) {
  struct flock fl {};
  fl.l_type = type;
  fl.l_whence = SEEK_SET;
  fl.l_start = static_cast<off_t>(byte);
  fl.l_len = 1;
  fl.l_pid = 0;  // required by OFD locks
  return fl;
}

}  // namespace

LockFd::LockFd(int fd) : fd_(fd), pid_(::getpid()) {
  if (fd_ >= 0) track(fd_);
}

LockFd::LockFd(LockFd&& o) noexcept : fd_(std::exchange(o.fd_, -1)), pid_(o.pid_) {}

LockFd& LockFd::operator=(LockFd&& o) noexcept {
  if (this != &o) {
    reset();
    fd_ = std::exchange(o.fd_, -1);
    pid_ = o.pid_;
  }
  return *this;
}

LockFd::~LockFd() { reset(); }

void LockFd::reset() noexcept {
  if (fd_ >= 0 && pid_ == ::getpid()) {
    untrack(fd_);
    ::close(fd_);  // drops every lock of this description
  }
  fd_ = -1;
}

bool try_lock(int fd, std::uint64_t byte) noexcept {
  struct flock fl = one_byte(F_WRLCK, byte);
  return ::fcntl(fd, F_OFD_SETLK, &fl) == 0;
}

void unlock(int fd, std::uint64_t byte) noexcept {
  struct flock fl = one_byte(F_UNLCK, byte);
  ::fcntl(fd, F_OFD_SETLK, &fl);
}

bool locked_by_other(int fd, std::uint64_t byte) noexcept {
  struct flock fl = one_byte(F_WRLCK, byte);
  if (::fcntl(fd, F_OFD_GETLK, &fl) != 0) return true;  // unknown: assume alive
  return fl.l_type != F_UNLCK;
}

}  // namespace lcmx::shm::detail
