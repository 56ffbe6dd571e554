// Group keys: key ids, key files (their format here; reading them with owner and mode checks and
// writing them never through a symbolic link in key_file.cpp, shared with the bridge's CURVE
// keys), and the per-source refusal record of a keyed group.
#include "lcmx/udpm/keys.hpp"

#include <arpa/inet.h>
#include <sodium.h>

#include <cstdio>
#include <cstring>
#include <sstream>
#include <variant>

#include "envelope.hpp"
#include "lcmx/udpm/detail/key_file.hpp"
#include "lcmx/udpm/error.hpp"

namespace lcmx::udpm {
namespace {

constexpr std::size_t kMaxKeyFileBytes = 4096;
constexpr const char* kIdContext = "lcmx-key-id";

[[noreturn]] void bad(const std::string& path, const std::string& why) {
  throw Error(Error::Code::bad_key, "group key file '" + path + "': " + why);
}

int hex_digit(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

std::string hex(const std::uint8_t* p, std::size_t n) {
  static constexpr char d[] = "0123456789abcdef";
  std::string s;
  for (std::size_t i = 0; i < n; ++i) s += d[p[i] >> 4], s += d[p[i] & 15];
  return s;
}

}  // namespace

std::uint32_t key_id(const std::array<std::uint8_t, kKeySize>& key) {
  detail::sodium_ready();
  unsigned char out[crypto_generichash_BYTES_MIN];
  ::crypto_generichash(out, sizeof out, reinterpret_cast<const unsigned char*>(kIdContext), std::strlen(kIdContext),
                       key.data(), key.size());
  return (std::uint32_t{out[0]} << 24) | (std::uint32_t{out[1]} << 16) | (std::uint32_t{out[2]} << 8) | out[3];
}

GroupKey make_key(const std::array<std::uint8_t, kKeySize>& bytes) { return GroupKey{bytes, key_id(bytes)}; }

GroupKey generate_key() {
  detail::sodium_ready();
  std::array<std::uint8_t, kKeySize> b{};
  ::randombytes_buf(b.data(), b.size());
  return make_key(b);
}

GroupKeys read_key_file(const std::string& path) {
  if (path.empty()) bad(path, "no file named");
  auto read = detail::read_key_file_bytes(path, detail::KeyFileAccess::owner_only,
                                          {"a group key", "`lcmx keygen --group`"}, kMaxKeyFileBytes);
  if (const auto* p = std::get_if<detail::KeyFileProblem>(&read)) bad(path, p->why);
  std::string& text = std::get<std::string>(read);
  GroupKeys keys;
  keys.origin = path;
  auto add = [&](const std::array<std::uint8_t, kKeySize>& b) {
    if (keys.keys.size() == 2) bad(path, "more than two keys (the current one and the next)");
    if (sodium_is_zero(b.data(), b.size())) bad(path, "a key of all zero bytes");
    keys.keys.push_back(make_key(b));
    if (keys.keys.size() == 2 && keys.keys[0].bytes == keys.keys[1].bytes) bad(path, "the same key twice");
  };
  if (text.size() == kKeySize) {  // the raw form (the text form has at least 64 characters)
    std::array<std::uint8_t, kKeySize> b{};
    std::memcpy(b.data(), text.data(), kKeySize);
    add(b);
    sodium_memzero(text.data(), text.size());
    return keys;
  }
  std::istringstream in(text);
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (const auto hash = line.find('#'); hash != std::string::npos) line.erase(hash);
    const auto b = line.find_first_not_of(" \t\r");
    if (b == std::string::npos) continue;
    line = line.substr(b, line.find_last_not_of(" \t\r") - b + 1);
    if (line == "encrypt") {
      keys.encrypt = true;
      continue;
    }
    std::array<std::uint8_t, kKeySize> k{};
    bool ok = line.size() == 2 * kKeySize;
    for (std::size_t i = 0; ok && i < kKeySize; ++i) {
      const int hi = hex_digit(line[2 * i]), lo = hex_digit(line[2 * i + 1]);
      ok = hi >= 0 && lo >= 0;
      k[i] = static_cast<std::uint8_t>(hi * 16 + lo);
    }
    if (!ok)
      bad(path, "line " + std::to_string(number) +
                    ": expected a key (64 hex digits), `encrypt`, a comment (#) or nothing (or the file is 32 raw "
                    "bytes), as `lcmx keygen --group` writes");
    add(k);
    sodium_memzero(k.data(), k.size());
  }
  sodium_memzero(text.data(), text.size());
  if (keys.keys.empty()) bad(path, "no key in the file");
  return keys;
}

void write_key_file(const std::string& path, const GroupKeys& keys, bool overwrite) {
  if (keys.keys.empty() || keys.keys.size() > 2) bad(path, "one or two keys are written");
  if (const auto p = detail::check_key_file_target(path, overwrite, " (--force replaces it)")) bad(path, p->why);
  std::string text =
      "# lcmx group key (lcmx keygen --group): keep it secret, mode 0600.\n"
      "# The first key seals what this host sends; every key listed (at most two) is accepted.\n"
      "# docs/keyed-groups.md \"Rotation\"\n";
  if (keys.encrypt) text += "encrypt\n";
  for (const auto& k : keys.keys) {
    char id[16];
    std::snprintf(id, sizeof id, "%08x", k.id);
    text += "# key id " + std::string(id) + "\n" + hex(k.bytes.data(), k.bytes.size()) + "\n";
  }
  const auto p = detail::write_key_file_bytes(path, text, 0600, overwrite);
  sodium_memzero(text.data(), text.size());
  if (p) bad(path, p->why);
}

const char* to_string(Refusal r) noexcept {
  switch (r) {
    case Refusal::unkeyed: return "unkeyed";
    case Refusal::unknown_key: return "unknown_key";
    case Refusal::bad_tag: return "bad_tag";
    case Refusal::replayed: return "replayed";
    case Refusal::stale: return "stale";
  }
  return "?";
}

void Refusals::record(std::uint32_t address_be, Refusal why) {
  std::lock_guard lock(mu_);
  const bool replay = why == Refusal::replayed || why == Refusal::stale;
  const std::uint64_t key = (std::uint64_t{address_be} << 1) | (replay ? 1 : 0);
  auto it = by_address_.find(key);
  if (it == by_address_.end()) {
    if (by_address_.size() >= kMaxSources) {
      ++overflow_;
      return;
    }
    it = by_address_.emplace(key, Source{address_be, why, 0}).first;
    new_.push_back(key);
  }
  ++it->second.count;
}

std::vector<Refusals::Source> Refusals::sources() const {
  std::lock_guard lock(mu_);
  std::vector<Source> out;
  out.reserve(by_address_.size());
  for (const auto& [a, s] : by_address_) out.push_back(s);
  return out;
}

std::vector<Refusals::Source> Refusals::take_new() {
  std::lock_guard lock(mu_);
  std::vector<Source> out;
  for (auto a : new_) out.push_back(by_address_.at(a));
  new_.clear();
  return out;
}

std::uint64_t Refusals::overflow() const {
  std::lock_guard lock(mu_);
  return overflow_;
}

std::string describe(const Refusals::Source& s) {
  char buf[INET_ADDRSTRLEN] = {};
  in_addr a{};
  a.s_addr = s.address_be;
  ::inet_ntop(AF_INET, &a, buf, sizeof buf);
  const std::string from = buf;
  switch (s.first) {
    case Refusal::replayed:
      return "replayed datagrams from " + from + ": refused (a captured datagram sent again)";
    case Refusal::stale:
      return "stale datagrams from " + from + ": refused (stamped too far from this host's clock: replayed from "
             "long ago, or the hosts' clocks are not in sync)";
    case Refusal::bad_tag:
      return "unauthenticated traffic from " + from + ": forged or damaged (the tag does not verify)";
    case Refusal::unknown_key:
      return "unauthenticated traffic from " + from + ": wrong key or not lcmx";
    case Refusal::unkeyed:
      break;
  }
  return "unauthenticated traffic from " + from + ": wrong key or not lcmx (no key at all: stock LCM or lcmx "
         "without the group key)";
}

}  // namespace lcmx::udpm
