// Segment files: create (O_EXCL, fallocate, Writer lock), open (ownership, mode, size
// checks), names, subscriber table, release of a departed Writer's generations.
#include <dirent.h>
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <map>

#include "impl.hpp"

namespace lcmx::shm::detail {
namespace {

bool is_digits(const std::string& s) {
  if (s.empty() || s.size() > 18) return false;
  for (char c : s) {
    if (c < '0' || c > '9') return false;
  }
  return true;
}

std::string errno_text(int e) { return std::strerror(e); }

int shm_open_cloexec(const std::string& name, int flags, mode_t mode = 0) {
  return ::shm_open(("/" + name).c_str(), flags | O_CLOEXEC | O_NOFOLLOW, mode);
}

struct Fd {  // plain RAII descriptor (not tracked for fork: holds no lock)
  int fd = -1;
  explicit Fd(int f) : fd(f) {}
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  ~Fd() {
    if (fd >= 0) ::close(fd);
  }
  int release() { return std::exchange(fd, -1); }
};

// Ownership policy for files we map: ours (same euid) or root's, regular, not writable by
// "others". Group write is allowed (lcmx creates 0660 files: the group is trusted).
const char* untrusted_why(const struct stat& st) {
  if (!S_ISREG(st.st_mode)) return "not a regular file";
  if (st.st_uid != ::geteuid() && st.st_uid != 0) return "owned by another user";
  if ((st.st_mode & S_IWOTH) != 0) return "writable by others";
  return nullptr;
}

}  // namespace

Mapping& Mapping::operator=(Mapping&& o) noexcept {
  if (this != &o) {
    this->~Mapping();
    addr = std::exchange(o.addr, nullptr);
    len = o.len;
    guard = std::exchange(o.guard, -1);
  }
  return *this;
}

Mapping::~Mapping() {
  if (addr == nullptr) return;
  guard_unregister(guard);  // first: the handler must not touch a range we give back
  ::munmap(addr, len);
  addr = nullptr;
  guard = -1;
}

std::optional<HeaderInfo> validate_header(const void* mem, std::uint64_t file_size,
                                          std::string* why) {
  auto fail = [&](const char* w) -> std::optional<HeaderInfo> {
    if (why) *why = w;
    return std::nullopt;
  };
  if (file_size < kHeaderSize) return fail("file smaller than the header");
  const auto* h = static_cast<const SegmentHeader*>(mem);
  // Pairs with the creator's magic.store(release): the rest of line 0/1 is visible.
  if (h->magic.load(std::memory_order_acquire) != kMagic) return fail("bad magic");
  if (h->version != kVersion) return fail("unsupported version");
  HeaderInfo info;
  const std::uint32_t slot_count = h->slot_count;
  const std::uint32_t max_subs = h->max_subscribers;
  const std::uint64_t slot_size = h->slot_size;
  if (slot_count < 2 || slot_count > kMaxSlotCount) return fail("bad slot_count");
  if (max_subs < 1 || max_subs > kMaxSubscribersLimit) return fail("bad max_subscribers");
  if (slot_size == 0 || slot_size > kMaxSlotSize || slot_size % kCacheLine != 0) {
    return fail("bad slot_size");
  }
  info.geo = make_geometry(slot_count, max_subs, slot_size);
  if (h->total_size != info.geo.total_size || h->subscribers_offset != info.geo.subscribers_offset ||
      h->desc_offset != info.geo.desc_offset || h->slots_offset != info.geo.slots_offset ||
      h->slot_stride != info.geo.slot_stride) {
    return fail("inconsistent layout");
  }
  if (info.geo.total_size > file_size) return fail("file smaller than its layout (truncated)");
  info.generation = h->generation;
  info.first_global_seq = h->first_global_seq;
  info.carried = h->carried;
  if (info.carried >= slot_count) return fail("bad carried count");
  info.owner_pid = h->owner_pid;
  info.owner_start_time = h->owner_start_time;
  info.owner_pidns = h->owner_pidns;
  info.writer_created_ns = h->writer_created_ns;
  return info;
}

std::optional<HeaderInfo> peek_segment(const std::string& name, std::string* why) {
  Fd fd(shm_open_cloexec(name, O_RDONLY));
  if (fd.fd < 0) {
    if (why) *why = errno_text(errno);
    return std::nullopt;
  }
  struct stat st {};
  if (::fstat(fd.fd, &st) != 0 || st.st_size < static_cast<off_t>(kHeaderSize)) {
    if (why) *why = "file smaller than the header";
    return std::nullopt;
  }
  if (const char* w = untrusted_why(st)) {
    if (why) *why = w;
    return std::nullopt;
  }
  Mapping m(::mmap(nullptr, kHeaderSize, PROT_READ, MAP_SHARED, fd.fd, 0), kHeaderSize);
  if (m.addr == MAP_FAILED) {
    m.addr = nullptr;
    if (why) *why = "mmap: " + errno_text(errno);
    return std::nullopt;
  }
  auto info = validate_header(m.addr, static_cast<std::uint64_t>(st.st_size), why);
  if (info && m.faulted()) {
    if (why) *why = "truncated while reading";
    return std::nullopt;
  }
  return info;
}

bool writer_lock_held(const std::string& name) noexcept {
  Fd fd(shm_open_cloexec(name, O_RDONLY));
  if (fd.fd < 0) return false;
  return locked_by_other(fd.fd, kWriterLockByte);
}

bool unlink_segment(const std::string& name) noexcept {
  return ::shm_unlink(("/" + name).c_str()) == 0;
}

std::unique_ptr<Segment> create_segment(
    const std::string& name, const Geometry& geo, std::uint64_t generation,
    std::uint64_t first_global_seq, std::int32_t pid, std::uint64_t start_time, std::uint64_t created_ns,
    const std::function<std::uint32_t(Segment&)>& fill) {
  int fd = -1;
  for (int attempt = 0; attempt < 2 && fd < 0; ++attempt) {
    fd = shm_open_cloexec(name, O_RDWR | O_CREAT | O_EXCL, 0660);
    if (fd >= 0) break;
    const int e = errno;
    if (e != EEXIST || attempt > 0) {
      throw Error(Errc::system, "create segment " + name + ": shm_open: " + errno_text(e));
    }
    if (writer_lock_held(name)) {
      throw Error(Errc::system, "create segment " + name + ": already exists (owner alive)");
    }
    std::string why;
    if (!peek_segment(name, &why)) {
      throw Error(Errc::system, "create segment " + name + ": already exists (" + why + ")");
    }
    unlink_segment(name);  // stale, owner dead: remove and retry once
  }
  auto seg = std::make_unique<Segment>();
  seg->name = name;
  seg->lock = LockFd(fd);
  auto fail = [&](const std::string& what, int e) {
    unlink_segment(name);
    throw Error(Errc::system, "segment " + name + ": " + what + ": " + errno_text(e));
  };
  // Writer lock first: from now on anyone can tell this file's owner is alive.
  if (!try_lock(fd, kWriterLockByte)) fail("writer lock (fcntl F_OFD_SETLK)", errno);
  ::fchmod(fd, 0660);  // independent of the umask
  // Reserve every page now: on a full tmpfs (Docker's default /dev/shm is 64 MiB) this is
  // ENOSPC here instead of a SIGBUS when a page is first touched.
  if (int e = ::posix_fallocate(fd, 0, static_cast<off_t>(geo.total_size)); e != 0) {
    unlink_segment(name);
    throw Error(Errc::system,
                "segment " + name + ": cannot reserve " + std::to_string(geo.total_size) +
                    " bytes in /dev/shm (posix_fallocate: " + errno_text(e) +
                    "; is /dev/shm full or too small?)");
  }
  // Map through a separate open file description: a fork()ed child inheriting the mapping
  // must not keep the lock's description (and so the lock) alive.
  Fd mfd(shm_open_cloexec(name, O_RDWR));
  if (mfd.fd < 0) fail("reopen for mapping", errno);
  void* a = ::mmap(nullptr, geo.total_size, PROT_READ | PROT_WRITE, MAP_SHARED, mfd.fd, 0);
  if (a == MAP_FAILED) fail("mmap", errno);
  seg->map = Mapping(a, geo.total_size);
  seg->geo = geo;
  seg->generation = generation;
  seg->first_global_seq = first_global_seq;
  // posix_fallocate zero-fills: every atomic starts at 0, a valid object representation.
  auto* h = static_cast<SegmentHeader*>(a);
  seg->hdr = h;
  h->version = kVersion;
  h->slot_count = geo.slot_count;
  h->max_subscribers = geo.max_subscribers;
  h->slot_size = geo.slot_size;
  h->total_size = geo.total_size;
  h->generation = generation;
  h->owner_pid = pid;
  h->owner_start_time = start_time;
  h->owner_pidns = self_pidns();
  h->writer_created_ns = created_ns;
  seg->writer_created_ns = created_ns;
  h->first_global_seq = first_global_seq;
  h->subscribers_offset = geo.subscribers_offset;
  h->desc_offset = geo.desc_offset;
  h->slots_offset = geo.slots_offset;
  h->slot_stride = geo.slot_stride;
  for (std::uint32_t i = 0; i < geo.max_subscribers; ++i) {
    auto& e = seg->sub(i);
    for (auto& p : e.pins) p.store(kPinFree, std::memory_order_relaxed);
  }
  for (std::uint32_t i = 0; i < geo.slot_count; ++i) {
    seg->desc(i).store(kDescEmpty, std::memory_order_relaxed);
    seg->slot(i).seq.store(kSlotEmpty, std::memory_order_relaxed);
  }
  if (fill) {
    std::uint32_t c = 0;
    try {
      c = fill(*seg);
    } catch (...) {
      unlink_segment(name);  // never published: no Reader can have it
      throw;
    }
    if (c >= geo.slot_count) std::abort();  // fill's contract
    seg->carried = c;
    h->carried = c;
    h->write_seq.store(c, std::memory_order_relaxed);  // published by the magic below
  }
  // Publishes everything above; pairs with validate_header's magic.load(acquire).
  h->magic.store(kMagic, std::memory_order_release);
  return seg;
}

std::unique_ptr<Segment> open_segment(const std::string& name) {
  auto seg = std::make_unique<Segment>();
  seg->name = name;
  Fd mfd(shm_open_cloexec(name, O_RDWR));
  if (mfd.fd < 0) {
    const int e = errno;
    if (e == ENOENT) throw Error(Errc::not_found, "open segment " + name + ": no such segment");
    if (e == ELOOP) {  // O_NOFOLLOW: a symbolic link planted under the name
      throw Error(Errc::untrusted, "open segment " + name + ": is a symbolic link");
    }
    throw Error(Errc::system, "open segment " + name + ": " + errno_text(e));
  }
  struct stat st {};
  if (::fstat(mfd.fd, &st) != 0) {
    throw Error(Errc::system, "fstat segment " + name + ": " + errno_text(errno));
  }
  // A segment name comes from an unauthenticated beacon: check who may have written it
  // before mapping it read-write.
  if (const char* why = untrusted_why(st)) {
    throw Error(Errc::untrusted, "segment " + name + ": refused: " + why);
  }
  if (st.st_size < static_cast<off_t>(kHeaderSize)) {
    throw Error(Errc::corrupt, "segment " + name + ": file smaller than the header");
  }
  const auto size = static_cast<std::uint64_t>(st.st_size);
  void* a = ::mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_SHARED, mfd.fd, 0);
  if (a == MAP_FAILED) {
    throw Error(Errc::system, "mmap segment " + name + ": " + errno_text(errno));
  }
  seg->map = Mapping(a, size);
  std::string why;
  auto info = validate_header(a, size, &why);
  if (!info) throw Error(Errc::corrupt, "segment " + name + ": " + why);
  // Our own description for OFD locks (entry lock, liveness tests); same file as mapped.
  int lfd = shm_open_cloexec(name, O_RDWR);
  struct stat lst {};
  if (lfd < 0 || ::fstat(lfd, &lst) != 0 || lst.st_ino != st.st_ino || lst.st_dev != st.st_dev) {
    if (lfd >= 0) ::close(lfd);
    throw Error(Errc::not_found, "segment " + name + ": replaced while opening");
  }
  seg->lock = LockFd(lfd);
  if (seg->faulted()) throw Error(Errc::corrupt, "segment " + name + ": truncated while opening");
  seg->geo = info->geo;
  seg->generation = info->generation;
  seg->first_global_seq = info->first_global_seq;
  seg->carried = info->carried;
  seg->writer_created_ns = info->writer_created_ns;
  seg->hdr = static_cast<SegmentHeader*>(a);
  if (auto sg = split_generation(name); sg && sg->second != seg->generation) {
    throw Error(Errc::corrupt, "segment " + name + ": generation field does not match the name");
  }
  return seg;
}

