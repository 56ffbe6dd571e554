// libFuzzer target: the keyed envelope (core/udpm/src/envelope.cpp, docs/keyed-groups.md).
//
// Input: byte 0 = flags (bit 0: encrypt, bit 1: the opener holds the second key only, bits 2..7:
// how many bytes to change), byte 1.. = an LCM datagram to seal (or, with flags bit 1 and
// nothing sealed, a datagram to open as it is).
// Checks, for every input:
//  - Opener::open never reads outside the datagram (ASan) and refuses the raw input unless it
//    is an envelope that verifies (which random bytes never are: it must not accept);
//  - sealing the input and opening it gives back exactly the input, once (a second open is
//    refused as a replay);
//  - the same envelope with any byte changed is refused, and the window is not moved by it
//    (the original still opens afterwards in a fresh opener... and a changed copy never does);
//  - an envelope sealed with a key the opener does not hold is refused as unknown_key.
// A failed check prints what failed and aborts, which libFuzzer reports as a crash.

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <vector>

#include "../../core/udpm/src/envelope.hpp"  // private header: reached by path on purpose

namespace {

#define FUZZ_CHECK(cond)                                                                 \
  do {                                                                                   \
    if (!(cond)) {                                                                       \
      std::fprintf(stderr, "fuzz_udpm_envelope: check failed: %s (%s:%d)\n", #cond,     \
                   __FILE__, __LINE__);                                                  \
      std::abort();                                                                      \
    }                                                                                    \
  } while (0)

using namespace lcmx::udpm;

GroupKeys keys_with(std::uint8_t fill, std::uint32_t id, bool encrypt) {
  GroupKeys k;
  GroupKey key;
  for (std::size_t i = 0; i < key.bytes.size(); ++i) key.bytes[i] = static_cast<std::uint8_t>(fill + i * 7);
  key.id = id;
  k.keys.push_back(key);
  k.encrypt = encrypt;
  return k;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  const std::uint8_t flags = data[0];
  const bool encrypt = (flags & 1) != 0;
  const std::size_t changes = flags >> 2;
  const std::uint8_t* inner = data + 1;
  const std::size_t inner_size = size - 1;
  static const GroupKeys a_auth = keys_with(1, 0x11111111, false), a_crypt = keys_with(1, 0x11111111, true);
  static const GroupKeys b = keys_with(2, 0x22222222, false);
  const GroupKeys& a = encrypt ? a_crypt : a_auth;

  // The raw input, as a datagram from the network.
  {
    std::vector<std::byte> raw(reinterpret_cast<const std::byte*>(inner), reinterpret_cast<const std::byte*>(inner) + inner_size);
    detail::Opener o;
    FUZZ_CHECK(o.open(a, raw).refused.has_value());
  }

  // Seal, open once, refuse a replay.
  static detail::Sealer sealer;
  std::vector<std::byte> env(kEnvelopeOverhead + inner_size);
  if (inner_size > 0) std::memcpy(env.data() + kEnvelopeHeaderSize, inner, inner_size);
  FUZZ_CHECK(sealer.seal(a, env.data(), inner_size) == env.size());
  {
    auto copy = env;
    detail::Opener o;
    const auto r = o.open(a, copy);
    FUZZ_CHECK(!r.refused);
    FUZZ_CHECK(r.inner.size() == inner_size);
    FUZZ_CHECK(inner_size == 0 || std::memcmp(r.inner.data(), inner, inner_size) == 0);
    auto again = env;
    FUZZ_CHECK(o.open(a, again).refused == Refusal::replayed);
    auto other = env;
    FUZZ_CHECK(detail::Opener().open(b, other).refused == Refusal::unknown_key);
  }
  // Changed bytes (positions and values from the input): refused, and the original still opens
  // in the same opener afterwards (a refused datagram moves no window).
  if (changes > 0) {
    auto bad = env;
    bool changed = false;
    for (std::size_t i = 0; i < changes; ++i) {
      const std::size_t at = (inner_size ? inner[i % inner_size] * 131u + i * 977u : i) % bad.size();
      const auto x = static_cast<std::byte>(1u + (i * 37u) % 255u);
      bad[at] ^= x;
      changed = true;
    }
    if (changed && bad != env) {
      detail::Opener o;
      FUZZ_CHECK(o.open(a, bad).refused.has_value());
      auto good = env;
      FUZZ_CHECK(!o.open(a, good).refused);
    }
  }
  return 0;
}
