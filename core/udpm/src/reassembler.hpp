#pragma once
// Private: LC03 fragment reassembly with bounded memory. Single-threaded.
//
// Memory: every partial message is charged its declared size plus its bookkeeping (per
// fragment: a seen flag and an extent), reserved when its first fragment arrives; the sum stays
// within Limits::max_bytes and the count within Limits::max_partials.
// Eviction, when a new partial message needs room: the source (address, port) holding the most
// partial messages gives up its oldest (ties: the one holding the most bytes). A sender flooding
// fragments of messages it never completes thus evicts its own, not other senders' messages in
// flight. Evictions are counted in Stats::incomplete_dropped.

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "lcmx/udpm/group.hpp"
#include "lcmx/udpm/wire.hpp"

namespace lcmx::udpm::detail {

class Reassembler {
 public:
  using Clock = std::chrono::steady_clock;

  struct Limits {
    std::size_t max_bytes;     // sum of declared sizes of partial messages
    std::size_t max_partials;  // number of partial messages
    Clock::duration timeout;   // since the last fragment of a partial message
  };

  struct Stats {
    std::uint64_t incomplete_dropped = 0;
    std::uint64_t malformed_dropped = 0;
    std::uint64_t duplicate_fragments = 0;
    std::uint64_t oversize_dropped = 0;
  };

  struct Complete {
    std::string channel;
    std::unique_ptr<std::byte[]> data;
    std::uint32_t size = 0;
    Source source{};
    std::uint32_t sequence = 0;
  };

  explicit Reassembler(Limits limits) : limits_(limits) {}

  // Adds one parsed LC03 fragment (d.fragment must be true). Returns the message when this
  // fragment completes it.
  std::optional<Complete> add(const ParsedDatagram& d, Source source, Clock::time_point now);

  // Drops partial messages idle for longer than the timeout, and forgets refused messages
  // (refuse()) idle as long.
  void expire(Clock::time_point now);

  // A receive filter refused the message whose fragment 0 is `d` (d.fragment, d.fragment_no 0):
  // its partial message, if fragments of it came first, is dropped without counting it
  // incomplete, and its other fragments are taken by refused() until they all came or it is
  // idle for the timeout. Returns the number of fragments dropped with the partial message.
  // Remembers at most kMaxRefused messages at once (past it the oldest is forgotten: its later
  // fragments then make a partial message that counts incomplete when it expires).
  std::size_t refuse(const ParsedDatagram& d, Source source, Clock::time_point now);
  // True, and the fragment is used up, when `d` (d.fragment) belongs to a message refuse()d.
  bool refused(const ParsedDatagram& d, Source source, Clock::time_point now);
  std::size_t refused_count() const noexcept { return refused_.size(); }
  static constexpr std::size_t kMaxRefused = 1024;

  const Stats& stats() const noexcept { return stats_; }
  std::size_t partial_count() const noexcept { return partials_.size(); }
  // Declared sizes plus bookkeeping of the partial messages (what max_bytes bounds).
  std::size_t reserved_bytes() const noexcept { return reserved_; }
  // What a partial message of `total_size` bytes in `fragment_count` fragments is charged.
  static std::size_t charge(std::uint32_t total_size, std::uint16_t fragment_count) noexcept {
    return std::size_t{total_size} + std::size_t{fragment_count} * kPerFragment;
  }

 private:
  struct Key {
    std::uint32_t address_be;
    std::uint16_t port_be;
    std::uint32_t sequence;
    friend bool operator==(const Key&, const Key&) = default;
  };
  struct KeyHash {
    std::size_t operator()(const Key& k) const noexcept {
      std::uint64_t h = (std::uint64_t{k.address_be} << 16) ^ k.port_be;
      h = h * 0x9E3779B97F4A7C15ull ^ k.sequence;
      return static_cast<std::size_t>(h * 0xBF58476D1CE4E5B9ull >> 7);
    }
  };
  struct Partial {
    std::string channel;
    std::unique_ptr<std::byte[]> data;  // total_size bytes, filled as fragments arrive
    std::vector<bool> seen;             // per fragment number
    // (offset, length) of each fragment received, to check they tile the message exactly.
    std::vector<std::pair<std::uint32_t, std::uint32_t>> extents;
    std::uint32_t total_size = 0;
    std::uint16_t fragment_count = 0;
    std::uint16_t received = 0;
    std::uint64_t bytes = 0;
    std::size_t charged = 0;  // what reserved_ holds for it
    Clock::time_point last{};
  };

  // A seen flag (vector<bool>: rounded up to a byte) and an (offset, length) extent.
  static constexpr std::size_t kPerFragment = 1 + sizeof(std::pair<std::uint32_t, std::uint32_t>);

  struct SourceUse {
    std::size_t partials = 0;
    std::size_t bytes = 0;
  };
  static std::uint64_t source_key(const Key& k) noexcept {
    return (std::uint64_t{k.address_be} << 16) | k.port_be;
  }

  void erase(std::unordered_map<Key, Partial, KeyHash>::iterator it);
  bool evict_one();

  // A refused message's fragments still to come (besides fragment 0).
  struct Refused {
    std::uint16_t left = 0;
    Clock::time_point last{};
  };

  Limits limits_;
  Stats stats_;
  std::unordered_map<Key, Partial, KeyHash> partials_;
  std::unordered_map<Key, Refused, KeyHash> refused_;
  std::unordered_map<std::uint64_t, SourceUse> sources_;  // per source with partial messages
  std::size_t reserved_ = 0;
};

}  // namespace lcmx::udpm::detail