std::optional<std::pair<std::string, std::uint64_t>> split_generation(const std::string& name) {
  auto pos = name.rfind("_g");
  if (pos == std::string::npos || pos == 0) return std::nullopt;
  std::string digits = name.substr(pos + 2);
  if (!is_digits(digits)) return std::nullopt;
  return std::make_pair(name.substr(0, pos), std::stoull(digits));
}

std::string generation_name(const std::string& base, std::uint64_t gen) {
  return base + "_g" + std::to_string(gen);
}

std::vector<std::string> list_shm(const std::string& prefix) {
  std::vector<std::string> out;
  DIR* d = ::opendir("/dev/shm");
  if (d == nullptr) return out;
  while (const dirent* e = ::readdir(d)) {
    std::string n = e->d_name;
    if (n.size() >= prefix.size() && n.compare(0, prefix.size(), prefix) == 0) out.push_back(n);
  }
  ::closedir(d);
  return out;
}

std::optional<std::uint64_t> find_highest_generation(const std::string& base) {
  std::optional<std::uint64_t> best;
  for (const auto& n : list_shm(base + "_g")) {
    auto sg = split_generation(n);
    if (sg && sg->first == base && (!best || sg->second > *best)) best = sg->second;
  }
  return best;
}

// ---- subscriber table ----
// Mutating entry i requires its OFD lock (byte kEntryLockBase + i): a live Reader holds the
// lock of its entry for as long as it is registered; a registrant or reclaimer takes the
// lock of a free or dead entry with a non-blocking F_OFD_SETLK, so winning the lock proves
// the previous owner is dead (or never existed) in any pid namespace. Under the lock the
// entry is (re)initialised from scratch whatever state a killed process left it in (killed
// mid-register, mid-deregister or mid-reclaim: nothing is wedged). The state word carries
// an epoch, bumped on every transition (compare-exchange), so a stale view can never free
// an entry re-claimed since (no ABA) and a Reader can tell its entry was taken from it.
// Readers of the table without the lock: the Writer's pin scan and counts (read-only).

