#include "reassembler.hpp"

#include <algorithm>
#include <cstring>
#include <iterator>

namespace lcmx::udpm::detail {

void Reassembler::erase(std::unordered_map<Key, Partial, KeyHash>::iterator it) {
  reserved_ -= it->second.charged;
  const auto s = sources_.find(source_key(it->first));
  if (s != sources_.end()) {
    s->second.bytes -= it->second.charged;
    if (--s->second.partials == 0) sources_.erase(s);
  }
  partials_.erase(it);
}

bool Reassembler::evict_one() {
  if (partials_.empty()) return false;
  // The source holding the most partial messages (then the most bytes)...
  auto victim = sources_.begin();
  for (auto it = sources_.begin(); it != sources_.end(); ++it)
    if (it->second.partials > victim->second.partials ||
        (it->second.partials == victim->second.partials && it->second.bytes > victim->second.bytes))
      victim = it;
  // ...gives up its oldest.
  auto oldest = partials_.end();
  for (auto it = partials_.begin(); it != partials_.end(); ++it)
    if (source_key(it->first) == victim->first && (oldest == partials_.end() || it->second.last < oldest->second.last))
      oldest = it;
  if (oldest == partials_.end()) oldest = partials_.begin();  // unreachable: sources_ mirrors partials_
  erase(oldest);
  ++stats_.incomplete_dropped;
  return true;
}

std::optional<Reassembler::Complete> Reassembler::add(const ParsedDatagram& d, Source source,
                                                      Clock::time_point now) {
  const Key key{source.address_be, source.port_be, d.sequence};
  auto it = partials_.find(key);
  if (it == partials_.end()) {
    const std::size_t cost = charge(d.total_size, d.fragment_count);
    if (cost > limits_.max_bytes) {
      ++stats_.oversize_dropped;  // counted once per fragment: the message can never complete
      return std::nullopt;
    }
    // Make room: bounded by the number of partials.
    while (!partials_.empty() && (partials_.size() >= limits_.max_partials ||
                                  reserved_ + cost > limits_.max_bytes))
      evict_one();
    if (limits_.max_partials == 0) return std::nullopt;
    Partial p;
    // Uninitialised: pages of a large buffer are only touched as fragments fill them.
    p.data = std::make_unique_for_overwrite<std::byte[]>(d.total_size);
    p.seen.assign(d.fragment_count, false);
    p.extents.reserve(d.fragment_count);  // charged up front: never grows past it
    p.total_size = d.total_size;
    p.fragment_count = d.fragment_count;
    p.charged = cost;
    it = partials_.emplace(key, std::move(p)).first;
    reserved_ += cost;
    auto& use = sources_[source_key(key)];
    ++use.partials;
    use.bytes += cost;
  }

  Partial& p = it->second;
  if (p.total_size != d.total_size || p.fragment_count != d.fragment_count) {
    ++stats_.malformed_dropped;  // inconsistent with the fragments seen so far: ignore it
    return std::nullopt;
  }
  if (p.seen[d.fragment_no]) {
    ++stats_.duplicate_fragments;
    return std::nullopt;
  }
  p.seen[d.fragment_no] = true;
  ++p.received;
  p.last = now;
  if (d.fragment_no == 0) p.channel.assign(d.channel);
  // parse_datagram guarantees fragment_offset + payload.size() <= total_size.
  if (!d.payload.empty()) std::memcpy(p.data.get() + d.fragment_offset, d.payload.data(), d.payload.size());
  p.bytes += d.payload.size();
  p.extents.emplace_back(d.fragment_offset, static_cast<std::uint32_t>(d.payload.size()));

  if (p.received < p.fragment_count) return std::nullopt;
  // Every fragment arrived: they must tile [0, total_size) exactly, without overlaps or gaps
  // (equal byte sums are not enough: an overlap can hide a gap of the same size).
  std::sort(p.extents.begin(), p.extents.end());
  std::uint64_t end = 0;
  bool tiled = true;
  for (const auto& [offset, length] : p.extents) {
    tiled = tiled && offset == end;
    end = std::uint64_t{offset} + length;
  }
  if (!tiled || end != p.total_size || p.bytes != p.total_size) {
    ++stats_.malformed_dropped;
    erase(it);
    return std::nullopt;
  }
  Complete c;
  c.channel = std::move(p.channel);
  c.data = std::move(p.data);
  c.size = p.total_size;
  c.source = source;
  c.sequence = d.sequence;
  erase(it);
  return c;
}

std::size_t Reassembler::refuse(const ParsedDatagram& d, Source source, Clock::time_point now) {
  const Key key{source.address_be, source.port_be, d.sequence};
  std::size_t dropped = 0;
  std::size_t left = d.fragment_count - 1u;
  if (const auto it = partials_.find(key); it != partials_.end()) {
    const Partial& p = it->second;
    if (p.fragment_count == d.fragment_count && p.total_size == d.total_size && !p.seen[0]) {
      // Fragments that overtook fragment 0: the same message, dropped with it.
      dropped = p.received;
      left -= p.received;
      erase(it);
    }
  }
  if (left == 0) return dropped;
  if (refused_.size() >= kMaxRefused && !refused_.contains(key)) {
    auto oldest = refused_.begin();
    for (auto it = refused_.begin(); it != refused_.end(); ++it)
      if (it->second.last < oldest->second.last) oldest = it;
    refused_.erase(oldest);
  }
  refused_[key] = Refused{static_cast<std::uint16_t>(left), now};
  return dropped;
}

bool Reassembler::refused(const ParsedDatagram& d, Source source, Clock::time_point now) {
  if (refused_.empty()) return false;
  const auto it = refused_.find(Key{source.address_be, source.port_be, d.sequence});
  if (it == refused_.end()) return false;
  if (--it->second.left == 0) refused_.erase(it);
  else it->second.last = now;
  return true;
}

void Reassembler::expire(Clock::time_point now) {
  for (auto it = refused_.begin(); it != refused_.end();) {
    if (now - it->second.last > limits_.timeout) it = refused_.erase(it);
    else ++it;
  }
  for (auto it = partials_.begin(); it != partials_.end();) {
    if (now - it->second.last > limits_.timeout) {
      const auto next = std::next(it);
      erase(it);
      it = next;
      ++stats_.incomplete_dropped;
    } else {
      ++it;
    }
  }
}

}  // namespace lcmx::udpm::detail
