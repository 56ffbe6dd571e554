// libFuzzer target: the Message Bridge's wire format (bridge/src/wire.cpp,
// lcmx/bridge/detail/wire.hpp) on hostile bytes, as a configured peer (or, without CURVE, a
// machine that sends from a peer's address) can send them.
//
// The whole input is one control frame for wire::decode. Checks:
//  - an accepted frame has every required field valid (names, topics, ports, bounded counts);
//  - encode() of it decodes again, and encode() of that is the same text (the canonical form
//    is a fixed point: what a bridge re-sends is what it read);
//  - the fields encode() carries survive the round trip.
// The input is also one data frame's topic and header, as the channel threads check them:
// byte 0 = topic length, then the topic, then the rest as the 24-byte header (accepted only
// when exactly 24 bytes); decode_header + encode_header give back the same 24 bytes. And the
// whole input is one word of a control frame naming a topic (decode_topic): one that decodes is
// the canonical spelling of a valid topic (encode_topic gives the word back), and any valid
// topic (the input's first up to 63 bytes) encodes to one word that decodes to it.
// A failed check prints what failed and aborts, which libFuzzer reports as a crash.

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <string_view>

#include "lcmx/bridge/detail/wire.hpp"

namespace {

#define FUZZ_CHECK(cond)                                                                  \
  do {                                                                                    \
    if (!(cond)) {                                                                        \
      std::fprintf(stderr, "fuzz_bridge_frame: check failed: %s (%s:%d)\n", #cond,       \
                   __FILE__, __LINE__);                                                   \
      std::abort();                                                                       \
    }                                                                                     \
  } while (0)

namespace wire = lcmx::bridge::wire;

bool valid_name(std::string_view s) {
  if (s.empty() || s.size() > 32) return false;
  for (unsigned char c : s)
    if (c <= ' ' || c == 0x7f) return false;
  return true;
}

void check_control(std::string_view frame) {
  const auto c = wire::decode(frame);
  if (!c) return;
  FUZZ_CHECK(frame.size() <= wire::kMaxControlFrame);
  FUZZ_CHECK(valid_name(c->from));
  FUZZ_CHECK(valid_name(c->link));
  if (c->kind == wire::Control::Kind::pong) {
    FUZZ_CHECK(!c->active && !c->has_demand && c->channels.empty() && c->want.empty() && c->offer.empty() &&
               c->have.empty() && c->keep.empty() && c->types.empty());
  }
  FUZZ_CHECK(c->channels.size() <= 256);
  for (const auto& [name, port] : c->channels) {
    FUZZ_CHECK(valid_name(name));
    FUZZ_CHECK(port >= 1 && port <= 65535);
  }
  FUZZ_CHECK(c->control_port >= 0 && c->control_port <= 65535);
  for (const auto& t : c->want) FUZZ_CHECK(wire::valid_topic(t));
  for (const auto& t : c->offer) FUZZ_CHECK(wire::valid_topic(t));
  for (const auto& t : c->have) FUZZ_CHECK(wire::valid_topic(t));
  FUZZ_CHECK(c->have.size() <= wire::kMaxCatalogue);
  FUZZ_CHECK(c->want.size() <= wire::kMaxDemand && c->offer.size() <= wire::kMaxDemand);
  FUZZ_CHECK(c->keep.size() <= wire::kMaxCatalogue);
  for (const auto& [t, n] : c->keep) FUZZ_CHECK(wire::valid_topic(t) && n <= wire::Control::kMaxKeep);
  FUZZ_CHECK(c->types.size() <= wire::kMaxCatalogue);
  for (const auto& [t, ty] : c->types)
    FUZZ_CHECK(wire::valid_topic(t) && wire::valid_type_name(ty.name));
  if (!c->has_demand)
    FUZZ_CHECK(c->want.empty() && c->offer.empty() && c->have.empty() && c->keep.empty() && c->types.empty());

  const std::string text = wire::encode(*c);
  const auto again = wire::decode(text);
  if (!again) {
    std::fprintf(stderr, "fuzz_bridge_frame: re-encoded frame rejected:\n%s\n", text.c_str());
    std::abort();
  }
  FUZZ_CHECK(wire::encode(*again) == text);
  FUZZ_CHECK(again->kind == c->kind);
  FUZZ_CHECK(again->from == c->from);
  FUZZ_CHECK(again->instance == c->instance);
  FUZZ_CHECK(again->link == c->link);
  FUZZ_CHECK(again->t_ns == c->t_ns);
  if (c->kind == wire::Control::Kind::ping) {
    FUZZ_CHECK(again->active == c->active);
    FUZZ_CHECK(again->has_demand == c->has_demand);
    if (c->has_demand) {
      FUZZ_CHECK(again->control_port == c->control_port);
      FUZZ_CHECK(again->channels == c->channels);
      FUZZ_CHECK(again->want == c->want);
      FUZZ_CHECK(again->offer == c->offer);
      FUZZ_CHECK(again->have == c->have);
      FUZZ_CHECK(again->keep == c->keep);
      FUZZ_CHECK(again->types == c->types);
    }
  }
}

void check_data(const std::uint8_t* data, std::size_t size) {
  if (size == 0) return;
  const std::size_t n = data[0];
  if (size - 1 < n) return;
  const std::string_view topic(reinterpret_cast<const char*>(data + 1), n);
  const bool ok = wire::valid_topic(topic);
  FUZZ_CHECK(!ok || (n >= 1 && n <= wire::kMaxTopic));
  const std::size_t rest = size - 1 - n;
  if (!ok || rest != wire::kDataHeader) return;
  const unsigned char* in = data + 1 + n;
  const auto h = wire::decode_header(in);
  unsigned char out[wire::kDataHeader];
  wire::encode_header(h, out);
  FUZZ_CHECK(std::memcmp(in, out, wire::kDataHeader) == 0);
}

void check_topic_word(std::string_view in) {
  if (const auto t = wire::decode_topic(in)) {
    FUZZ_CHECK(wire::valid_topic(*t));
    FUZZ_CHECK(wire::encode_topic(*t) == in);
  }
  const std::string_view t = in.substr(0, wire::kMaxTopic);
  if (!wire::valid_topic(t)) return;
  const std::string w = wire::encode_topic(t);
  for (unsigned char c : w) FUZZ_CHECK(c > ' ' && c != 0x7f);
  const auto back = wire::decode_topic(w);
  FUZZ_CHECK(back && *back == t);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  check_control(std::string_view(reinterpret_cast<const char*>(data), size));
  check_data(data, size);
  check_topic_word(std::string_view(reinterpret_cast<const char*>(data), size));
  return 0;
}