namespace {

void clear_dead_entry(const Segment& seg, SubscriberEntry& e) noexcept {
  // Release the dead Reader's pins (seq_cst: the Writer's pin scan is seq_cst).
  for (auto& p : e.pins) p.store(kPinFree, std::memory_order_seq_cst);
  // A Reader killed while armed left the waiter count raised: every commit would make a
  // useless wake syscall. The exchange makes exactly one clearer subtract it.
  if (e.armed.exchange(0, std::memory_order_acq_rel) != 0) {
    seg.hdr->waiters.fetch_sub(1, std::memory_order_seq_cst);
  }
  e.pid.store(0, std::memory_order_relaxed);
}

}  // namespace

bool subscriber_alive(const Segment& seg, std::uint32_t i) noexcept {
  const std::uint32_t w = seg.sub(i).state.load(std::memory_order_acquire);
  if (sub_state(w) == kSubFree) return false;
  return locked_by_other(seg.lock.get(), kEntryLockBase + i);
}

std::size_t reclaim_dead_subscribers(const Segment& seg) noexcept {
  std::size_t n = 0;
  const int fd = seg.lock.get();
  const std::uint32_t hw =
      std::min(seg.hdr->sub_high_water.load(std::memory_order_seq_cst), seg.geo.max_subscribers);
  for (std::uint32_t i = 0; i < hw; ++i) {
    auto& e = seg.sub(i);
    std::uint32_t w = e.state.load(std::memory_order_acquire);
    const bool leftovers = e.armed.load(std::memory_order_relaxed) != 0;
    if (sub_state(w) == kSubFree && !leftovers) continue;
    if (!try_lock(fd, kEntryLockBase + i)) continue;  // owner (or a registrant) alive
    w = e.state.load(std::memory_order_acquire);
    clear_dead_entry(seg, e);
    if (sub_state(w) != kSubFree) {
      // CAS cases: success => freed with a new epoch; failure => impossible while we hold
      // the lock unless a hostile process wrote the word: leave it to the next pass.
      if (e.state.compare_exchange_strong(w, sub_word(sub_epoch(w) + 1, kSubFree),
                                          std::memory_order_acq_rel)) {
        ++n;
      }
    }
    unlock(fd, kEntryLockBase + i);
  }
  return n;
}

