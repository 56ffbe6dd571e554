// The vehicle table's file format (vehicle_table.hpp, docs/discovery.md "Vehicle table").
#include "vehicle_table.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <utility>

namespace lcmx::discovery::table {

namespace {
template <class T>
void put(std::vector<std::byte>& out, std::size_t at, const T& v) {
  std::memcpy(out.data() + at, &v, sizeof v);
}
}  // namespace

std::vector<std::byte> encode(const Content& content, std::uint64_t host_id, std::uint64_t generation) {
  std::size_t hosts = std::min<std::size_t>(content.hosts.size(), kMaxHosts), records = 0, bytes = 0;
  for (std::size_t h = 0; h < hosts; ++h) {
    records += content.hosts[h].records.size();
    for (const auto& r : content.hosts[h].records) bytes += r.bytes.size();
  }
  const std::size_t index = sizeof(Header) + hosts * sizeof(Host) + records * sizeof(Record);
  std::vector<std::byte> out(index + bytes);
  Header hd{};
  hd.version = kVersion;
  hd.header_size = sizeof(Header);
  hd.host_count = static_cast<std::uint32_t>(hosts);
  hd.record_count = static_cast<std::uint32_t>(records);
  hd.host_id = host_id;
  hd.writer = content.writer;
  hd.written_ns = reg::now_ns();
  hd.generation = generation;
  hd.flags = content.complete ? kComplete : 0;
  put(out, 0, hd);
  std::size_t next_record = 0, next_byte = index;
  for (std::size_t h = 0; h < hosts; ++h) {
    const auto& in = content.hosts[h];
    Host host = in.host;
    host.first_record = static_cast<std::uint32_t>(next_record);
    host.record_count = static_cast<std::uint32_t>(in.records.size());
    put(out, sizeof(Header) + h * sizeof(Host), host);
    for (const auto& r : in.records) {
      Record rec{};
      rec.participant_id = r.participant_id;
      rec.revision = r.revision;
      rec.offset = next_byte;
      rec.length = static_cast<std::uint32_t>(r.bytes.size());
      rec.flags = r.flags;
      std::memcpy(rec.topics, r.topics.w, sizeof rec.topics);
      put(out, sizeof(Header) + hosts * sizeof(Host) + next_record * sizeof(Record), rec);
      if (!r.bytes.empty()) std::memcpy(out.data() + next_byte, r.bytes.data(), r.bytes.size());
      next_byte += r.bytes.size();
      ++next_record;
    }
  }
  return out;
}

std::optional<File> File::open(const std::string& path, bool* refused) {
  File f;
  f.fd_ = ::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW);
  if (f.fd_ < 0) {
    if (refused) *refused = errno != ENOENT;  // (a symbolic link: ELOOP)
    return std::nullopt;
  }
  if (refused) *refused = true;  // until every check passed
  struct stat st{};
  if (::fstat(f.fd_, &st) != 0 || !S_ISREG(st.st_mode) || (st.st_mode & 022) != 0 ||
      st.st_size < static_cast<off_t>(sizeof(Header)) || st.st_size > reg::kMaxStateBytes)
    return std::nullopt;
  f.size_ = static_cast<std::uint64_t>(st.st_size);
  f.owner_ = static_cast<std::uint32_t>(st.st_uid);
  if (!f.read(&f.header_, sizeof f.header_, 0)) return std::nullopt;
  const auto& h = f.header_;
  if (h.version != kVersion || h.header_size != sizeof(Header) || h.host_count > kMaxHosts) return std::nullopt;
  const std::uint64_t index = sizeof(Header) + std::uint64_t{h.host_count} * sizeof(Host) +
                              std::uint64_t{h.record_count} * sizeof(Record);
  if (index > f.size_) return std::nullopt;
  f.hosts_.resize(h.host_count);
  if (h.host_count > 0 && !f.read(f.hosts_.data(), h.host_count * sizeof(Host), sizeof(Header))) return std::nullopt;
  for (const auto& host : f.hosts_)
    if (std::uint64_t{host.first_record} + host.record_count > h.record_count) return std::nullopt;
  if (refused) *refused = false;
  return f;
}

File::File(File&& o) noexcept
    : fd_(std::exchange(o.fd_, -1)), size_(o.size_), owner_(o.owner_), header_(o.header_), hosts_(std::move(o.hosts_)) {}

File& File::operator=(File&& o) noexcept {
  if (this != &o) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = std::exchange(o.fd_, -1);
    size_ = o.size_;
    owner_ = o.owner_;
    header_ = o.header_;
    hosts_ = std::move(o.hosts_);
  }
  return *this;
}

File::~File() {
  if (fd_ >= 0) ::close(fd_);
}

bool File::read(void* out, std::size_t size, std::uint64_t offset) const {
  if (offset > size_ || size > size_ - offset) return false;
  auto* p = static_cast<char*>(out);
  std::size_t done = 0;
  while (done < size) {
    const auto n = ::pread(fd_, p + done, size - done, static_cast<off_t>(offset + done));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return false;
    done += static_cast<std::size_t>(n);
  }
  return true;
}

std::optional<std::vector<Record>> File::records(const Host& host) const {
  if (std::uint64_t{host.first_record} + host.record_count > header_.record_count) return std::nullopt;
  std::vector<Record> out(host.record_count);
  const std::uint64_t at = sizeof(Header) + std::uint64_t{header_.host_count} * sizeof(Host) +
                           std::uint64_t{host.first_record} * sizeof(Record);
  if (!out.empty() && !read(out.data(), out.size() * sizeof(Record), at)) return std::nullopt;
  for (const auto& r : out)
    if (r.offset > size_ || r.length > size_ - r.offset) return std::nullopt;
  return out;
}

std::optional<std::vector<std::byte>> File::bytes(const Record& record) const {
  std::vector<std::byte> out(record.length);
  if (!read(out.data(), out.size(), record.offset)) return std::nullopt;
  return out;
}

}  // namespace lcmx::discovery::table
