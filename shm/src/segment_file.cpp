// Segment files: create (O_EXCL), open + validate, names, subscriber table.
#include <dirent.h>

#include <boost/interprocess/exceptions.hpp>
#include <boost/interprocess/shared_memory_object.hpp>

#include <cerrno>
#include <cstring>

#include "impl.hpp"

namespace bip = boost::interprocess;

namespace lcmx::shm::detail {
namespace {

Error from_boost(const std::string& what, const bip::interprocess_exception& e) {
  switch (e.get_error_code()) {
    case bip::not_found_error: return Error(Errc::not_found, what + ": no such segment");
    default: return Error(Errc::system, what + ": " + e.what());
  }
}

bool is_digits(const std::string& s) {
  if (s.empty() || s.size() > 18) return false;
  for (char c : s) {
    if (c < '0' || c > '9') return false;
  }
  return true;
}

}  // namespace

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
  info.owner_pid = h->owner_pid;
  info.owner_start_time = h->owner_start_time;
  return info;
}

std::optional<HeaderInfo> peek_segment(const std::string& name, std::string* why) {
  try {
    bip::shared_memory_object shm(bip::open_only, name.c_str(), bip::read_only);
    bip::offset_t size = 0;
    if (!shm.get_size(size) || size < static_cast<bip::offset_t>(kHeaderSize)) {
      if (why) *why = "file smaller than the header";
      return std::nullopt;
    }
    bip::mapped_region r(shm, bip::read_only, 0, kHeaderSize);
    return validate_header(r.get_address(), static_cast<std::uint64_t>(size), why);
  } catch (const bip::interprocess_exception& e) {
    if (why) *why = e.what();
    return std::nullopt;
  }
}

bool unlink_segment(const std::string& name) noexcept {
  return bip::shared_memory_object::remove(name.c_str());
}

std::unique_ptr<Segment> create_segment(const std::string& name, const Geometry& geo,
                                        std::uint64_t generation, std::uint64_t first_global_seq,
                                        std::int32_t pid, std::uint64_t start_time) {
  std::optional<bip::shared_memory_object> shm;
  for (int attempt = 0; attempt < 2 && !shm; ++attempt) {
    try {
      bip::permissions perm;
      perm.set_permissions(0660);
      shm.emplace(bip::create_only, name.c_str(), bip::read_write, perm);
    } catch (const bip::interprocess_exception& e) {
      if (e.get_error_code() != bip::already_exists_error || attempt > 0) {
        throw Error(Errc::system, "create segment " + name + ": " + e.what());
      }
      std::string why;
      auto info = peek_segment(name, &why);
      if (!info || process_alive(info->owner_pid, info->owner_start_time)) {
        throw Error(Errc::system, "create segment " + name + ": already exists" +
                                      (info ? " (owner alive)" : " (" + why + ")"));
      }
      unlink_segment(name);  // stale, owner dead: remove and retry once
    }
  }
  auto seg = std::make_unique<Segment>();
  seg->name = name;
  try {
    shm->truncate(static_cast<bip::offset_t>(geo.total_size));
    seg->region = bip::mapped_region(*shm, bip::read_write, 0, geo.total_size);
  } catch (const bip::interprocess_exception& e) {
    unlink_segment(name);
    throw Error(Errc::system, "map segment " + name + ": " + e.what());
  }
  seg->geo = geo;
  seg->generation = generation;
  seg->first_global_seq = first_global_seq;
  // ftruncate zero-fills: every atomic starts at 0, which is a valid object representation.
  auto* h = static_cast<SegmentHeader*>(seg->region.get_address());
  seg->hdr = h;
  h->version = kVersion;
  h->slot_count = geo.slot_count;
  h->max_subscribers = geo.max_subscribers;
  h->slot_size = geo.slot_size;
  h->total_size = geo.total_size;
  h->generation = generation;
  h->owner_pid = pid;
  h->owner_start_time = start_time;
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
  // Publishes everything above; pairs with validate_header's magic.load(acquire).
  h->magic.store(kMagic, std::memory_order_release);
  return seg;
}

