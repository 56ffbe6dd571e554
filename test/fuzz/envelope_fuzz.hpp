// What the envelope fuzz targets check for one lcmx_msgs type T on hostile bytes (the checked
// decoders of lcmx/lcmtypes/envelope.hpp):
//  - a decode allocates at most 8 bytes per input byte (ASan's count of live heap bytes while
//    the decoded object lives; libFuzzer's -rss_limit_mb and malloc limit catch the rest);
//  - what it accepts is exactly lcm-gen's encoding: lcm-gen re-encodes the object to the same
//    bytes, and lcm-gen's own decode reads all of them;
//  - every truncation of an accepted input is refused.
// A failed check prints what failed and aborts (a crash for libFuzzer).
#pragma once

#include <sanitizer/allocator_interface.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <span>
#include <vector>

#include "lcmx/lcmtypes/envelope.hpp"

#define ENVELOPE_CHECK(cond)                                                                  \
  do {                                                                                        \
    if (!(cond)) {                                                                            \
      std::fprintf(stderr, "envelope fuzz: check failed: %s (%s:%d)\n", #cond, __FILE__, __LINE__); \
      std::abort();                                                                           \
    }                                                                                         \
  } while (0)

namespace envelope_fuzz {

// Live heap bytes the decoded object may hold: 8 per input byte, and slack for the fuzzer's
// own allocations on other threads (its RSS watcher).
inline std::size_t bound(std::size_t input) { return 8 * input + 4096; }

template <class T>
bool check(std::span<const std::byte> in) {
  bool ok = false;
  {
    const std::size_t before = __sanitizer_get_current_allocated_bytes();
    T m{};
    ok = lcmx::lcmtypes::decode(in, m);
    const std::size_t now = __sanitizer_get_current_allocated_bytes();
    if (now > before && now - before > bound(in.size())) {
      std::fprintf(stderr, "envelope fuzz: %s: %zu input bytes decoded into %zu heap bytes\n", T::getTypeName(),
                   in.size(), now - before);
      std::abort();
    }
    if (ok) {
      const std::vector<std::byte> again = lcmx::lcmtypes::encode(m);
      ENVELOPE_CHECK(again.size() == in.size());
      ENVELOPE_CHECK(std::equal(again.begin(), again.end(), in.begin()));
      T theirs{};
      ENVELOPE_CHECK(theirs.decode(in.data(), 0, static_cast<int>(in.size())) == static_cast<int>(in.size()));
    }
  }
  if (ok && in.size() <= 4096) {
    for (std::size_t n = 0; n < in.size(); n += 1 + n / 64) {  // every one near the start, then sparser
      T t{};
      ENVELOPE_CHECK(!lcmx::lcmtypes::decode(in.first(n), t));
    }
  }
  return ok;
}

}  // namespace envelope_fuzz
