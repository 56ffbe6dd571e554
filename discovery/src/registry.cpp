// The host registry (registry_impl.hpp, docs/discovery.md "Registry").
#include <dirent.h>
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <random>
#include <sstream>
#include <stdexcept>
#include <thread>

#include <spdlog/spdlog.h>

#include "lcmx/discovery/identity.hpp"
#include "lcmx/shm/futex.hpp"
#include "lcmx/shm/segment.hpp"
#include "registry_impl.hpp"
#include "vehicle_table.hpp"

namespace lcmx::discovery {
namespace reg {

std::uint64_t fnv1a(std::span<const std::byte> bytes, std::uint64_t h) {
  for (auto b : bytes) {
    h ^= static_cast<std::uint8_t>(b);
    h *= 1099511628211ull;
  }
  return h;
}

namespace {
std::uint64_t fnv_str(const std::string& s, std::uint64_t h = 1469598103934665603ull) {
  return fnv1a(std::as_bytes(std::span(s.data(), s.size())), h);
}
}  // namespace

std::uint64_t group_hash(const udpm::GroupConfig& g) {
  return fnv_str(g.address + ":" + std::to_string(g.port));
}

std::int64_t now_ns() {
  timespec ts{};
  ::clock_gettime(CLOCK_MONOTONIC, &ts);
  return std::int64_t{ts.tv_sec} * 1000000000 + ts.tv_nsec;
}

TopicBits topic_bits(const std::string& topic) {
  const auto h = fnv_str(topic);
  TopicBits b{};
  for (int k = 0; k < 3; ++k) b.bit[k] = static_cast<std::uint16_t>((h >> (k * 10)) & 1023);
  return b;
}

void TopicFilter::add(const std::string& topic) {
  for (auto bit : topic_bits(topic).bit) w[bit / 64] |= std::uint64_t{1} << (bit % 64);
}

bool TopicFilter::may_hold(const std::string& topic) const {
  const auto h = fnv_str(topic);
  for (int k = 0; k < 3; ++k) {
    const auto bit = (h >> (k * 10)) & 1023;
    if (!(w[bit / 64] & (std::uint64_t{1} << (bit % 64)))) return false;
  }
  return true;
}

bool TopicFilter::intersects_names(const std::vector<std::string>& topics) const {
  for (const auto& t : topics)
    if (may_hold(t)) return true;
  return false;
}

}  // namespace reg

namespace {

std::string hex(std::uint64_t v) {
  std::ostringstream s;
  s << std::hex << v;
  return s.str();
}

[[noreturn]] void fail(const std::string& what) {
  throw std::runtime_error("lcmx discovery registry: " + what + ": " + std::strerror(errno));
}

bool lock_byte(int fd, off_t byte, short type, bool wait) {
  struct flock fl{};
  fl.l_type = type;
  fl.l_whence = SEEK_SET;
  fl.l_start = byte;
  fl.l_len = 1;
  for (;;) {
    if (::fcntl(fd, wait ? F_OFD_SETLKW : F_OFD_SETLK, &fl) == 0) return true;
    if (errno == EINTR) continue;
    return false;
  }
}

// Held: someone else holds a write lock on the byte.
bool byte_held(int fd, off_t byte) {
  struct flock fl{};
  fl.l_type = F_WRLCK;
  fl.l_whence = SEEK_SET;
  fl.l_start = byte;
  fl.l_len = 1;
  if (::fcntl(fd, F_OFD_GETLK, &fl) != 0) return true;  // cannot tell: alive
  return fl.l_type != F_UNLCK;
}

void sweep(const std::string& directory, const std::string& self);

std::size_t file_size(std::uint32_t slots) {
  return sizeof(reg::Header) + std::size_t{slots} * sizeof(reg::Slot) + reg::kLogSize * sizeof(std::uint64_t) +
         reg::kBuckets * sizeof(std::uint32_t);
}

}  // namespace

std::string Registry::path_for(std::uint64_t host_id, const udpm::GroupConfig& group, const std::string& directory) {
  return directory + "/lcmxreg_" + hex(host_id) + "_" + hex(reg::group_hash(group));
}

Registry::Registry(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Registry::~Registry() = default;
const std::string& Registry::path() const { return impl_->path; }
std::uint64_t Registry::host_id() const { return impl_->header->host_id; }
bool Registry::created() const { return impl_->created; }
std::uint32_t Registry::slots() const { return impl_->slot_count; }

std::uint32_t Registry::occupied() const {
  std::uint32_t n = 0;
  const auto hw = std::min(impl_->header->high_water.load(std::memory_order_acquire), impl_->slot_count);
  for (std::uint32_t i = 0; i < hw; ++i) {
    const auto s = reg::state_of(impl_->slots[i].state.load(std::memory_order_acquire));
    if (s != reg::kFree) ++n;
  }
  return n;
}

std::shared_ptr<Registry> Registry::open(const RegistryOptions& o) {
  auto impl = std::make_unique<Impl>();
  impl->options = o;
  if (impl->options.host_id == 0) impl->options.host_id = discovery::host_id();
  const auto slots = std::clamp<std::uint32_t>(o.slots, 2, 65536);
  impl->path = path_for(impl->options.host_id, o.group, o.directory);
  const auto ghash = reg::group_hash(o.group);
  for (int attempt = 0;; ++attempt) {
    if (attempt == 5) throw std::runtime_error("lcmx discovery registry: " + impl->path + " keeps being removed");
    const int fd = ::open(impl->path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC | O_NOFOLLOW, 0600);
    if (fd < 0) fail("cannot open " + impl->path + " (another user's registry not shared read-write?)");
    // A user (read lock, held until we close): whoever removes the file must get the write
    // lock first, so it cannot remove it under us; if it did just before, we open a new one.
    if (!lock_byte(fd, reg::kLockUsers, F_RDLCK, true)) {
      ::close(fd);
      fail("cannot lock " + impl->path);
    }
    struct stat st{};
    if (::fstat(fd, &st) != 0) fail("fstat " + impl->path);
    if (st.st_nlink == 0) {  // removed by its last user between our open and lock
      ::close(fd);
      continue;
    }
    // Initialisation under the init lock: a creator that died half-way leaves version 0 (or a
    // short file), and the next one initialises it again.
    if (!lock_byte(fd, reg::kLockInit, F_WRLCK, true)) {
      ::close(fd);
      fail("cannot lock " + impl->path);
    }
    // Its size again, under the init lock: the size read before it may be from before another
    // process initialised the file, and initialising it again (ftruncate to 0) would take the
    // pages from under that process's mapping (SIGBUS).
    if (::fstat(fd, &st) != 0) fail("fstat " + impl->path);
    if (!S_ISREG(st.st_mode)) {
      ::close(fd);
      throw std::runtime_error("lcmx discovery registry: " + impl->path + " is not a regular file");
    }
    bool init = static_cast<std::size_t>(st.st_size) < sizeof(reg::Header);
    std::uint32_t count = slots;
    if (!init) {
      reg::Header h{};
      if (::pread(fd, &h, sizeof h, 0) != static_cast<ssize_t>(sizeof h)) fail("read " + impl->path);
      const auto version = h.version.load();
      if (version == 0) {
        init = true;  // a creator died half-way
      } else if (version != reg::kVersion || h.header_size != sizeof(reg::Header) ||
                 h.slot_size != sizeof(reg::Slot) || h.slot_count < 2 || h.slot_count > 65536 ||
                 h.log_size != reg::kLogSize ||
                 h.host_id != impl->options.host_id || h.group_hash != ghash ||
                 static_cast<std::size_t>(st.st_size) < file_size(h.slot_count)) {
        ::close(fd);
        throw std::runtime_error("lcmx discovery registry: " + impl->path +
                                 " is not a registry of this version, host and group (remove it if no "
                                 "lcmx process of this host runs)");
      } else {
        count = h.slot_count;
      }
    }
    if (init) {
      if (st.st_uid == ::geteuid()) ::fchmod(fd, 0666);  // several users share it (umask aside)
      if (::ftruncate(fd, 0) != 0) fail("truncate " + impl->path);
      const int r = ::posix_fallocate(fd, 0, static_cast<off_t>(file_size(count)));
      if (r != 0) {
        errno = r;
        ::close(fd);
        fail("cannot size " + impl->path + " (/dev/shm full?)");
      }
    }
    const auto size = file_size(count);
    void* p = ::mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    if (p == MAP_FAILED) fail("mmap " + impl->path);
    impl->fd = fd;
    impl->size = size;
    impl->header = static_cast<reg::Header*>(p);
    impl->slots = reinterpret_cast<reg::Slot*>(static_cast<char*>(p) + sizeof(reg::Header));
    impl->slot_count = count;
    impl->log = reinterpret_cast<std::atomic<std::uint64_t>*>(static_cast<char*>(p) + sizeof(reg::Header) +
                                                              std::size_t{count} * sizeof(reg::Slot));
    impl->buckets = reinterpret_cast<std::atomic<std::uint32_t>*>(impl->log + reg::kLogSize);
    if (init) {
      auto* h = impl->header;
      h->header_size = sizeof(reg::Header);
      h->slot_count = count;
      h->slot_size = sizeof(reg::Slot);
      h->host_id = impl->options.host_id;
      h->group_hash = ghash;
      h->registry_id = random_participant_id();
      h->log_size = reg::kLogSize;
      // An entry that names position 0 for slot 0 would be taken as written: mark all unwritten.
      for (std::uint32_t k = 0; k < reg::kLogSize; ++k) impl->log[k].store(~0ull, std::memory_order_relaxed);
      // version last: a reader that sees it sees the fields above (release; paired with the
      // acquire load in a later open(), which runs under the init lock anyway).
      h->version.store(reg::kVersion, std::memory_order_release);
    }
    lock_byte(fd, reg::kLockInit, F_UNLCK, false);
    if (init) sweep(o.directory, impl->path);  // leftovers of killed processes
    impl->created = init;
    break;
  }
  return std::shared_ptr<Registry>(new Registry(std::move(impl)));
}

Registry::Impl::~Impl() {
  if (own >= 0) {
    members = 1;
    leave();
  } else if (fd >= 0) {
    remove_if_unused();
  }
  if (header) ::munmap(header, size);
  if (fd >= 0) ::close(fd);
}

std::string Registry::Impl::state_path_for(std::int64_t participant) const {
  return path + "_p" + hex(static_cast<std::uint64_t>(participant));
}

void Registry::Impl::join(std::int64_t participant, std::int32_t lease_ms, std::int32_t period_ms) {
  std::lock_guard lock(mutex);
  ++members;
  if (own >= 0) return;
  own_id = participant;
  state_path = state_path_for(participant);
  state_fd = ::open(state_path.c_str(), O_RDWR | O_CREAT | O_EXCL | O_CLOEXEC | O_NOFOLLOW, 0644);
  if (state_fd < 0) fail("cannot create " + state_path);
  ::fchmod(state_fd, 0644);
  for (std::uint32_t i = 0; i < slot_count; ++i) {
    auto& s = slots[i];
    auto cur = s.state.load(std::memory_order_acquire);
    if (reg::state_of(cur) != reg::kFree) continue;
    // CAS kFree(e) -> kClaimed(e). Fails: someone else claimed it (or it changed): next slot.
    // Success (acq_rel): the fields below are ours until kLive is stored.
    if (!s.state.compare_exchange_strong(cur, reg::make_state(reg::epoch_of(cur), reg::kClaimed),
                                         std::memory_order_acq_rel))
      continue;
    s.participant_id.store(participant, std::memory_order_relaxed);
    s.revision.store(0, std::memory_order_relaxed);
    s.seq.store(0, std::memory_order_relaxed);
    s.stats_seq.store(0, std::memory_order_relaxed);
    s.heartbeat_ns.store(reg::now_ns(), std::memory_order_relaxed);
    s.pid.store(static_cast<std::int32_t>(::getpid()), std::memory_order_relaxed);
    s.lease_ms.store(lease_ms, std::memory_order_relaxed);
    s.start_time.store(static_cast<std::int64_t>(process_start_time(static_cast<int>(::getpid()))),
                       std::memory_order_relaxed);
    s.pid_namespace.store(pid_namespace(), std::memory_order_relaxed);
    s.uid.store(::geteuid(), std::memory_order_relaxed);
    s.flags.store(0, std::memory_order_relaxed);
    s.vehicle_group.store(0, std::memory_order_relaxed);
    s.period_ms.store(static_cast<std::uint32_t>(std::max(period_ms, 1)), std::memory_order_relaxed);
    for (auto& w : s.topics) w.store(0, std::memory_order_relaxed);
    // Liveness: the kernel drops this lock when we die (any pid namespace).
    if (!lock_byte(fd, reg::kLockSlots + static_cast<off_t>(i), F_WRLCK, false)) {
      // Held: a previous owner's process still runs (cannot happen for a freed slot unless
      // it was freed wrongly): give the slot back and try the next.
      s.state.store(cur, std::memory_order_release);
      continue;
    }
    own = static_cast<int>(i);
    // high_water: max (relaxed CAS loop; published by the release below).
    auto hw = header->high_water.load(std::memory_order_relaxed);
    while (hw < i + 1 && !header->high_water.compare_exchange_weak(hw, i + 1, std::memory_order_relaxed)) {
    }
    // kLive (release): pairs with readers' acquire load of `state`.
    s.state.store(reg::make_state(reg::epoch_of(cur), reg::kLive), std::memory_order_release);
    bump_changes(i);
    return;
  }
  ::close(state_fd);
  ::unlink(state_path.c_str());
  state_fd = -1;
  --members;
  throw std::runtime_error("lcmx discovery registry: " + path + " is full (" + std::to_string(slot_count) +
                           " participants on this host and group)");
}

void Registry::Impl::bump_changes(std::uint32_t i, const std::uint64_t* also) {
  if (i < slot_count) {
    const auto pos = header->log_head.fetch_add(1, std::memory_order_relaxed);
    // release: the slot's change is visible to a reader that reads this entry (acquire).
    log[pos % reg::kLogSize].store(reg::log_entry(pos, i), std::memory_order_release);
    for (std::size_t k = 0; k < reg::kTopicWords; ++k) {
      auto w = slots[i].topics[k].load(std::memory_order_relaxed) | (also ? also[k] : 0);
      while (w) {
        const auto bit = k * 64 + static_cast<std::size_t>(__builtin_ctzll(w));
        w &= w - 1;
        // release: pairs with the reader's acquire load of the word before its pass.
        buckets[bit].fetch_add(1, std::memory_order_release);
        shm::futex_wake_all(&buckets[bit]);
      }
    }
  }
  header->changes.fetch_add(1, std::memory_order_release);  // pairs with readers' acquire load
  shm::futex_wake_all(&header->changes);
}

bool Registry::Impl::publish(bool vehicle, std::vector<std::byte> bytes, std::uint64_t structural,
                             const reg::TopicFilter* topics, std::uint32_t flags, std::uint64_t vehicle_group) {
  std::lock_guard lock(mutex);
  if (own < 0) return false;
  auto& s = slots[own];
  bool bump = false;
  if (vehicle) {
    bump = structural != vehicle_struct;
    vehicle_bytes = std::move(bytes);
    vehicle_struct = structural;
  } else {
    bump = structural != host_struct;
    host_bytes = std::move(bytes);
    host_struct = structural;
  }
  std::vector<std::byte> file(sizeof(reg::StateHeader) + host_bytes.size() + vehicle_bytes.size());
  reg::StateHeader h{};
  h.version = reg::kStateVersion;
  h.host_len = static_cast<std::uint32_t>(host_bytes.size());
  h.vehicle_len = static_cast<std::uint32_t>(vehicle_bytes.size());
  h.host_struct = host_struct;
  h.vehicle_struct = vehicle_struct;
  // (an empty section has no data(): memcpy must not be given it, even for 0 bytes)
  if (!host_bytes.empty()) std::memcpy(file.data() + sizeof h, host_bytes.data(), host_bytes.size());
  if (!vehicle_bytes.empty())
    std::memcpy(file.data() + sizeof h + host_bytes.size(), vehicle_bytes.data(), vehicle_bytes.size());
  h.checksum = reg::fnv1a(std::span(file).subspan(sizeof h));
  const auto rev = s.revision.load(std::memory_order_relaxed) + (bump ? 1 : 0);
  h.revision = rev;
  std::memcpy(file.data(), &h, sizeof h);
  // Seqlock: odd while writing. The release fence after the odd store keeps the writes below
  // after it; readers pair it with an acquire fence before re-reading seq.
  const auto seq = s.seq.load(std::memory_order_relaxed);
  s.seq.store(seq + 1, std::memory_order_relaxed);
  std::atomic_thread_fence(std::memory_order_release);
  bool ok = ::pwrite(state_fd, file.data(), file.size(), 0) == static_cast<ssize_t>(file.size());
  if (ok) ok = ::ftruncate(state_fd, static_cast<off_t>(file.size())) == 0;
  std::uint64_t before[reg::kTopicWords];
  for (std::size_t k = 0; k < reg::kTopicWords; ++k) before[k] = s.topics[k].load(std::memory_order_relaxed);
  if (topics && !vehicle)
    for (std::size_t k = 0; k < reg::kTopicWords; ++k) s.topics[k].store(topics->w[k], std::memory_order_relaxed);
  if (!vehicle) {
    const auto keep = s.flags.load(std::memory_order_relaxed) & ~0xffffu;
    s.flags.store(keep | (flags & 0xffffu), std::memory_order_relaxed);
  } else {
    s.vehicle_group.store(vehicle_group, std::memory_order_relaxed);
  }
  if (bump) s.revision.store(rev, std::memory_order_relaxed);
  else s.stats_seq.fetch_add(1, std::memory_order_relaxed);
  s.seq.store(seq + 2, std::memory_order_release);  // even: pairs with readers' acquire load
  if (!ok) spdlog::warn("lcmx discovery: cannot write {}: {}", state_path, std::strerror(errno));
  if (bump) bump_changes(static_cast<std::uint32_t>(own), before);
  return bump;
}

void Registry::Impl::heartbeat() {
  if (own >= 0) slots[own].heartbeat_ns.store(reg::now_ns(), std::memory_order_relaxed);
}

void Registry::Impl::leave() {
  std::lock_guard lock(mutex);
  if (own < 0 || --members > 0) return;
  auto& s = slots[own];
  ::unlink(state_path.c_str());
  if (state_fd >= 0) ::close(state_fd), state_fd = -1;
  const auto cur = s.state.load(std::memory_order_acquire);
  // kFree with the next epoch (release): readers see the slot left.
  s.state.store(reg::make_state(reg::epoch_of(cur) + 1, reg::kFree), std::memory_order_release);
  lock_byte(fd, reg::kLockSlots + own, F_UNLCK, false);
  bump_changes(static_cast<std::uint32_t>(own));
  own = -1;
  remove_if_unused();  // the last one out
}

namespace {
// Removes `path` and its state files if no one has it open (a write lock on kLockUsers through
// `fd`, which may hold a read lock itself: upgraded, then back to read). Never blocks.
bool remove_unused(int fd, const std::string& path, bool keep_read_lock) {
  if (!lock_byte(fd, reg::kLockUsers, F_WRLCK, false)) return false;
  ::unlink(path.c_str());
  const auto slash = path.rfind('/');
  const auto dir = path.substr(0, slash), base = path.substr(slash + 1) + "_p";
  if (DIR* d = ::opendir(dir.c_str())) {
    while (auto* e = ::readdir(d)) {
      const std::string name = e->d_name;
      if (name.rfind(base, 0) == 0) ::unlink((dir + "/" + name).c_str());
    }
    ::closedir(d);
  }
  lock_byte(fd, reg::kLockUsers, keep_read_lock ? F_RDLCK : F_UNLCK, false);
  return true;
}

// Registries of this directory that no one has open any more (their processes were killed),
// and state files whose registry is gone: removed. Run when a registry is created (rare).
void sweep(const std::string& directory, const std::string& self) {
  DIR* d = ::opendir(directory.c_str());
  if (!d) return;
  std::vector<std::string> registries, states;
  while (auto* e = ::readdir(d)) {
    const std::string name = e->d_name;
    if (name.rfind("lcmxreg_", 0) != 0) continue;
    (name.find("_p") == std::string::npos ? registries : states).push_back(name);
  }
  ::closedir(d);
  for (const auto& r : registries) {
    const auto path = directory + "/" + r;
    if (path == self) continue;
    const int fd = ::open(path.c_str(), O_RDWR | O_CLOEXEC | O_NOFOLLOW);
    if (fd < 0) continue;
    remove_unused(fd, path, false);
    ::close(fd);
  }
  for (const auto& st : states) {
    const auto base = st.substr(0, st.rfind("_p"));
    struct stat sb{};
    if (::stat((directory + "/" + base).c_str(), &sb) != 0 && errno == ENOENT) ::unlink((directory + "/" + st).c_str());
  }
}
}  // namespace

bool Registry::Impl::remove_if_unused() { return remove_unused(fd, path, true); }

std::optional<reg::State> Registry::Impl::read_state(std::uint32_t i, std::int64_t participant,
                                                     std::uint64_t seq) const {
  if (i >= slot_count || (seq & 1)) return std::nullopt;
  const auto& s = slots[i];
  const int f = ::open(state_path_for(participant).c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW);
  if (f < 0) return std::nullopt;
  struct stat st{};
  std::vector<std::byte> buf;
  bool ok = ::fstat(f, &st) == 0 && S_ISREG(st.st_mode) && (st.st_mode & 022) == 0 &&
            st.st_uid == s.uid.load(std::memory_order_relaxed) && st.st_size >= 64 &&
            st.st_size <= reg::kMaxStateBytes;
  if (ok) {
    buf.resize(static_cast<std::size_t>(st.st_size));
    ok = ::pread(f, buf.data(), buf.size(), 0) == static_cast<ssize_t>(buf.size());
  }
  ::close(f);
  // Acquire fence: pairs with the writer's release fence after its odd store; a writer that
  // started meanwhile has changed seq.
  std::atomic_thread_fence(std::memory_order_acquire);
  if (!ok || s.seq.load(std::memory_order_relaxed) != seq) return std::nullopt;
  reg::StateHeader h{};
  std::memcpy(&h, buf.data(), sizeof h);
  if (h.version != reg::kStateVersion || std::size_t{h.host_len} + h.vehicle_len != buf.size() - sizeof h ||
      h.checksum != reg::fnv1a(std::span(buf).subspan(sizeof h)))
    return std::nullopt;
  reg::State out;
  out.host.assign(buf.begin() + sizeof h, buf.begin() + sizeof h + h.host_len);
  out.vehicle.assign(buf.begin() + sizeof h + h.host_len, buf.end());
  out.host_struct = h.host_struct;
  out.vehicle_struct = h.vehicle_struct;
  out.revision = h.revision;
  return out;
}

std::string Registry::Impl::table_path_for(std::uint64_t vehicle_group) const { return path + "_pv" + hex(vehicle_group); }

bool Registry::Impl::write_table(std::uint64_t vehicle_group, std::span<const std::byte> bytes) const {
  const auto target = table_path_for(vehicle_group);
  const auto tmp = target + "w" + std::to_string(::getpid());
  const int f = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0644);
  if (f < 0) return false;
  bool ok = ::fchmod(f, 0644) == 0;  // (whatever the umask)
  std::size_t done = 0;
  while (ok && done < bytes.size()) {
    const auto n = ::write(f, bytes.data() + done, bytes.size() - done);
    if (n < 0 && errno == EINTR) continue;
    ok = n > 0;
    if (ok) done += static_cast<std::size_t>(n);
  }
  ::close(f);
  if (ok) ok = ::rename(tmp.c_str(), target.c_str()) == 0;
  if (!ok) {
    const int err = errno;
    ::unlink(tmp.c_str());
    errno = err;
    return false;
  }
  header->vehicle_changes.fetch_add(1, std::memory_order_release);  // pairs with the followers' acquire load
  shm::futex_wake_all(&header->vehicle_changes);
  return true;
}

bool Registry::Impl::patch_table_time(std::uint64_t vehicle_group, std::int64_t written_ns) const {
  const int f = ::open(table_path_for(vehicle_group).c_str(), O_WRONLY | O_CLOEXEC | O_NOFOLLOW);
  if (f < 0) return false;
  const bool ok = ::pwrite(f, &written_ns, sizeof written_ns, offsetof(table::Header, written_ns)) == static_cast<ssize_t>(sizeof written_ns);
  ::close(f);
  return ok;
}

bool Registry::Impl::owner_alive(std::uint32_t i) const {
  return i < slot_count && byte_held(fd, reg::kLockSlots + static_cast<off_t>(i));
}

bool Registry::Impl::try_lock(off_t byte) { return lock_byte(fd, byte, F_WRLCK, false); }
void Registry::Impl::unlock(off_t byte) { lock_byte(fd, byte, F_UNLCK, false); }

void Registry::Impl::reclaim(std::uint32_t i, std::uint64_t seen) {
  if (i >= slot_count) return;
  auto& s = slots[i];
  const auto participant = s.participant_id.load(std::memory_order_relaxed);
  const auto pid = s.pid.load(std::memory_order_relaxed);
  const auto pidns = s.pid_namespace.load(std::memory_order_relaxed);
  // kDead (CAS from what the caller saw: a slot that changed meanwhile is left alone).
  if (!s.state.compare_exchange_strong(seen, reg::make_state(reg::epoch_of(seen), reg::kDead),
                                       std::memory_order_acq_rel))
    return;
  bump_changes(i);
  ::unlink(state_path_for(participant).c_str());
  // Its shared memory: only its own segments, by name (core's shm_base_prefix).
  if (pid > 0) {
    const auto prefix = std::string(shm::kPrefix) + hex(header->host_id) + "_" + std::to_string(pid) + "n" +
                        hex(pidns) + "_";
    const auto r = shm::reclaim_orphans(prefix);
    if (r.removed > 0) spdlog::info("lcmx discovery: removed {} shared-memory segments of pid {}", r.removed, pid);
  }
  auto dead = reg::make_state(reg::epoch_of(seen), reg::kDead);
  // epoch + 2: a reader that missed kDead still tells a death from a goodbye (epoch + 1).
  s.state.compare_exchange_strong(dead, reg::make_state(reg::epoch_of(seen) + 2, reg::kFree),
                                  std::memory_order_acq_rel);
  bump_changes(i);
}

void Registry::remove(std::uint64_t host_id, const udpm::GroupConfig& group, const std::string& directory) {
  const auto path = path_for(host_id, group, directory);
  ::unlink(path.c_str());
  const auto base = path.substr(directory.size() + 1) + "_p";
  if (DIR* d = ::opendir(directory.c_str())) {
    while (auto* e = ::readdir(d)) {
      const std::string name = e->d_name;
      if (name.rfind(base, 0) == 0) ::unlink((directory + "/" + name).c_str());
    }
    ::closedir(d);
  }
}

}  // namespace lcmx::discovery