std::unique_ptr<Segment> open_segment(const std::string& name) {
  auto seg = std::make_unique<Segment>();
  seg->name = name;
  bip::offset_t size = 0;
  try {
    bip::shared_memory_object shm(bip::open_only, name.c_str(), bip::read_write);
    if (!shm.get_size(size)) throw Error(Errc::system, "fstat " + name);
    if (size < static_cast<bip::offset_t>(kHeaderSize)) {
      throw Error(Errc::corrupt, "segment " + name + ": file smaller than the header");
    }
    // Map the whole file as it is now; validate before computing any address from it.
    seg->region = bip::mapped_region(shm, bip::read_write, 0, static_cast<std::size_t>(size));
  } catch (const bip::interprocess_exception& e) {
    throw from_boost("open segment " + name, e);
  }
  std::string why;
  auto info = validate_header(seg->region.get_address(), static_cast<std::uint64_t>(size), &why);
  if (!info) throw Error(Errc::corrupt, "segment " + name + ": " + why);
  seg->geo = info->geo;
  seg->generation = info->generation;
  seg->first_global_seq = info->first_global_seq;
  seg->hdr = static_cast<SegmentHeader*>(seg->region.get_address());
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
// Entry states: Free -> Claiming (CAS, registrant) -> Active (store release)
//               Active|Claiming(pid != 0, dead) -> Reclaiming (CAS, reclaimer) -> Free
//               Active -> Free (owner deregisters; only the owner stores to its Active entry)
// pid/start_time are written only by the Claiming owner (start first, then pid release) and
// zeroed before Free, so a Claiming entry with pid == 0 is a registration in progress.

std::size_t reclaim_dead_subscribers(const Segment& seg) {
  std::size_t n = 0;
  const std::uint32_t hw =
      std::min(seg.hdr->sub_high_water.load(std::memory_order_seq_cst), seg.geo.max_subscribers);
  for (std::uint32_t i = 0; i < hw; ++i) {
    auto& e = seg.sub(i);
    std::uint32_t s = e.state.load(std::memory_order_acquire);
    if (s != kSubActive && s != kSubClaiming) continue;
    const std::int32_t pid = e.pid.load(std::memory_order_acquire);  // pairs with pid release
    if (pid == 0) continue;  // Claiming in progress
    if (process_alive(pid, e.start_time.load(std::memory_order_relaxed))) continue;
    // CAS cases: success => we alone clear it; failure => it changed (reclaimed by someone
    // else, deregistered, re-registered): leave it.
    if (!e.state.compare_exchange_strong(s, kSubReclaiming, std::memory_order_acq_rel)) continue;
    for (auto& p : e.pins) p.store(kPinFree, std::memory_order_seq_cst);
    e.pid.store(0, std::memory_order_relaxed);
    e.start_time.store(0, std::memory_order_relaxed);
    e.state.store(kSubFree, std::memory_order_release);
    ++n;
  }
  return n;
}

std::uint32_t register_subscriber(const Segment& seg, std::int32_t pid, std::uint64_t start) {
  reclaim_dead_subscribers(seg);
  for (std::uint32_t i = 0; i < seg.geo.max_subscribers; ++i) {
    auto& e = seg.sub(i);
    std::uint32_t expected = kSubFree;
    // CAS cases: success => the entry is ours; failure => in use by someone: next entry.
    if (!e.state.compare_exchange_strong(expected, kSubClaiming, std::memory_order_acq_rel)) {
      continue;
    }
    for (auto& p : e.pins) p.store(kPinFree, std::memory_order_relaxed);
    e.drops.store(0, std::memory_order_relaxed);
    e.next.store(0, std::memory_order_relaxed);
    e.start_time.store(start, std::memory_order_relaxed);
    e.pid.store(pid, std::memory_order_release);
    // Raise the high-water mark (seq_cst) before any pin can be stored: the writer loads it
    // after its kSlotWriting store, so it scans every entry that can hold a pin it must see.
    auto& hw = seg.hdr->sub_high_water;
    std::uint32_t cur = hw.load(std::memory_order_seq_cst);
    // CAS cases: cur >= i+1 => done; else retry with the reloaded value.
    while (cur < i + 1 && !hw.compare_exchange_weak(cur, i + 1, std::memory_order_seq_cst)) {
    }
    e.state.store(kSubActive, std::memory_order_release);
    return i;
  }
  throw Error(Errc::no_subscriber_slot, "segment " + seg.name + ": subscriber table full");
}

void deregister_subscriber(const Segment& seg, std::uint32_t entry) noexcept {
  auto& e = seg.sub(entry);
  // Release: our reads of pinned payloads happen-before the writer reuses those slots.
  for (auto& p : e.pins) p.store(kPinFree, std::memory_order_release);
  e.pid.store(0, std::memory_order_relaxed);
  e.start_time.store(0, std::memory_order_relaxed);
  e.state.store(kSubFree, std::memory_order_release);
}

}  // namespace lcmx::shm::detail
