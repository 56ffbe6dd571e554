#pragma once
// Private: LC03 fragment reassembly with bounded memory. Single-threaded.

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

  // Drops partial messages idle for longer than the timeout.
  void expire(Clock::time_point now);

  const Stats& stats() const noexcept { return stats_; }
  std::size_t partial_count() const noexcept { return partials_.size(); }
  std::size_t reserved_bytes() const noexcept { return reserved_; }

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
    Clock::time_point last{};
  };

  void erase(std::unordered_map<Key, Partial, KeyHash>::iterator it);
  bool evict_oldest();

  Limits limits_;
  Stats stats_;
  std::unordered_map<Key, Partial, KeyHash> partials_;
  std::size_t reserved_ = 0;
};

}  // namespace lcmx::udpm::detail
