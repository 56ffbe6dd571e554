// Text escaping (lcmx/types/detail/text.hpp): JSON string literals.
#include "lcmx/types/detail/text.hpp"

namespace lcmx::types::detail {
namespace {

void append_u00(std::string& out, unsigned c) {
  static constexpr char hex[] = "0123456789abcdef";
  out += "\\u00";
  out += hex[(c >> 4) & 0xf];
  out += hex[c & 0xf];
}

}  // namespace

void append_json_string(std::string& out, std::string_view s, C1Controls c1) {
  out += '"';
  for (std::size_t i = 0; i < s.size();) {
    char32_t cp = 0;
    const std::size_t n = utf8_at(s, i, cp);
    if (n == 0) {  // not UTF-8: the byte as its Latin-1 code point
      append_u00(out, static_cast<unsigned char>(s[i]));
      ++i;
      continue;
    }
    switch (cp) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\r': out += "\\r"; break;
      case '\t': out += "\\t"; break;
      default:
        if (cp < 0x20 || cp == 0x7f || (c1 == C1Controls::escape && cp >= 0x80 && cp <= 0x9f))
          append_u00(out, static_cast<unsigned>(cp));
        else
          out.append(s.substr(i, n));
    }
    i += n;
  }
  out += '"';
}

}  // namespace lcmx::types::detail
