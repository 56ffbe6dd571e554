#include "socket_filter.hpp"

#include <arpa/inet.h>

#include <algorithm>
#include <cstring>
#include <limits>

#include "lcmx/udpm/error.hpp"
#include "lcmx/udpm/keys.hpp"
#include "lcmx/udpm/wire.hpp"

namespace lcmx::udpm {

bool takes_everything(const ReceiveFilter& f) noexcept {
  return !f.channels && (f.control_channel.empty() || f.control_all);
}

namespace detail {

void check_filter(const ReceiveFilter& f) {
  auto bad = [](const std::string& why) { throw Error(Error::Code::invalid_config, "udpm receive filter: " + why); };
  auto check_name = [&](const std::string& c, const char* what) {
    if (c.size() > kMaxChannelLength)
      bad(std::string(what) + " '" + c + "' is " + std::to_string(c.size()) + " bytes (max 63)");
    if (c.find('\0') != std::string::npos) bad(std::string(what) + " contains a NUL byte");
  };
  if (f.channels)
    for (const auto& c : *f.channels) check_name(c, "channel");
  check_name(f.control_channel, "control channel");
  if (f.mark_prefix.size() > kMaxMarkPrefix)
    bad("mark prefix of " + std::to_string(f.mark_prefix.size()) + " bytes (max " + std::to_string(kMaxMarkPrefix) +
        ")");
}

FilterRule::FilterRule(const ReceiveFilter& f)
    : everything_(takes_everything(f)),
      all_channels_(!f.channels),
      control_(f.control_channel),
      control_all_(f.control_all),
      prefix_(f.mark_prefix),
      mark_channel_at_(f.mark_channel_at),
      any_source_(!f.mark_sources) {
  if (f.channels) {
    channels_ = *f.channels;
    std::sort(channels_.begin(), channels_.end());
    channels_.erase(std::unique(channels_.begin(), channels_.end()), channels_.end());
  }
  if (f.mark_sources) sources_ = *f.mark_sources;
}

bool FilterRule::takes(std::string_view channel, std::span<const std::byte> payload,
                       const Source& source) const noexcept {
  if (everything_) return true;
  if (!control_.empty() && channel == control_) {
    if (control_all_) return true;
    if (payload.size() < prefix_.size() || !std::equal(prefix_.begin(), prefix_.end(), payload.begin())) return false;
    if (mark_channel_at_ && !all_channels_) {
      // An LCM string: big-endian int32 length counting the NUL, the bytes, the NUL.
      const std::size_t at = *mark_channel_at_;
      if (payload.size() < at + 4) return false;
      std::uint32_t len = 0;
      for (int k = 0; k < 4; ++k) len = (len << 8) | std::to_integer<std::uint8_t>(payload[at + static_cast<std::size_t>(k)]);
      if (len == 0 || len - 1 > kMaxChannelLength || payload.size() < at + 4 + len ||
          payload[at + 4 + len - 1] != std::byte{0})
        return false;
      const std::string_view name(reinterpret_cast<const char*>(payload.data() + at + 4), len - 1);
      if (!std::binary_search(channels_.begin(), channels_.end(), name, std::less<>{})) return false;
    }
    return any_source_ || std::find(sources_.begin(), sources_.end(), source) != sources_.end();
  }
  return all_channels_ || std::binary_search(channels_.begin(), channels_.end(), channel, std::less<>{});
}

namespace {

// UDP socket filters see the datagram from its UDP header (the payload at 8, source port at 0)
// and the IPv4 header at SKF_NET_OFF (source address at +12). BPF_ABS loads are big-endian; a
// load past the end of the packet ends the program with 0 (drop), so every compare below is
// guarded by the packet's length (BPF_LEN: UDP header + payload) and never loads past it.
constexpr std::uint32_t kUdpPayload = 8;
constexpr std::uint32_t kSourceAddress = static_cast<std::uint32_t>(SKF_NET_OFF) + 12;
constexpr std::uint32_t kAccept = std::numeric_limits<std::uint32_t>::max();  // keep all of it
constexpr std::uint32_t kDrop = 0;

// A classic BPF assembler with labels. Conditional jumps reach at most 255 instructions ahead;
// finish() refuses a program that needs more (or more than kMaxInstructions).
class Assembler {
 public:
  using Label = std::size_t;
  static constexpr Label kNext = std::numeric_limits<Label>::max();  // fall through

