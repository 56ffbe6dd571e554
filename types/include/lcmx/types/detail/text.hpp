#pragma once
// Text escaping, the one implementation for lcmx::types' renderings (to_json, to_text) and the
// lcmx tools' escaping of names from the network (apps/lcmx/safe_text.hpp). Installed, not
// stable (detail/).

#include <cstddef>
#include <string>
#include <string_view>

namespace lcmx::types::detail {

// Length of the valid UTF-8 sequence at s[i] (1 for ASCII), or 0 when the bytes there are not
// UTF-8 (a stray continuation byte, an overlong form, a surrogate, past U+10FFFF, cut).
// `cp` receives the code point. Requires i < s.size().
inline std::size_t utf8_at(std::string_view s, std::size_t i, char32_t& cp) noexcept {
  const auto c = static_cast<unsigned char>(s[i]);
  std::size_t n = 0;
  if (c < 0x80) {
    cp = c;
    return 1;
  }
  if (c >= 0xc2 && c <= 0xdf) n = 2, cp = c & 0x1f;
  else if (c >= 0xe0 && c <= 0xef) n = 3, cp = c & 0x0f;
  else if (c >= 0xf0 && c <= 0xf4) n = 4, cp = c & 0x07;
  else return 0;
  if (i + n > s.size()) return 0;
  for (std::size_t k = 1; k < n; ++k) {
    const auto cc = static_cast<unsigned char>(s[i + k]);
    if ((cc & 0xc0) != 0x80) return 0;
    cp = (cp << 6) | (cc & 0x3f);
  }
  if ((n == 3 && (cp < 0x800 || (cp >= 0xd800 && cp <= 0xdfff))) || (n == 4 && (cp < 0x10000 || cp > 0x10ffff)))
    return 0;
  return n;
}

// What append_json_string does with the C1 controls (U+0080..U+009F as UTF-8), which some
// terminals act on like ESC [.
enum class C1Controls {
  keep,    // as they are (to_json)
  escape,  // as \u0080.. (to_text's strings, the tools' json_text: safe on a terminal)
};

// Appends `s` to `out` as a JSON string literal (RFC 8259), quotes included: " and \ escaped,
// \n \r \t by name, the other C0 controls and DEL as \u00XX, the C1 controls as `c1` says, a
// byte that is not UTF-8 as \u00XX (its Latin-1 code point), so the output is valid UTF-8;
// every other character as it is.
void append_json_string(std::string& out, std::string_view s, C1Controls c1);

}  // namespace lcmx::types::detail
