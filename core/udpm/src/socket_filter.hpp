// Private: a ReceiveFilter (lcmx/udpm/filter.hpp) as the rule drain() applies in user space
// (FilterRule), and as the classic BPF program the receive socket runs in the kernel
// (socket_program). group.cpp owns when they change; unit tests reach both.
#pragma once

#include <linux/filter.h>

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "lcmx/udpm/filter.hpp"
#include "lcmx/udpm/source.hpp"

namespace lcmx::udpm::detail {

// Throws Error(invalid_config) naming the bad part: a channel or the control channel that is
// not a valid channel name (wire.hpp), a mark_prefix longer than kMaxMarkPrefix.
void check_filter(const ReceiveFilter& f);

// The user-space rule of a checked ReceiveFilter. Immutable; not synchronised (the receive
// thread's).
class FilterRule {
 public:
  FilterRule() = default;  // takes everything
  explicit FilterRule(const ReceiveFilter& f);

  // True when it takes every datagram.
  bool everything() const noexcept { return everything_; }
  // Whether it takes a message of `channel` from `source` whose payload starts with `payload`
  // (the whole payload, or at least its first kMaxMarkPrefix bytes and, with mark_channel_at,
  // the mark's channel name).
  bool takes(std::string_view channel, std::span<const std::byte> payload, const Source& source) const noexcept;

 private:
  bool everything_ = true;
  bool all_channels_ = true;
  std::vector<std::string> channels_;  // sorted, unique (all_channels_ false)
  std::string control_;
  bool control_all_ = true;
  std::vector<std::byte> prefix_;
  std::optional<std::size_t> mark_channel_at_;
  bool any_source_ = true;
  std::vector<Source> sources_;
};

// What the kernel program does besides the filter.
struct ProgramSpec {
  // The own-datagram drop (GroupConfig::receive_own false): datagrams from port own_port_be and
  // one of own_addresses (network order; the first 16).
  bool drop_own = false;
  std::uint16_t own_port_be = 0;
  std::vector<std::uint32_t> own_addresses;
  // Keyed groups: the ids of the group's keys. Unkeyed: nullopt.
  std::optional<std::vector<std::uint32_t>> key_ids;
};

// How much of the filter a program holds, most first; each drops a subset of what the one
// before drops (filter.hpp "The kernel program").
enum class KernelPart : std::uint8_t {
  whole,            // the whole rule
  without_channels, // every channel but the control channel taken; the control rule whole
  without_sources,  // every channel taken; of the control channel only marks (any source)
  own_only,         // the own-datagram drop alone (or nothing)
};

inline constexpr std::size_t kMaxInstructions = BPF_MAXINSNS;  // 4096

// The program for `part` of filter `f`, or nullopt when it does not fit classic BPF (more than
// kMaxInstructions, or a conditional jump farther than 255). An empty program means "attach
// none": nothing to drop. own_only always fits.
std::optional<std::vector<sock_filter>> socket_program(const ProgramSpec& spec, const ReceiveFilter& f,
                                                       KernelPart part);

}  // namespace lcmx::udpm::detail