  Label label() {
    at_.push_back(kUnbound);
    return at_.size() - 1;
  }
  void bind(Label l) { at_[l] = code_.size(); }
  void stmt(std::uint16_t code, std::uint32_t k) { code_.push_back(BPF_STMT(code, k)); }
  void ret(std::uint32_t k) { stmt(BPF_RET | BPF_K, k); }
  // if (A op k) goto jt else goto jf.
  void jump(std::uint16_t op, std::uint32_t k, Label jt, Label jf) {
    fixes_.push_back({code_.size(), jt, jf, false});
    code_.push_back(BPF_JUMP(BPF_JMP | op | BPF_K, k, 0, 0));
  }
  void ja(Label to) {
    fixes_.push_back({code_.size(), to, kNext, true});
    code_.push_back(BPF_STMT(BPF_JMP | BPF_JA, 0));
  }
  // Drops to `fail` unless the packet holds at least `bytes` bytes (from the UDP header).
  void need(std::uint32_t bytes, Label fail) {
    stmt(BPF_LD | BPF_W | BPF_LEN, 0);
    jump(BPF_JGE, bytes, kNext, fail);
  }
  // Goes to `fail` unless the packet's bytes at `offset` are `bytes`: word, half-word and byte
  // loads, none past offset + size (the caller checked the length).
  void compare(std::uint32_t offset, std::span<const std::uint8_t> bytes, Label fail) {
    std::size_t i = 0;
    while (i < bytes.size()) {
      const std::size_t left = bytes.size() - i;
      const std::size_t w = left >= 4 ? 4 : left >= 2 ? 2 : 1;
      std::uint32_t v = 0;
      for (std::size_t j = 0; j < w; ++j) v = (v << 8) | bytes[i + j];
      stmt(BPF_LD | (w == 4 ? BPF_W : w == 2 ? BPF_H : BPF_B) | BPF_ABS, offset + static_cast<std::uint32_t>(i));
      jump(BPF_JEQ, v, kNext, fail);
      i += w;
    }
  }
  std::size_t size() const noexcept { return code_.size(); }

  std::optional<std::vector<sock_filter>> finish() {
    if (code_.size() > kMaxInstructions) return std::nullopt;
    for (const Fix& f : fixes_) {
      const auto offset = [&](Label l) -> std::optional<std::size_t> {
        if (l == kNext) return 0;
        if (at_[l] == kUnbound || at_[l] <= f.at) return std::nullopt;  // unbound or backwards
        return at_[l] - f.at - 1;
      };
      const auto jt = offset(f.jt);
      const auto jf = offset(f.jf);
      if (!jt || !jf) return std::nullopt;
      if (f.always) {
        code_[f.at].k = static_cast<std::uint32_t>(*jt);
      } else {
        if (*jt > 255 || *jf > 255) return std::nullopt;
        code_[f.at].jt = static_cast<std::uint8_t>(*jt);
        code_[f.at].jf = static_cast<std::uint8_t>(*jf);
      }
    }
    return std::move(code_);
  }

