// libFuzzer target: lcmx::types on hostile input — the `.lcm` parser and registry, the message
// decoder, from_json, and the renderings.
//
// Input: `.lcm` text, then optionally the line "%%" and a body: one selector byte (bit 7: the
// rest is JSON for from_json, else message bytes; bits 0-6: which type of the text, modulo
// their number), then the rest. The message bytes get the type's fingerprint in front, so the
// fuzzer reaches the decoder's body instead of the fingerprint check.
// Invariants (a violation aborts): nothing but types::Error is thrown; a decoded message
// re-encodes to bytes that decode to the same encoding, renders as text and JSON, and its JSON
// reads back with from_json (to the same JSON when it has no escaped bytes); what from_json
// accepts encodes, and the encoding decodes to the same encoding.
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <string_view>
#include <vector>

#include "lcmx/types/types.hpp"

namespace t = lcmx::types;

namespace {

[[noreturn]] void broken(const char* what, const std::string& detail) {
  std::fprintf(stderr, "fuzz_types: %s: %s\n", what, detail.c_str());
  std::abort();
}

void check_message(const t::StructType& type, const std::vector<std::uint8_t>& bytes) {
  t::Value v;
  try {
    v = t::decode(type, bytes.data(), bytes.size());
  } catch (const t::Error&) {
    return;  // hostile bytes: an Error is the contract
  }
  std::vector<std::uint8_t> again;
  try {
    again = t::encode(type, v);
  } catch (const t::Error& e) {
    broken("a decoded message does not encode", e.what());
  }
  try {
    if (t::encode(type, t::decode(type, again.data(), again.size())) != again)
      broken("decode(encode(decoded)) changed", type.full_name());
  } catch (const t::Error& e) {
    broken("a re-encoded message does not decode", e.what());
  }
  (void)t::to_text(v, {.max_array = 4});
  const std::string json = t::to_json(v);
  try {
    const t::Value back = t::from_json(type, json);
    if (json.find("\\u00") == std::string::npos && t::to_json(back) != json)
      broken("from_json(to_json(v)) differs", json.substr(0, 200));
    (void)t::encode(type, back);
  } catch (const t::Error& e) {
    broken("to_json's output does not read back", std::string(e.what()) + " in " + json.substr(0, 200));
  }
}

void check_json(const t::StructType& type, std::string_view text) {
  t::Value v;
  try {
    v = t::from_json(type, text);
  } catch (const t::Error&) {
    return;
  }
  try {
    const auto bytes = t::encode(type, v);
    if (t::encode(type, t::decode(type, bytes.data(), bytes.size())) != bytes)
      broken("a from_json message does not round-trip", type.full_name());
  } catch (const t::Error& e) {
    broken("what from_json accepts does not encode/decode", e.what());
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view in(reinterpret_cast<const char*>(data), size);
  const std::size_t sep = in.find("\n%%\n");
  const std::string_view lcm = in.substr(0, sep);
  t::TypeRegistry reg;
  try {
    reg = t::TypeRegistry::load_texts({{"fuzz.lcm", std::string(lcm)}});
  } catch (const t::Error&) {
    return 0;
  } catch (const std::exception& e) {
    broken("the parser threw something else than types::Error", e.what());
  }
  if (sep == std::string_view::npos || reg.size() == 0) return 0;
  std::string_view body = in.substr(sep + 4);
  if (body.empty()) return 0;
  const auto selector = static_cast<std::uint8_t>(body[0]);
  body.remove_prefix(1);
  const t::StructType& type = *reg.types()[(selector & 0x7f) % reg.size()];
  try {
    if (selector & 0x80) {
      check_json(type, body);
    } else {
      std::vector<std::uint8_t> msg(8 + body.size());
      for (int i = 0; i < 8; ++i) msg[static_cast<std::size_t>(i)] = static_cast<std::uint8_t>(type.fingerprint >> (56 - 8 * i));
      std::copy(body.begin(), body.end(), msg.begin() + 8);
      check_message(type, msg);
      // The registry's lookup by fingerprint finds a type with this fingerprint.
      if (const auto* found = reg.find(type.fingerprint); !found || found->fingerprint != type.fingerprint)
        broken("find(fingerprint) missed", type.full_name());
    }
  } catch (const t::Error& e) {
    broken("an Error escaped a check", e.what());
  }
  return 0;
}
