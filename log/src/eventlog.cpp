#include "lcmx/log/eventlog.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <sys/uio.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <climits>
#include <cstring>
#include <utility>

namespace lcmx::eventlog {
namespace {

constexpr std::size_t kWindow = 1u << 20;          // reader's read-ahead
constexpr std::size_t kWriteBuffer = 1u << 20;     // writer's buffer
constexpr std::size_t kDirectWrite = 64u << 10;    // data at least this big is written in place
constexpr std::size_t kMaxDamageKept = 1000;
constexpr std::byte kSync[4] = {std::byte{0xED}, std::byte{0xA1}, std::byte{0xDA}, std::byte{0x01}};

void put_be(std::byte* p, std::uint64_t v, int bytes) {
  for (int i = bytes - 1; i >= 0; --i, v >>= 8) p[i] = static_cast<std::byte>(v & 0xffu);
}
std::uint64_t get_be(const std::byte* p, int bytes) {
  std::uint64_t v = 0;
  for (int i = 0; i < bytes; ++i) v = (v << 8) | std::to_integer<std::uint8_t>(p[i]);
  return v;
}
std::string errno_text(const std::string& what) { return what + ": " + std::strerror(errno); }

}  // namespace

void encode_header(std::byte* out, std::int64_t number, std::int64_t timestamp_us,
                   std::uint32_t channel_length, std::uint32_t data_length) {
  put_be(out, kSyncWord, 4);
  put_be(out + 4, static_cast<std::uint64_t>(number), 8);
  put_be(out + 12, static_cast<std::uint64_t>(timestamp_us), 8);
  put_be(out + 20, channel_length, 4);
  put_be(out + 24, data_length, 4);
}

const char* to_string(Damage::Kind k) {
  return k == Damage::Kind::truncated ? "truncated" : "corrupt";
}

// ---------------------------------------------------------------- Reader

Reader Reader::open(const std::string& path, ReaderOptions options) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw Error(errno_text("cannot open '" + path + "'"));
  struct stat st{};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd);
    throw Error("'" + path + "' is not a regular file");
  }
  Reader r(fd, options);
  r.size_ = static_cast<std::uint64_t>(st.st_size);
  return r;
}

Reader::Reader(int fd, ReaderOptions o) : fd_(fd), options_(o) {}

Reader::Reader(Reader&& o) noexcept
    : fd_(std::exchange(o.fd_, -1)), options_(o.options_), pos_(o.pos_), size_(o.size_),
      win_(std::move(o.win_)), win_off_(o.win_off_), win_len_(std::exchange(o.win_len_, 0)),
      damage_(std::move(o.damage_)), damage_count_(o.damage_count_),
      damaged_bytes_(o.damaged_bytes_) {}

Reader& Reader::operator=(Reader&& o) noexcept {
  if (this != &o) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = std::exchange(o.fd_, -1);
    options_ = o.options_;
    pos_ = o.pos_;
    size_ = o.size_;
    win_ = std::move(o.win_);
    win_off_ = o.win_off_;
    win_len_ = std::exchange(o.win_len_, 0);
    damage_ = std::move(o.damage_);
    damage_count_ = o.damage_count_;
    damaged_bytes_ = o.damaged_bytes_;
  }
  return *this;
}

Reader::~Reader() {
  if (fd_ >= 0) ::close(fd_);
}

void Reader::refresh_size() {
  struct stat st{};
  if (::fstat(fd_, &st) == 0) {
    const auto s = static_cast<std::uint64_t>(st.st_size);
    if (s != size_) win_len_ = 0;  // grown (or cut): the window may be stale at its end
    size_ = s;
  }
}

void Reader::seek(std::uint64_t offset) { pos_ = offset; }