std::pair<std::uint32_t, std::uint32_t> register_subscriber(const Segment& seg, int lock,
                                                            std::int32_t pid) {
  for (std::uint32_t i = 0; i < seg.geo.max_subscribers; ++i) {
    auto& e = seg.sub(i);
    std::uint32_t w = e.state.load(std::memory_order_acquire);
    // Cheap skip of entries of live Readers (one fcntl instead of two).
    if (sub_state(w) != kSubFree && locked_by_other(lock, kEntryLockBase + i)) continue;
    // Lock cases: acquired => no live process owns or is changing entry i; else skip it.
    if (!try_lock(lock, kEntryLockBase + i)) continue;
    w = e.state.load(std::memory_order_acquire);
    clear_dead_entry(seg, e);  // whatever a dead owner or a killed reclaimer left
    e.drops.store(0, std::memory_order_relaxed);
    e.next.store(0, std::memory_order_relaxed);
    e.pid.store(pid, std::memory_order_relaxed);
    // Raise the high-water mark (seq_cst) before any pin can be stored: the writer loads it
    // after its kSlotWriting store, so it scans every entry that can hold a pin it must see.
    auto& hw = seg.hdr->sub_high_water;
    std::uint32_t cur = hw.load(std::memory_order_seq_cst);
    // CAS cases: cur >= i+1 => done; else retry with the reloaded value.
    while (cur < i + 1 && !hw.compare_exchange_weak(cur, i + 1, std::memory_order_seq_cst)) {
    }
    const std::uint32_t mine = sub_word(sub_epoch(w) + 1, kSubActive);
    // CAS cases: success => ours with a fresh epoch; failure => the word was changed by a
    // process not following the lock protocol (hostile): give the entry up.
    if (!e.state.compare_exchange_strong(w, mine, std::memory_order_seq_cst)) {
      unlock(lock, kEntryLockBase + i);
      continue;
    }
    return {i, mine};  // the lock stays held until deregister (or our death)
  }
  throw Error(Errc::no_subscriber_slot, "segment " + seg.name + ": subscriber table full");
}

