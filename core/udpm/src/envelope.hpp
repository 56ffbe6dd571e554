// The keyed envelope (lcmx/udpm/keys.hpp): sealing and opening one datagram, and the replay
// window per sender. Private to lcmx::udpm (group.cpp; unit tests reach it).
#pragma once

#include <cstddef>
#include <cstdint>
#include <array>
#include <optional>
#include <span>
#include <unordered_map>

#include "lcmx/udpm/keys.hpp"

namespace lcmx::udpm::detail {

// Starts libsodium once (sodium_init). Throws Error(system) if it cannot.
void sodium_ready();

// XChaCha20's subkey of one sender under one key: HChaCha20(key, sender id | 8 zero bytes), the
// first 16 bytes of every nonce of that sender (docs/keyed-groups.md "Wire form"). Kept so that
// each datagram costs ChaCha20-Poly1305-IETF alone (the same bytes as XChaCha20-Poly1305).
// Wiped when dropped.
class Subkey {
 public:
  Subkey() = default;
  Subkey(const Subkey&) = delete;
  Subkey& operator=(const Subkey&) = delete;
  ~Subkey();
  // The subkey for (key, sender), derived again only when either differs from the last call.
  const unsigned char* of(const GroupKey& key, std::uint64_t sender) noexcept;

 private:
  bool set_ = false;
  std::uint64_t sender_ = 0;
  std::array<std::uint8_t, kKeySize> key_{};
  unsigned char sub_[kKeySize] = {};
};

// The sending side of one Group. Not thread-safe: the Group's send mutex guards it.
class Sealer {
 public:
  Sealer();  // a random sender id; throws as sodium_ready()
  // Seals in place: `buffer` holds the LCM datagram at offset kEnvelopeHeaderSize
  // (`inner_size` bytes) and room for the tag after it; writes the header and the tag, and
  // encrypts the datagram when keys.encrypt. keys.keys must not be empty. Returns the
  // envelope's size, kEnvelopeOverhead + inner_size.
  std::size_t seal(const GroupKeys& keys, std::byte* buffer, std::size_t inner_size) noexcept;
  std::uint64_t sender_id() const noexcept { return sender_; }
  std::uint64_t counter() const noexcept { return counter_; }

 private:
  std::uint64_t sender_ = 0;
  std::uint64_t counter_ = 0;  // of the last datagram sealed
  Subkey subkey_;              // of this sender under the key it seals with
};

// Anti-replay window of one sender, as IPsec's (RFC 6479): the highest counter accepted and a
// bitmap of the kWindow counters below it. A counter is accepted once; one more than kWindow
// below the highest is refused (reordering on one link is far less).
class ReplayWindow {
 public:
  static constexpr std::uint64_t kBlocks = 16;
  static constexpr std::uint64_t kWindow = (kBlocks - 1) * 64;  // 960
  // True, and marks it, if `counter` was not accepted before and is in the window. The first
  // counter accepted also marks every counter below it as seen: a receiver takes nothing a
  // sender sent before the first datagram it heard from it (a late joiner is not fed old
  // captures).
  bool accept(std::uint64_t counter) noexcept;

 private:
  std::uint64_t top_ = 0;  // 0: nothing accepted yet (counters start at 1)
  std::uint64_t bits_[kBlocks] = {};
};

// The receiving side of one Group (the receive thread).
class Opener {
 public:
  struct Opened {
    std::span<std::byte> inner;       // the LCM datagram (decrypted in place)
    std::optional<Refusal> refused;  // set when the datagram is refused (inner empty)
  };
  // Checks the envelope in `datagram` against `keys` (tag first, then the sender's replay
  // window), decrypting in place. Never reads outside `datagram`.
  // `own_sender`: the receiving Group's own sender id (0: none). Its own datagrams come back
  // only from its own sockets (multicast loop; `from_self`); one of them from anywhere else
  // is a reflection of a captured datagram: refused as replayed (its window is never filled
  // when the kernel drops the Group's own datagrams).
  // `now_s` / `max_skew_s`: this host's CLOCK_REALTIME seconds and GroupConfig::keyed_max_skew
  // (0: no check): a sender not known yet is taken only if its stamp is within max_skew_s.
  Opened open(const GroupKeys& keys, std::span<std::byte> datagram, std::uint64_t own_sender = 0,
              bool from_self = false, std::uint32_t now_s = 0, std::uint32_t max_skew_s = 0) noexcept;
  std::size_t senders() const noexcept { return windows_.size(); }

  // Senders remembered; past this the one heard least recently is forgotten (a datagram of
  // it captured earlier could then be taken once more: docs/keyed-groups.md "Replay").
  static constexpr std::size_t kMaxSenders = 4096;

 private:
  struct Sender {
    ReplayWindow window;
    std::uint64_t heard = 0;  // value of tick_ when last accepted
    Subkey subkey;            // of the key its last accepted datagram was sealed with
  };
  std::unordered_map<std::uint64_t, Sender> windows_;
  std::uint64_t tick_ = 0;
  Subkey scratch_;  // of the last sender not known yet
};

}  // namespace lcmx::udpm::detail