// Reads up to n bytes at `off` (fewer at the end of the file), through the window for small
// reads. Throws Error on an I/O error.
std::size_t Reader::read_at(std::uint64_t off, void* buf, std::size_t n) {
  if (n == 0 || off >= size_) return 0;
  n = static_cast<std::size_t>(std::min<std::uint64_t>(n, size_ - off));
  auto* out = static_cast<std::byte*>(buf);
  if (off >= win_off_ && off + n <= win_off_ + win_len_) {
    std::memcpy(out, win_.data() + (off - win_off_), n);
    return n;
  }
  auto pread_all = [&](std::byte* dst, std::size_t len, std::uint64_t at) {
    std::size_t done = 0;
    while (done < len) {
      const ssize_t r = ::pread(fd_, dst + done, len - done, static_cast<off_t>(at + done));
      if (r < 0) {
        if (errno == EINTR) continue;
        throw Error(errno_text("read failed"));
      }
      if (r == 0) break;  // the file shrank meanwhile
      done += static_cast<std::size_t>(r);
    }
    return done;
  };
  if (n >= kWindow / 2) return pread_all(out, n, off);
  if (win_.size() < kWindow) win_.resize(kWindow);
  win_off_ = off;
  win_len_ = pread_all(win_.data(), kWindow, off);
  const std::size_t got = std::min(n, win_len_);
  std::memcpy(out, win_.data(), got);
  return got;
}

// Whether an acceptable event starts at `off` (see README.md): sane lengths, inside the
// file, followed by a sync word or the end of the file (or a tail too short to hold one).
// `truncated`: the header is fine but the event runs past the end of the file.
bool Reader::header_at(std::uint64_t off, std::int64_t& number, std::int64_t& ts,
                       std::uint32_t& chlen, std::uint32_t& dlen, bool& truncated) {
  truncated = false;
  std::byte h[kHeaderSize];
  if (read_at(off, h, kHeaderSize) < kHeaderSize) {
    truncated = true;
    return false;
  }
  if (std::memcmp(h, kSync, 4) != 0) return false;
  number = static_cast<std::int64_t>(get_be(h + 4, 8));
  ts = static_cast<std::int64_t>(get_be(h + 12, 8));
  const auto c = static_cast<std::int32_t>(get_be(h + 20, 4));
  const auto d = static_cast<std::int32_t>(get_be(h + 24, 4));
  if (c <= 0 || static_cast<std::size_t>(c) > kMaxChannelLength || d < 0) return false;
  chlen = static_cast<std::uint32_t>(c);
  dlen = static_cast<std::uint32_t>(d);
  const std::uint64_t end = off + kHeaderSize + chlen + dlen;
  if (end > size_) {
    truncated = true;
    return false;
  }
  if (size_ - end >= 4) {
    std::byte s[4];
    if (read_at(end, s, 4) < 4 || std::memcmp(s, kSync, 4) != 0) return false;
  }
  char ch[kMaxChannelLength];
  if (read_at(off + kHeaderSize, ch, chlen) < chlen) return false;
  return std::memchr(ch, '\0', chlen) == nullptr;
}

std::optional<std::uint64_t> Reader::find_sync(std::uint64_t from) {
  std::byte buf[64 * 1024];
  while (from + 4 <= size_) {
    const std::size_t n = read_at(from, buf, sizeof buf);
    if (n < 4) return std::nullopt;
    const void* hit = ::memmem(buf, n, kSync, 4);
    if (hit != nullptr)
      return from + static_cast<std::uint64_t>(static_cast<const std::byte*>(hit) - buf);
    from += n - 3;  // a sync word may straddle two reads
  }
  return std::nullopt;
}

void Reader::add_damage(Damage::Kind k, std::uint64_t off, std::uint64_t len) {
  if (len == 0) return;
  ++damage_count_;
  damaged_bytes_ += len;
  if (damage_.size() < kMaxDamageKept) damage_.push_back({k, off, len});
}