 private:
  static constexpr std::size_t kUnbound = std::numeric_limits<std::size_t>::max();
  struct Fix {
    std::size_t at;
    Label jt, jf;
    bool always;  // BPF_JA: jt in k
  };
  std::vector<sock_filter> code_;
  std::vector<std::size_t> at_;
  std::vector<Fix> fixes_;
};

std::vector<std::uint8_t> with_nul(std::string_view s) {
  std::vector<std::uint8_t> v(s.begin(), s.end());
  v.push_back(0);
  return v;
}

}  // namespace

std::optional<std::vector<sock_filter>> socket_program(const ProgramSpec& spec, const ReceiveFilter& f,
                                                       KernelPart part) {
  // What this part judges in the kernel.
  bool judge_channels = f.channels.has_value();
  bool control = !f.control_channel.empty() && !f.control_all;
  bool sources = control && f.mark_sources.has_value();
  if (part != KernelPart::whole) judge_channels = false;
  if (part == KernelPart::without_sources || part == KernelPart::own_only) sources = false;
  if (part == KernelPart::own_only) control = false;
  // The control channel always takes its marks; with control_all it is judged only to keep it
  // out of `channels`' verdict.
  const bool control_block = !f.control_channel.empty() && (control || judge_channels);
  const bool drop_own = spec.drop_own && !spec.own_addresses.empty();

  Assembler a;
  using L = Assembler::Label;
  constexpr L next = Assembler::kNext;
  if (drop_own) {
    const L own = a.label(), not_own = a.label();
    a.stmt(BPF_LD | BPF_H | BPF_ABS, 0);  // source port
    a.jump(BPF_JEQ, ntohs(spec.own_port_be), next, not_own);
    a.stmt(BPF_LD | BPF_W | BPF_ABS, kSourceAddress);
    const std::size_t n = std::min<std::size_t>(spec.own_addresses.size(), 16);
    for (std::size_t i = 0; i < n; ++i) a.jump(BPF_JEQ, ntohl(spec.own_addresses[i]), own, next);
    a.ja(not_own);
    a.bind(own);
    a.ret(kDrop);  // ours
    a.bind(not_own);
  }
  if (!judge_channels && !control) {
    if (!drop_own) return std::vector<sock_filter>{};  // nothing to drop
    a.ret(kAccept);
    return a.finish();
  }

  // Where the LCM datagram starts: at the UDP payload, or after an authenticated envelope's
  // header. Anything else is not judged here: taken (user space counts and reports it).
  const std::uint32_t p = kUdpPayload + (spec.key_ids ? static_cast<std::uint32_t>(kEnvelopeHeaderSize) : 0);
  const L taken = a.label(), judge = a.label();
  a.need(p + static_cast<std::uint32_t>(kShortHeaderSize), taken);
  if (spec.key_ids) {
    a.stmt(BPF_LD | BPF_W | BPF_ABS, kUdpPayload);  // envelope magic
    a.jump(BPF_JEQ, kMagicKeyed, next, taken);
    a.stmt(BPF_LD | BPF_H | BPF_ABS, kUdpPayload + 4);  // version | flags: authenticated only
    a.jump(BPF_JEQ, std::uint32_t{kEnvelopeVersion} << 8, next, taken);
    a.stmt(BPF_LD | BPF_W | BPF_ABS, kUdpPayload + 8);  // key id: one of ours
    const L known = a.label();
    for (std::size_t i = 0; i < spec.key_ids->size(); ++i)
      a.jump(BPF_JEQ, (*spec.key_ids)[i], known, i + 1 == spec.key_ids->size() ? taken : next);
    if (spec.key_ids->empty()) a.ja(taken);
    a.bind(known);
  }
  a.stmt(BPF_LD | BPF_W | BPF_ABS, p);
  a.jump(BPF_JEQ, kMagicShort, judge, taken);  // LC03 (and anything else): taken
  a.bind(taken);
  a.ret(kAccept);
  a.bind(judge);

  // One block per channel taken: its length and bytes (NUL included), then taken; on the first
  // difference, the next block. Every jump stays within its block (<= 35 instructions).
  const std::uint32_t chan = p + static_cast<std::uint32_t>(kShortHeaderSize);
  if (judge_channels) {
    std::vector<std::string> names = *f.channels;
    std::sort(names.begin(), names.end());
    names.erase(std::unique(names.begin(), names.end()), names.end());
    for (const auto& c : names) {
      if (!f.control_channel.empty() && c == f.control_channel) continue;  // judged apart, below
      const L other = a.label();
      const auto bytes = with_nul(c);
      a.need(chan + static_cast<std::uint32_t>(bytes.size()), other);
      a.compare(chan, bytes, other);
      a.ret(kAccept);
      a.bind(other);
      if (a.size() > kMaxInstructions) return std::nullopt;
    }
  }
  const std::uint32_t otherwise = judge_channels ? kDrop : kAccept;
  if (control_block) {
    const L not_control = a.label(), is_control = a.label();
    const auto bytes = with_nul(f.control_channel);
    a.need(chan + static_cast<std::uint32_t>(bytes.size()), not_control);
    a.compare(chan, bytes, not_control);
    a.ja(is_control);
    a.bind(not_control);
    a.ret(otherwise);
    a.bind(is_control);
    if (!control) {
      a.ret(kAccept);  // control_all
    } else {
      // A mark: the payload starts with the prefix (a datagram too short for it is not one).
      const L not_mark = a.label(), mark = a.label();
      const std::uint32_t payload = chan + static_cast<std::uint32_t>(bytes.size());
      const std::vector<std::uint8_t> prefix(reinterpret_cast<const std::uint8_t*>(f.mark_prefix.data()),
                                             reinterpret_cast<const std::uint8_t*>(f.mark_prefix.data()) +
                                                 f.mark_prefix.size());
      a.need(payload + static_cast<std::uint32_t>(prefix.size()), not_mark);
      a.compare(payload, prefix, not_mark);
      a.ja(mark);
      a.bind(not_mark);
      a.ret(kDrop);
      a.bind(mark);
      if (f.mark_channel_at && judge_channels) {
        // The channel it names (an LCM string: length with the NUL, bytes, NUL): one block per
        // channel taken, as above; none matched: dropped.
        const std::uint32_t name = payload + static_cast<std::uint32_t>(*f.mark_channel_at);
        std::vector<std::string> names = *f.channels;
        std::sort(names.begin(), names.end());
        names.erase(std::unique(names.begin(), names.end()), names.end());
        const L named = a.label();
        for (const auto& c : names) {
          const L other = a.label();
          std::vector<std::uint8_t> bytes;
          const auto len = static_cast<std::uint32_t>(c.size() + 1);
          for (int k = 3; k >= 0; --k) bytes.push_back(static_cast<std::uint8_t>(len >> (8 * k)));
          const auto text = with_nul(c);
          bytes.insert(bytes.end(), text.begin(), text.end());
          a.need(name + static_cast<std::uint32_t>(bytes.size()), other);
          a.compare(name, bytes, other);
          a.ja(named);
          a.bind(other);
          if (a.size() > kMaxInstructions) return std::nullopt;
        }
        a.ret(kDrop);
        a.bind(named);
      }
      if (sources) {
        for (const Source& s : *f.mark_sources) {
          const L other = a.label();
          a.stmt(BPF_LD | BPF_W | BPF_ABS, kSourceAddress);
          a.jump(BPF_JEQ, ntohl(s.address_be), next, other);
          a.stmt(BPF_LD | BPF_H | BPF_ABS, 0);
          a.jump(BPF_JEQ, ntohs(s.port_be), next, other);
          a.ret(kAccept);
          a.bind(other);
          if (a.size() > kMaxInstructions) return std::nullopt;
        }
        a.ret(kDrop);
      } else {
        a.ret(kAccept);
      }
    }
  } else {
    a.ret(otherwise);
  }
  return a.finish();
}

}  // namespace detail
}  // namespace lcmx::udpm
