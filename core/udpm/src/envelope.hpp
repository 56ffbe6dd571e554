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
  // The subkey derived last (of() called at least once).
  const unsigned char* current() const noexcept { return sub_; }
  // Changes each time the subkey is derived (0: never): what a OneTimeKey was made under.
  std::uint64_t generation() const noexcept { return generation_; }

 private:
  std::uint64_t generation_ = 0;
  bool set_ = false;
  std::uint64_t sender_ = 0;
  std::array<std::uint8_t, kKeySize> key_{};
  unsigned char sub_[kKeySize] = {};
};

// ChaCha20-Poly1305-IETF's tag (RFC 8439 section 2.8) under the one-time key `otk`: Poly1305
// over ad | zeros to 16 | c | zeros to 16 | le64(ad size) | le64(c size). These are the steps of
// libsodium's crypto_aead_chacha20poly1305_ietf_{en,de}crypt_detached, taken apart so that the
// one-time key (their first step) can be made ahead (OneTimeKey; docs/keyed-groups.md "Wire
// form"); every primitive is libsodium's, and a unit test checks the bytes against its AEAD.
// (bench/udp --seal-micro measures it.)
void tag_of(unsigned char (&tag)[kEnvelopeTagSize], const unsigned char* otk, const unsigned char* ad,
            std::size_t ad_size, const unsigned char* c, std::size_t c_size) noexcept;

// Poly1305's one-time key for one counter of one sender: the first 32 bytes of ChaCha20(subkey,
// 4 zero bytes | counter, block 0), as ChaCha20-Poly1305-IETF derives it. Made ahead, for the
// counter expected next, once a datagram is handled (prepare()), so that the next datagram's
// path runs Poly1305 alone (docs/keyed-groups.md "Wire form"). Used only when both the counter
// and the subkey's generation match; wiped when dropped.
class OneTimeKey {
 public:
  OneTimeKey() = default;
  OneTimeKey(const OneTimeKey&) = delete;
  OneTimeKey& operator=(const OneTimeKey&) = delete;
  ~OneTimeKey();
  // Makes the key of `counter` under `subkey`'s current subkey (of() called at least once).
  void prepare(const Subkey& subkey, std::uint64_t counter) noexcept;
  // The key of `counter` under `subkey`'s current subkey: the one made ahead if it is that one,
  // else made now.
  const unsigned char* of(const Subkey& subkey, std::uint64_t counter) noexcept;

 private:
  std::uint64_t counter_ = 0;     // 0: none made
  std::uint64_t generation_ = 0;  // the subkey's generation it was made under
  unsigned char key_[32] = {};
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
  // Makes the next datagram's one-time key under keys.keys.front(); call after sending, off the
  // next datagram's path. keys.keys must not be empty.
  void prepare(const GroupKeys& keys) noexcept;
  std::uint64_t sender_id() const noexcept { return sender_; }
  std::uint64_t counter() const noexcept { return counter_; }

 private:
  std::uint64_t sender_ = 0;
  std::uint64_t counter_ = 0;  // of the last datagram sealed
  Subkey subkey_;              // of this sender under the key it seals with
  OneTimeKey next_;            // of counter_ + 1, when prepare() ran
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
  // The highest counter accepted (0: none).
  std::uint64_t top() const noexcept { return top_; }

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
  // Makes, for each sender accepted since the last call, the one-time key of the counter after
  // the highest it accepted. Call after the datagrams were handled (off their path).
  void prepare() noexcept;

  // Senders remembered; past this the one heard least recently is forgotten (a datagram of
  // it captured earlier could then be taken once more: docs/keyed-groups.md "Replay").
  static constexpr std::size_t kMaxSenders = 4096;

 private:
  struct Sender {
    ReplayWindow window;
    std::uint64_t heard = 0;  // value of tick_ when last accepted
    Subkey subkey;            // of the key its last accepted datagram was sealed with
    OneTimeKey next;          // of the counter after the highest accepted (prepare())
  };
  std::unordered_map<std::uint64_t, Sender> windows_;
  // Senders accepted since prepare() ran (bounded: past kMaxPending the rest make theirs on
  // their next datagram's path).
  static constexpr std::size_t kMaxPending = 64;
  std::uint64_t pending_[kMaxPending] = {};
  std::size_t npending_ = 0;
  std::uint64_t tick_ = 0;
  Subkey scratch_;  // of the last sender not known yet
  OneTimeKey scratch_key_;
};

}  // namespace lcmx::udpm::detail