bool Reader::next(Event& e) {
  if (fd_ < 0) return false;
  if (pos_ >= size_) {
    refresh_size();
    if (pos_ >= size_) return false;
  }
  std::int64_t number = 0, ts = 0;
  std::uint32_t chlen = 0, dlen = 0;
  bool truncated = false;
  if (!header_at(pos_, number, ts, chlen, dlen, truncated)) {
    if (truncated) {
      // A file still being written may have grown since: look again before calling it torn.
      refresh_size();
      if (header_at(pos_, number, ts, chlen, dlen, truncated)) goto accepted;
    }
    {
      const std::uint64_t start = pos_;
      std::uint64_t from = pos_ + 1;
      for (;;) {
        const auto s = find_sync(from);
        if (!s) {
          add_damage(Damage::Kind::truncated, start, size_ - start);
          pos_ = size_;
          return false;
        }
        if (header_at(*s, number, ts, chlen, dlen, truncated)) {
          add_damage(Damage::Kind::corrupt, start, *s - start);
          pos_ = *s;
          break;
        }
        from = *s + 1;
      }
    }
  }
accepted:
  e.offset = pos_;
  e.number = number;
  e.timestamp_us = ts;
  e.channel.resize(chlen);
  read_at(pos_ + kHeaderSize, e.channel.data(), chlen);
  e.size = dlen;
  const std::size_t want = std::min<std::size_t>(dlen, options_.data_prefix);
  e.data.resize(want);
  if (want > 0 && read_at(pos_ + kHeaderSize + chlen, e.data.data(), want) < want)
    throw Error("read failed: the file shrank while being read");
  pos_ += kHeaderSize + chlen + dlen;
  return true;
}

// ---------------------------------------------------------------- Writer

Writer Writer::open(const std::string& path, OpenMode mode) {
  std::uint64_t size = 0;
  std::int64_t next = 0;
  int flags = O_WRONLY | O_CREAT | O_CLOEXEC;
  if (mode == OpenMode::create) flags |= O_EXCL;
  if (mode == OpenMode::overwrite) flags |= O_TRUNC;
  if (mode == OpenMode::append) {
    flags |= O_APPEND;
    struct stat st{};
    if (::stat(path.c_str(), &st) == 0) {
      // Continue the numbering; cut off a torn last event so that appended events are not
      // taken for its remainder.
      ReaderOptions ro;
      ro.data_prefix = 0;
      auto r = Reader::open(path, ro);
      Event e;
      std::uint64_t good_end = 0;
      bool any = false;
      while (r.next(e)) {
        any = true;
        next = e.number + 1;
        good_end = r.position();
      }
      if (!any) good_end = 0;
      if (!r.damage().empty() && r.damage().back().kind == Damage::Kind::truncated &&
          r.damage().back().offset >= good_end) {
        if (::truncate(path.c_str(), static_cast<off_t>(good_end)) != 0)
          throw Error(errno_text("cannot cut the torn end of '" + path + "'"));
      }
    }
  }
  const int fd = ::open(path.c_str(), flags, 0644);
  if (fd < 0) throw Error(errno_text("cannot open '" + path + "' for writing"));
  struct stat st{};
  if (::fstat(fd, &st) == 0) size = static_cast<std::uint64_t>(st.st_size);
  return Writer(fd, path, size, next);
}

Writer::Writer(int fd, std::string path, std::uint64_t size, std::int64_t next_number)
    : fd_(fd), path_(std::move(path)), bytes_(size), next_number_(next_number),
      first_number_(next_number) {
  buf_.reserve(kWriteBuffer + 4096);
}

Writer::Writer(Writer&& o) noexcept
    : fd_(std::exchange(o.fd_, -1)), path_(std::move(o.path_)), buf_(std::move(o.buf_)),
      bytes_(o.bytes_), next_number_(o.next_number_), first_number_(o.first_number_),
      buf_ends_(std::move(o.buf_ends_)), events_out_(o.events_out_) {}

Writer& Writer::operator=(Writer&& o) noexcept {
  if (this != &o) {
    try {
      close();
    } catch (...) {
    }
    fd_ = std::exchange(o.fd_, -1);
    path_ = std::move(o.path_);
    buf_ = std::move(o.buf_);
    bytes_ = o.bytes_;
    next_number_ = o.next_number_;
    first_number_ = o.first_number_;
    buf_ends_ = std::move(o.buf_ends_);
    events_out_ = o.events_out_;
  }
  return *this;
}

