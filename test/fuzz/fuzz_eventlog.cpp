// libFuzzer target: lcmx::eventlog::Reader on arbitrary files. Invariants: it never crashes or
// throws on content, every byte of the file is either in an accepted event or in a reported
// damaged region (in file order, without overlap), and events re-written by the Writer read
// back identical.
#include <sys/mman.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "lcmx/log/eventlog.hpp"

namespace el = lcmx::eventlog;

namespace {
std::string memfd_path(const std::uint8_t* data, std::size_t size, int& fd) {
  fd = ::memfd_create("fuzz_eventlog", MFD_CLOEXEC);
  if (fd < 0) std::abort();
  std::size_t done = 0;
  while (done < size) {
    const ssize_t n = ::write(fd, data + done, size - done);
    if (n <= 0) std::abort();
    done += static_cast<std::size_t>(n);
  }
  return "/proc/self/fd/" + std::to_string(fd);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  int fd = -1;
  const std::string path = memfd_path(data, size, fd);
  std::vector<el::Event> events;
  std::uint64_t covered = 0;
  std::uint64_t pos = 0;
  {
    auto r = el::Reader::open(path);
    el::Event e;
    std::size_t damage_seen = 0;
    while (r.next(e)) {
      // Damage found before this event lies between the previous event and this one.
      for (; damage_seen < r.damage().size(); ++damage_seen) {
        const auto& d = r.damage()[damage_seen];
        if (d.offset != pos || d.kind != el::Damage::Kind::corrupt) std::abort();
        pos += d.length;
        covered += d.length;
      }
      if (e.offset != pos) std::abort();
      if (e.channel.empty() || e.channel.size() > el::kMaxChannelLength || e.data.size() != e.size)
        std::abort();
      pos = r.position();
      covered += el::kHeaderSize + e.channel.size() + e.data.size();
      events.push_back(e);
    }
    for (; damage_seen < r.damage().size(); ++damage_seen) {
      const auto& d = r.damage()[damage_seen];
      if (d.offset != pos) std::abort();
      pos += d.length;
      covered += d.length;
    }
    if (covered != size || r.damaged_bytes() + (covered - r.damaged_bytes()) != size) std::abort();
  }
  ::close(fd);

  // Round trip: the accepted events, written again, read back the same.
  if (!events.empty()) {
    char tmpl[] = "/tmp/fuzz_eventlog_XXXXXX";
    const int tfd = ::mkstemp(tmpl);
    if (tfd < 0) std::abort();
    ::close(tfd);
    {
      auto w = el::Writer::open(tmpl, el::OpenMode::overwrite);
      for (const auto& e : events) w.write(e.timestamp_us, e.channel, e.data);
      w.close();
    }
    auto r = el::Reader::open(tmpl);
    el::Event e;
    std::size_t i = 0;
    while (r.next(e)) {
      if (i >= events.size() || e.channel != events[i].channel || e.data != events[i].data ||
          e.timestamp_us != events[i].timestamp_us || e.number != static_cast<std::int64_t>(i))
        std::abort();
      ++i;
    }
    if (i != events.size() || r.damage_count() != 0) std::abort();
    std::remove(tmpl);
  }
  return 0;
}
