#include "envelope.hpp"

#include <sodium.h>

#include <cstring>
#include <ctime>
#include <mutex>

#include "lcmx/udpm/error.hpp"

namespace lcmx::udpm::detail {
namespace {

constexpr std::uint8_t kFlagEncrypted = 1;
static_assert(crypto_aead_xchacha20poly1305_ietf_ABYTES == kEnvelopeTagSize);
static_assert(crypto_aead_xchacha20poly1305_ietf_KEYBYTES == kKeySize);
static_assert(crypto_aead_xchacha20poly1305_ietf_NPUBBYTES == 24);

void put_u32(std::byte* p, std::uint32_t v) {
  for (int i = 3; i >= 0; --i, v >>= 8) p[i] = std::byte(v & 0xff);
}
void put_u64(std::byte* p, std::uint64_t v) {
  for (int i = 7; i >= 0; --i, v >>= 8) p[i] = std::byte(v & 0xff);
}
std::uint32_t get_u32(const std::byte* p) {
  std::uint32_t v = 0;
  for (int i = 0; i < 4; ++i) v = (v << 8) | std::to_integer<std::uint32_t>(p[i]);
  return v;
}
std::uint64_t get_u64(const std::byte* p) {
  std::uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | std::to_integer<std::uint64_t>(p[i]);
  return v;
}
auto* uc(std::byte* p) { return reinterpret_cast<unsigned char*>(p); }
auto* uc(const std::byte* p) { return reinterpret_cast<const unsigned char*>(p); }

// Header offsets.
constexpr std::size_t kOffVersion = 4, kOffFlags = 5, kOffKeyId = 8, kOffTime = 12, kOffSender = 16, kOffCounter = 24;
static_assert(kOffCounter + 8 == kEnvelopeHeaderSize);

// The nonce (24 bytes): sender id | 8 zero bytes | counter. XChaCha20-Poly1305 of it is
// ChaCha20-Poly1305-IETF keyed with HChaCha20(key, its first 16 bytes) (Subkey: once per
// sender) under the 12-byte nonce 4 zero bytes | counter, which is what is computed here.
void ietf_nonce_of(const std::byte* header, unsigned char (&nonce)[crypto_aead_chacha20poly1305_ietf_NPUBBYTES]) {
  static_assert(crypto_aead_chacha20poly1305_ietf_NPUBBYTES == 12);
  std::memset(nonce, 0, 4);
  std::memcpy(nonce + 4, header + kOffCounter, 8);
}

}  // namespace

void tag_of(unsigned char (&tag)[kEnvelopeTagSize], const unsigned char* otk, const unsigned char* ad,
            std::size_t ad_size, const unsigned char* c, std::size_t c_size) noexcept {
  static const unsigned char zeros[16] = {};
  unsigned char sizes[16];
  for (int i = 0; i < 8; ++i) {
    sizes[i] = static_cast<unsigned char>(static_cast<std::uint64_t>(ad_size) >> (8 * i));
    sizes[8 + i] = static_cast<unsigned char>(static_cast<std::uint64_t>(c_size) >> (8 * i));
  }
  crypto_onetimeauth_poly1305_state st;
  ::crypto_onetimeauth_poly1305_init(&st, otk);
  ::crypto_onetimeauth_poly1305_update(&st, ad, ad_size);
  ::crypto_onetimeauth_poly1305_update(&st, zeros, (0x10 - ad_size) & 0xf);
  if (c_size > 0) ::crypto_onetimeauth_poly1305_update(&st, c, c_size);
  ::crypto_onetimeauth_poly1305_update(&st, zeros, (0x10 - c_size) & 0xf);
  ::crypto_onetimeauth_poly1305_update(&st, sizes, sizeof sizes);
  ::crypto_onetimeauth_poly1305_final(&st, tag);
  ::sodium_memzero(&st, sizeof st);
}

namespace {
// The tag of the envelope at `envelope` (header, then `inner_size` bytes of body): over header
// and body as additional data when authenticated, over the header as additional data and the
// body as ciphertext when encrypted (the body already encrypted). Sealer and Opener alike.
void envelope_tag(unsigned char (&tag)[kEnvelopeTagSize], const unsigned char* otk, const std::byte* envelope,
                  std::size_t inner_size, bool encrypted) noexcept {
  if (encrypted) tag_of(tag, otk, uc(envelope), kEnvelopeHeaderSize, uc(envelope + kEnvelopeHeaderSize), inner_size);
  else tag_of(tag, otk, uc(envelope), kEnvelopeHeaderSize + inner_size, nullptr, 0);
}
}  // namespace

void sodium_ready() {
  static const int r = ::sodium_init();  // thread-safe, once
  if (r < 0) throw Error(Error::Code::system, "udpm: libsodium failed to start (sodium_init)");
}

Subkey::~Subkey() {
  ::sodium_memzero(sub_, sizeof sub_);
  ::sodium_memzero(key_.data(), key_.size());
}

const unsigned char* Subkey::of(const GroupKey& key, std::uint64_t sender) noexcept {
  if (!set_ || sender != sender_ || key.bytes != key_) {
    std::byte in[crypto_core_hchacha20_INPUTBYTES] = {};  // sender id | 8 zero bytes
    put_u64(in, sender);
    ::crypto_core_hchacha20(sub_, uc(in), key.bytes.data(), nullptr);
    key_ = key.bytes;
    sender_ = sender;
    set_ = true;
    ++generation_;
  }
  return sub_;
}

OneTimeKey::~OneTimeKey() { ::sodium_memzero(key_, sizeof key_); }

void OneTimeKey::prepare(const Subkey& subkey, std::uint64_t counter) noexcept {
  static_assert(crypto_onetimeauth_poly1305_KEYBYTES == sizeof key_);
  std::byte header[kEnvelopeHeaderSize] = {};
  put_u64(header + kOffCounter, counter);
  unsigned char nonce[crypto_aead_chacha20poly1305_ietf_NPUBBYTES];
  ietf_nonce_of(header, nonce);
  ::crypto_stream_chacha20_ietf(key_, sizeof key_, nonce, subkey.current());
  counter_ = counter;
  generation_ = subkey.generation();
}

const unsigned char* OneTimeKey::of(const Subkey& subkey, std::uint64_t counter) noexcept {
  if (counter_ == 0 || counter_ != counter || generation_ != subkey.generation()) prepare(subkey, counter);
  return key_;
}

Sealer::Sealer() {
  sodium_ready();
  ::randombytes_buf(&sender_, sizeof sender_);
}

std::size_t Sealer::seal(const GroupKeys& keys, std::byte* buffer, std::size_t inner_size) noexcept {
  const GroupKey& key = keys.keys.front();
  put_u32(buffer, kMagicKeyed);
  buffer[kOffVersion] = std::byte{kEnvelopeVersion};
  buffer[kOffFlags] = std::byte{keys.encrypt ? kFlagEncrypted : std::uint8_t{0}};
  buffer[6] = buffer[7] = std::byte{0};
  put_u32(buffer + kOffKeyId, key.id);
  put_u32(buffer + kOffTime, static_cast<std::uint32_t>(std::time(nullptr)));
  put_u64(buffer + kOffSender, sender_);
  put_u64(buffer + kOffCounter, ++counter_);  // 2^64 datagrams: never wraps
  unsigned char nonce[crypto_aead_chacha20poly1305_ietf_NPUBBYTES];
  ietf_nonce_of(buffer, nonce);
  const unsigned char* sub = subkey_.of(key, sender_);
  std::byte* body = buffer + kEnvelopeHeaderSize;
  if (keys.encrypt) ::crypto_stream_chacha20_ietf_xor_ic(uc(body), uc(body), inner_size, nonce, 1, sub);
  unsigned char tag[kEnvelopeTagSize];
  envelope_tag(tag, next_.of(subkey_, counter_), buffer, inner_size, keys.encrypt);
  std::memcpy(body + inner_size, tag, sizeof tag);
  return kEnvelopeOverhead + inner_size;
}

void Sealer::prepare(const GroupKeys& keys) noexcept {
  subkey_.of(keys.keys.front(), sender_);
  next_.prepare(subkey_, counter_ + 1);
}

bool ReplayWindow::accept(std::uint64_t counter) noexcept {
  if (counter == 0) return false;  // never sent
  if (top_ == 0) {  // the first: it and everything before it count as seen
    top_ = counter;
    for (auto& b : bits_) b = ~std::uint64_t{0};
    const std::uint64_t r = counter % 64;  // in its own block, the bits above it are free
    bits_[(counter / 64) % kBlocks] = r == 63 ? ~std::uint64_t{0} : (std::uint64_t{1} << (r + 1)) - 1;
    return true;
  }
  const std::uint64_t block = counter / 64;
  if (counter > top_) {
    // Clear the blocks the window moves over (at most all of them).
    const std::uint64_t top_block = top_ / 64;
    const std::uint64_t moved = std::min<std::uint64_t>(block - top_block, kBlocks);
    for (std::uint64_t i = 1; i <= moved; ++i) bits_[(top_block + i) % kBlocks] = 0;
    top_ = counter;
  } else if (top_ - counter > kWindow) {
    return false;  // too old to tell: refused
  }
  std::uint64_t& word = bits_[block % kBlocks];
  const std::uint64_t bit = std::uint64_t{1} << (counter % 64);
  if ((word & bit) != 0) return false;
  word |= bit;
  return true;
}

Opener::Opened Opener::open(const GroupKeys& keys, std::span<std::byte> d, std::uint64_t own_sender,
                            bool from_self, std::uint32_t now_s, std::uint32_t max_skew_s) noexcept {
  if (d.size() < kEnvelopeOverhead || get_u32(d.data()) != kMagicKeyed) return {{}, Refusal::unkeyed};
  if (std::to_integer<std::uint8_t>(d[kOffVersion]) != kEnvelopeVersion) return {{}, Refusal::unknown_key};
  const std::uint8_t flags = std::to_integer<std::uint8_t>(d[kOffFlags]);
  if ((flags & ~kFlagEncrypted) != 0) return {{}, Refusal::bad_tag};  // (authenticated below anyway)
  const std::uint32_t id = get_u32(d.data() + kOffKeyId);
  const std::size_t inner_size = d.size() - kEnvelopeOverhead;
  std::byte* body = d.data() + kEnvelopeHeaderSize;
  const std::byte* tag = body + inner_size;
  unsigned char nonce[crypto_aead_chacha20poly1305_ietf_NPUBBYTES];
  ietf_nonce_of(d.data(), nonce);
  const std::uint64_t sender = get_u64(d.data() + kOffSender), counter = get_u64(d.data() + kOffCounter);
  auto it = windows_.find(sender);
  // A known sender's subkey and next one-time key are kept with its window; one not heard yet
  // (or a forgery naming no known sender) costs HChaCha20 and ChaCha20 each time, in scratch_.
  const bool heard = it != windows_.end();
  Subkey& subkey = heard ? it->second.subkey : scratch_;
  OneTimeKey& otk = heard ? it->second.next : scratch_key_;
  const bool encrypted = (flags & kFlagEncrypted) != 0;
  bool known = false, verified = false;
  for (const auto& key : keys.keys) {  // at most two; ids may collide (2^-32): try each that matches
    if (key.id != id) continue;
    known = true;
    const unsigned char* sub = subkey.of(key, sender);
    unsigned char expected[kEnvelopeTagSize];
    envelope_tag(expected, otk.of(subkey, counter), d.data(), inner_size, encrypted);
    if (::crypto_verify_16(expected, uc(tag)) == 0) {
      if (encrypted) ::crypto_stream_chacha20_ietf_xor_ic(uc(body), uc(body), inner_size, nonce, 1, sub);
      verified = true;
      break;
    }
  }
  if (!known) return {{}, Refusal::unknown_key};
  if (!verified) return {{}, Refusal::bad_tag};
  // Authentic: now the sender's replay window.
  if (own_sender != 0 && sender == own_sender && !from_self) return {{}, Refusal::replayed};
  if (it == windows_.end()) {
    if (max_skew_s != 0) {
      const std::uint32_t stamp = get_u32(d.data() + kOffTime);
      const std::uint32_t ahead = stamp - now_s, behind = now_s - stamp;  // modulo 2^32
      if (std::min(ahead, behind) > max_skew_s) return {{}, Refusal::stale};
    }
    if (windows_.size() >= kMaxSenders) {
      auto oldest = windows_.begin();
      for (auto i = windows_.begin(); i != windows_.end(); ++i)
        if (i->second.heard < oldest->second.heard) oldest = i;
      windows_.erase(oldest);
    }
    it = windows_.try_emplace(sender).first;
  }
  if (!it->second.window.accept(counter)) return {{}, Refusal::replayed};
  it->second.heard = ++tick_;
  if (npending_ < kMaxPending && (npending_ == 0 || pending_[npending_ - 1] != sender)) pending_[npending_++] = sender;
  return {std::span<std::byte>(body, inner_size), std::nullopt};
}

void Opener::prepare() noexcept {
  for (std::size_t i = 0; i < npending_; ++i) {
    const auto it = windows_.find(pending_[i]);
    if (it == windows_.end()) continue;  // forgotten since (kMaxSenders)
    Sender& s = it->second;
    if (s.subkey.generation() == 0) continue;  // heard once: its subkey is made on its next datagram
    s.next.prepare(s.subkey, s.window.top() + 1);
  }
  npending_ = 0;
}

}  // namespace lcmx::udpm::detail