Writer::~Writer() {
  try {
    close();
  } catch (...) {
  }
}

void Writer::write_all(const void* p, std::size_t n, std::size_t* done) {
  const auto* b = static_cast<const std::byte*>(p);
  while (n > 0) {
    const ssize_t r = ::write(fd_, b, n);
    if (r < 0) {
      if (errno == EINTR) continue;
      throw Error(errno_text("write to '" + path_ + "' failed"));
    }
    b += r;
    n -= static_cast<std::size_t>(r);
    if (done != nullptr) *done += static_cast<std::size_t>(r);
  }
}

void Writer::write(std::int64_t timestamp_us, std::string_view channel,
                   std::span<const std::byte> data) {
  if (fd_ < 0) throw Error("write to a closed log");
  if (channel.empty() || channel.size() > kMaxChannelLength)
    throw Error("channel name must have 1.." + std::to_string(kMaxChannelLength) + " bytes");
  if (data.size() > static_cast<std::size_t>(INT32_MAX))
    throw Error("event data of " + std::to_string(data.size()) + " bytes exceeds the format's 2 GiB");
  std::byte h[kHeaderSize];
  encode_header(h, next_number_, timestamp_us, static_cast<std::uint32_t>(channel.size()),
                static_cast<std::uint32_t>(data.size()));
  if (data.size() >= kDirectWrite) {
    flush();
    iovec iov[3] = {{h, kHeaderSize},
                    {const_cast<char*>(channel.data()), channel.size()},
                    {const_cast<std::byte*>(data.data()), data.size()}};
    std::size_t total = kHeaderSize + channel.size() + data.size();
    int first = 0;
    while (total > 0) {
      const ssize_t r = ::writev(fd_, iov + first, 3 - first);
      if (r < 0) {
        if (errno == EINTR) continue;
        throw Error(errno_text("write to '" + path_ + "' failed"));
      }
      auto done = static_cast<std::size_t>(r);
      total -= done;
      while (first < 3 && done >= iov[first].iov_len) done -= iov[first++].iov_len;
      if (first < 3) {
        iov[first].iov_base = static_cast<char*>(iov[first].iov_base) + done;
        iov[first].iov_len -= done;
      }
    }
    ++events_out_;
  } else {
    const auto* c = reinterpret_cast<const std::byte*>(channel.data());
    buf_.insert(buf_.end(), h, h + kHeaderSize);
    buf_.insert(buf_.end(), c, c + channel.size());
    buf_.insert(buf_.end(), data.begin(), data.end());
    buf_ends_.push_back(buf_.size());
    if (buf_.size() >= kWriteBuffer) flush();
  }
  bytes_ += kHeaderSize + channel.size() + data.size();
  ++next_number_;
}

void Writer::flush() {
  if (fd_ < 0 || buf_.empty()) return;
  // Cleared even if the write fails: the events are lost either way, and a retry would
  // write a duplicate prefix.
  std::vector<std::byte> b;
  b.swap(buf_);
  buf_.reserve(kWriteBuffer + 4096);
  std::vector<std::size_t> ends;
  ends.swap(buf_ends_);
  std::size_t done = 0;
  try {
    write_all(b.data(), b.size(), &done);
  } catch (...) {  // the events wholly written before the failure are in the file
    events_out_ += std::upper_bound(ends.begin(), ends.end(), done) - ends.begin();
    throw;
  }
  events_out_ += static_cast<std::int64_t>(ends.size());
}

void Writer::close() {
  if (fd_ < 0) return;
  try {
    flush();
  } catch (...) {
    ::close(std::exchange(fd_, -1));
    throw;
  }
  if (::close(std::exchange(fd_, -1)) != 0) throw Error(errno_text("close of '" + path_ + "' failed"));
}

}  // namespace lcmx::eventlog
