#pragma once
// Group keys (docs/keyed-groups.md): a keyed udpm::Group seals every datagram it sends into an
// lcmx envelope authenticated (optionally encrypted) with libsodium's
// XChaCha20-Poly1305-IETF, and takes on receive only envelopes whose tag verifies, once.
//
// Envelope (all integers big-endian), kEnvelopeHeaderSize + the LCM datagram + kEnvelopeTagSize:
//   u32 magic "LCXK" | u8 version 2 | u8 flags (bit 0: encrypted) | u16 reserved 0
//   | u32 key id | u32 time (the sender's CLOCK_REALTIME, seconds, mod 2^32) | u64 sender id
//   | u64 counter | body | 16-byte tag
// body: the LCM datagram (LC02, or one LC03 fragment) in the clear (authenticated: the AEAD
// over an empty message, the whole header and body as additional data), or encrypted (the
// body is the AEAD's ciphertext, the header its additional data). Nonce (24 bytes): sender id
// | 8 zero bytes | counter, so XChaCha20's subkey (HChaCha20 of the first 16) is one per
// sender and kept (version 1 had the counter in those 16 bytes). The sender id is random per Group (64 bits from randombytes), the
// counter starts at 1 and grows by one per datagram, so one Group never repeats a nonce; two
// Groups repeat one only if they draw the same sender id (2^-64 per pair).
// Stock liblcm drops a datagram with an unknown magic without a word: it neither hears nor
// disturbs a keyed group.

#include <array>
#include <cstddef>
#include <cstdint>
#include <mutex>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

namespace lcmx::udpm {

inline constexpr std::uint32_t kMagicKeyed = 0x4c43584b;  // "LCXK"
// 2: nonce sender id | 0 | counter (1: sender id | counter | 0; refused as an unknown key).
inline constexpr std::uint8_t kEnvelopeVersion = 2;
inline constexpr std::size_t kEnvelopeHeaderSize = 32;
inline constexpr std::size_t kEnvelopeTagSize = 16;
inline constexpr std::size_t kEnvelopeOverhead = kEnvelopeHeaderSize + kEnvelopeTagSize;
inline constexpr std::size_t kKeySize = 32;

struct GroupKey {
  std::array<std::uint8_t, kKeySize> bytes{};
  // Derived from the key (keyed BLAKE2b), so a datagram names the key it was sealed with and
  // a receiver refuses another key's datagrams without trying it.
  std::uint32_t id = 0;
};

// What a keyed group seals with and accepts.
struct GroupKeys {
  // One or two keys: keys[0] seals what this Group sends, every key listed is accepted
  // (rotation, docs/keyed-groups.md "Rotation").
  std::vector<GroupKey> keys;
  // Seal with encryption (payloads secret). Receivers take both forms whatever they send.
  bool encrypt = false;
  std::string origin;  // the key file, for messages ("" when made in memory)
};

// The key id of a key (the first 4 bytes of BLAKE2b-128 keyed with it over "lcmx-key-id").
std::uint32_t key_id(const std::array<std::uint8_t, kKeySize>& key);
// A random key (randombytes_buf) with its id. Throws Error(system) if libsodium cannot start.
GroupKey generate_key();
// A key from 32 given bytes (tests, benches), with its id.
GroupKey make_key(const std::array<std::uint8_t, kKeySize>& bytes);

// Reads a key file: 32 raw bytes (one key), or the text form `lcmx keygen --group` writes:
// lines of 64 hex digits (one key each, at most two; the first seals), an optional line
// `encrypt`, blank lines and `#` comments. The file opened (a symbolic link is followed) must
// be a regular file of at most 4096 bytes, owned by this user and readable by nobody else
// (mode 0600 or stricter), as the bridge's secret keys.
// Throws: Error(bad_key) whose message names the file and what is wrong with it.
GroupKeys read_key_file(const std::string& path);

// Writes `keys` in the text form to `path`, mode 0600: to a new temporary file beside it,
// then renamed over it (`overwrite`) or linked to its name (refused if the name exists). A
// symbolic link or anything but a regular file at `path` is refused, overwrite or not.
// Throws: Error(bad_key) naming the file.
void write_key_file(const std::string& path, const GroupKeys& keys, bool overwrite);

// Why a datagram was refused on a keyed group.
enum class Refusal : std::uint8_t {
  unkeyed,      // no lcmx envelope: stock LCM, or an lcmx host without the key
  unknown_key,  // an envelope sealed with a key this group does not hold (wrong key)
  bad_tag,      // the tag does not verify: forged or damaged
  replayed,     // a valid datagram received a second time (or older than the replay window)
  // a valid datagram of a sender not heard yet, stamped further from this host's clock than
  // GroupConfig::keyed_max_skew: replayed from long ago, or the clocks are not in sync
  stale,
};
const char* to_string(Refusal r) noexcept;

// Per source address, what a keyed group refused: one entry for its unauthenticated datagrams
// (unkeyed, unknown key, bad tag) and one for its replays, each reported once by take_new().
// Thread-safe; bounded (kMaxSources entries; refusals after that are counted in overflow()).
class Refusals {
 public:
  struct Source {
    std::uint32_t address_be = 0;
    Refusal first = Refusal::unkeyed;  // the reason of the entry's first refusal
    std::uint64_t count = 0;           // datagrams refused from it (of the entry's kind)
  };
  static constexpr std::size_t kMaxSources = 1024;

  void record(std::uint32_t address_be, Refusal why);
  // Every source refused so far.
  std::vector<Source> sources() const;
  // Sources refused for the first time since the previous call (each is returned once).
  std::vector<Source> take_new();
  std::uint64_t overflow() const;

 private:
  mutable std::mutex mu_;
  // Key: address << 1 | replayed.
  std::unordered_map<std::uint64_t, Source> by_address_;
  std::vector<std::uint64_t> new_;
  std::uint64_t overflow_ = 0;
};

// "unauthenticated traffic from 10.0.0.7: wrong key or not lcmx" (or "replayed datagrams ...").
std::string describe(const Refusals::Source& s);

}  // namespace lcmx::udpm
