#pragma once
// lcmx::udpm::Source — a datagram's sender (group.hpp, filter.hpp).

#include <cstdint>
#include <string>

namespace lcmx::udpm {

// A sender's IPv4 address and UDP port, both in network byte order.
struct Source {
  std::uint32_t address_be;
  std::uint16_t port_be;
  friend bool operator==(const Source&, const Source&) = default;
};
std::string to_string(const Source& source);  // "a.b.c.d:port"

}  // namespace lcmx::udpm
