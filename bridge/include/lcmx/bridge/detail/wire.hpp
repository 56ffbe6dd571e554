// The bridges' wire format (docs/bridge.md "Wire format"). Installed, not stable.
//
// Control (control_port, one frame per message, text, '\n'-separated "key value" lines):
//   LCMXB1 PING | LCMXB1 PONG
//   from <bridge name>            instance <16 hex>   link <link name>   t <sender ns>
//   PING only: control <port>, channel <name> <port> (repeated), and on the active link
//   "demand" followed by "want <topic> [<age ms>]", "offer <topic>" and "have <topic>" lines (the
//   full sets; "have": the sender's catalogue, at most kMaxCatalogue topics), "keep <topic> <N>" and
//   "type <topic> <fingerprint, 16 hex> <lcm type name>" lines. A topic is written as one word
//   (encode_topic: bytes up to the space, DEL and '%' as %XX), so any LCM channel name can be
//   demanded.
// Data (channel ports, DEALER -> ROUTER): [topic, the name's bytes as they are][header: instance
// u64 LE, seq u64 LE, keep u64 LE][payload].
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace lcmx::bridge::wire {

inline constexpr std::size_t kMaxControlFrame = 4u << 20;  // bytes
inline constexpr std::size_t kMaxTopic = 63;                // LCM's channel limit
inline constexpr std::size_t kDataHeader = 24;
// The catalogue ("have" lines): the large topics a bridge's host publishes, which peers with
// pattern subscribers announce on their hosts. More in a frame is malformed.
inline constexpr std::size_t kMaxCatalogue = 1024;
// "want" and "offer" lines, each: more in a frame is malformed. With kMaxControlFrame, kMaxTopic,
// kMaxCatalogue and the 256 channels they bound what decode() allocates for one frame.
inline constexpr std::size_t kMaxDemand = 4096;

struct Control {
  enum class Kind { ping, pong } kind = Kind::ping;
  std::string from;
  std::uint64_t instance = 0;
  std::string link;
  std::int64_t t_ns = 0;
  // PING only. `active`: sent on the link the sender uses for this peer (keeps its demand
  // alive). `has_demand`: the full state follows (control port, channels, want, offer); sent
  // when it changed and at least every second, so most pings are a few dozen bytes.
  bool active = false;
  int control_port = 0;
  std::vector<std::pair<std::string, int>> channels;
  bool has_demand = false;
  std::set<std::string> want, offer;
  // A wanted topic's age: how long the sender's host has wanted it, in ms, when the frame was
  // sent (at most kMaxWantAgeMs; absent: 0). The receiver serves it from then on, so a publisher
  // that starts while the demand travels loses no message (the start-up race, docs/bridge.md).
  std::map<std::string, std::uint32_t> want_age_ms;
  static constexpr std::uint32_t kMaxWantAgeMs = 600000;
  // Keep last N of offered topics (PublisherOptions::history of the sender's publishers, at
  // most kMaxKeep): the receiver's republisher keeps as many. Absent: 0.
  std::map<std::string, std::uint32_t> keep;
  static constexpr std::uint32_t kMaxKeep = 1000;
  // Part of the demand state: the topics the sender could serve (docs/bridge.md "Pattern
  // subscribers"), at most kMaxCatalogue.
  std::set<std::string> have;
  // The lcm-gen type of offered and catalogued topics at the sender's host (its publishers',
  // when they agree), at most kMaxCatalogue: the receiver's republisher announces it, so tools
  // there show it and a subscriber of another type is told of the mismatch. Absent: raw bytes.
  struct TopicType {
    std::int64_t fingerprint = 0;
    std::string name;
    bool operator==(const TopicType&) const = default;
  };
  std::map<std::string, TopicType> types;
  static constexpr std::size_t kMaxTypeName = 255;
};

// A topic the bridges carry: any LCM channel name, 1..kMaxTopic bytes of anything but NUL.
bool valid_topic(std::string_view t);
// A topic as one word of a control frame's text: bytes up to the space (0x00..0x20), DEL and
// '%' as "%XX" (two upper-case hex digits), every other byte as it is. `t` must be valid_topic.
std::string encode_topic(std::string_view t);
// The topic a word of a control frame names; nullopt unless `word` is encode_topic's spelling of
// a valid_topic (so each topic has exactly one spelling: no other escape, no lower-case hex, no
// bare byte that needs one). Bounded: at most 3 x kMaxTopic bytes are looked at.
std::optional<std::string> decode_topic(std::string_view word);
// An lcm type name that a "type" line can carry: 1..Control::kMaxTypeName bytes, no whitespace or
// control characters. A bridge sends only those: one the decoder refuses would void the frame.
bool valid_type_name(std::string_view name);

std::string encode(const Control& c);
// nullopt for anything malformed (unknown kind or key, bad numbers, oversize, bad topics, more
// lines of a kind than its limit). Bounded: the frame's size is checked before anything is
// parsed, and every collection against its limit before it grows.
std::optional<Control> decode(std::string_view frame);

struct DataHeader {
  std::uint64_t instance = 0;
  std::uint64_t seq = 0;
  // Keep last N of the topic at its origin (PublisherOptions::history): the receiving
  // bridge's republisher keeps as many (at most Control::kMaxKeep; more reads as that).
  std::uint64_t keep = 0;
};
void encode_header(const DataHeader& h, unsigned char out[kDataHeader]);
DataHeader decode_header(const unsigned char in[kDataHeader]);

}  // namespace lcmx::bridge::wire
