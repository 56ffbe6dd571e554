// Key files on disk (lcmx/udpm/detail/key_file.hpp): group keys and the bridge's CURVE keys.
#include "lcmx/udpm/detail/key_file.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>

namespace lcmx::udpm::detail {
namespace {

KeyFileProblem problem(std::string why) { return KeyFileProblem{std::move(why)}; }

KeyFileProblem errno_problem(const char* what, int e) { return problem(std::string(what) + std::strerror(e)); }

// Why `st` (of a key file) is refused under `access`, or nullopt.
std::optional<KeyFileProblem> access_problem(const struct stat& st, KeyFileAccess access, KeyFileWords words) {
  const uid_t me = ::geteuid();
  char mode[8];
  std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
  const std::string found = "(mode " + std::string(mode) + ", owner uid " + std::to_string(st.st_uid) + ")";
  switch (access) {
    case KeyFileAccess::owner_only:
      if (st.st_uid == me && (st.st_mode & 077) == 0) return std::nullopt;
      return problem(std::string(words.noun) + " must be owned by this user (uid " + std::to_string(me) +
                     ") and readable by nobody else " + found + ": chmod 600 it (and chown it to this user)");
    case KeyFileAccess::public_key:
      if ((st.st_uid == me || st.st_uid == 0) && (st.st_mode & 022) == 0) return std::nullopt;
      return problem(std::string(words.noun) + " must be owned by this user or root and writable by nobody else " +
                     found + ": chmod go-w it");
  }
  return problem("unknown access policy");
}

}  // namespace

std::variant<std::string, KeyFileProblem> read_key_file_bytes(const std::string& path, KeyFileAccess access,
                                                              KeyFileWords words, std::size_t max_bytes) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NONBLOCK | O_NOCTTY);
  if (fd < 0) return errno_problem("cannot read: ", errno);
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode) || st.st_size > static_cast<off_t>(max_bytes)) {
    ::close(fd);
    return problem("not a key file (expected a regular file of at most " + std::to_string(max_bytes) + " bytes, as " +
                   std::string(words.made_by) + " writes)");
  }
  if (auto p = access_problem(st, access, words)) {
    ::close(fd);
    return std::move(*p);
  }
  std::string text(max_bytes + 1, '\0');
  std::size_t got = 0;
  while (got < text.size()) {
    const ssize_t n = ::read(fd, text.data() + got, text.size() - got);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) {
      const int e = errno;
      ::close(fd);
      return errno_problem("cannot read: ", e);
    }
    if (n == 0) break;
    got += static_cast<std::size_t>(n);
  }
  ::close(fd);
  if (got > max_bytes) return problem("not a key file (larger than " + std::to_string(max_bytes) + " bytes)");
  text.resize(got);  // no reallocation: a caller that wipes text.data() wipes every byte read
  return text;
}

std::optional<KeyFileProblem> check_key_file_target(const std::string& path, bool overwrite,
                                                    std::string_view exists_hint) {
  struct stat st {};
  if (::lstat(path.c_str(), &st) == 0) {
    if (S_ISLNK(st.st_mode)) return problem("is a symbolic link: refused (remove it first)");
    if (!S_ISREG(st.st_mode)) return problem("exists and is not a regular file: refused");
    if (!overwrite) return problem(std::string("cannot create: ") + std::strerror(EEXIST) + std::string(exists_hint));
  } else if (errno != ENOENT) {
    return errno_problem("cannot create: ", errno);
  }
  return std::nullopt;
}

std::optional<KeyFileProblem> write_key_file_bytes(const std::string& path, std::string_view text, mode_t mode,
                                                   bool overwrite) {
  std::string tmp = path + ".XXXXXX";
  const int fd = ::mkostemp(tmp.data(), O_CLOEXEC);  // mode 0600, O_EXCL: a new file, never a link's target
  if (fd < 0) return errno_problem("cannot create: ", errno);
  const bool ok = ::fchmod(fd, mode) == 0 &&
                  ::write(fd, text.data(), text.size()) == static_cast<ssize_t>(text.size()) && ::fsync(fd) == 0;
  const int e = errno;
  ::close(fd);
  if (!ok) {
    ::unlink(tmp.c_str());
    return errno_problem("write failed: ", e);
  }
  const int r = overwrite ? ::rename(tmp.c_str(), path.c_str()) : ::link(tmp.c_str(), path.c_str());
  const int re = errno;
  if (!overwrite || r != 0) ::unlink(tmp.c_str());
  if (r != 0) return errno_problem("cannot create: ", re);
  return std::nullopt;
}

}  // namespace lcmx::udpm::detail