void deregister_subscriber(const Segment& seg, std::uint32_t entry, int lock) noexcept {
  auto& e = seg.sub(entry);
  // Release: our reads of pinned payloads happen-before the writer reuses those slots.
  for (auto& p : e.pins) p.store(kPinFree, std::memory_order_release);
  e.pid.store(0, std::memory_order_relaxed);
  std::uint32_t w = e.state.load(std::memory_order_relaxed);
  if (sub_state(w) != kSubFree) {
    e.state.compare_exchange_strong(w, sub_word(sub_epoch(w) + 1, kSubFree),
                                    std::memory_order_release);
  }
  unlock(lock, kEntryLockBase + entry);
}

// ---- a departed Writer's generations ----

bool has_live_subscriber(const Segment& seg) noexcept {
  const std::uint32_t hw =
      std::min(seg.hdr->sub_high_water.load(std::memory_order_seq_cst), seg.geo.max_subscribers);
  for (std::uint32_t i = 0; i < hw; ++i) {
    if (subscriber_alive(seg, i)) return true;
  }
  return false;
}

std::size_t release_unneeded_generations(const std::string& base,
                                         std::uint64_t caller_gen) noexcept {
  std::size_t removed = 0;
  try {
    std::map<std::uint64_t, std::string> names;
    for (const auto& n : list_shm(base + "_g")) {
      auto sg = split_generation(n);
      if (sg && sg->first == base) names.emplace(sg->second, n);
    }
    // The oldest generation a live Reader is registered in (the caller's own counts even if
    // its name is gone). Only a cleanly closed Writer leaves generations for lagging
    // Readers; a crashed one's files all go (Readers that mapped them keep their mapping).
    std::uint64_t oldest = caller_gen;
    std::vector<std::pair<std::uint64_t, std::string>> ours;
    for (const auto& [gen, name] : names) {
      std::unique_ptr<Segment> seg;
      try {
        seg = open_segment(name);
      } catch (const Error&) {
        continue;  // foreign, corrupt or untrusted: left alone (reclaim warns)
      }
      if (seg->generation != gen) continue;
      if (locked_by_other(seg->lock.get(), kWriterLockByte)) {
        return removed;  // a live Writer owns this base (again): not ours to clean
      }
      const bool closed = seg->hdr->writer_closed.load(std::memory_order_acquire) != 0;
      if (closed && gen < oldest && has_live_subscriber(*seg)) oldest = gen;
      ours.emplace_back(gen, name);
    }
    // Generations below the oldest Reader are needed by nobody; from it on they are needed
    // to follow, as long as there is something newer than it to follow to.
    const bool keep_tail = !ours.empty() && ours.back().first > oldest;
    for (const auto& [gen, name] : ours) {
      if (gen >= oldest && keep_tail) break;
      if (unlink_segment(name)) ++removed;
    }
  } catch (...) {  // allocation: leave the rest to a later pass
  }
  return removed;
}

}  // namespace lcmx::shm::detail
