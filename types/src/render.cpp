// JSON and human-readable renderings of a Value tree.
#include <charconv>
#include <cmath>

#include "lcmx/types/value.hpp"

namespace lcmx::types {
namespace {

template <class F>
void append_float(std::string& out, F f) {
  if (!std::isfinite(f)) {
    out += std::isnan(f) ? "nan" : (f > 0 ? "inf" : "-inf");
    return;
  }
  char buf[64];
  const auto r = std::to_chars(buf, buf + sizeof buf, f);  // shortest round-trip
  out.append(buf, r.ptr);
}

// Length of the valid UTF-8 sequence at s[i], or 0.
std::size_t utf8_sequence(std::string_view s, std::size_t i) {
  const auto c = static_cast<unsigned char>(s[i]);
  std::size_t n = 0;
  std::uint32_t cp = 0;
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

void append_json_string(std::string& out, std::string_view s) {
  static const char* hex = "0123456789abcdef";
  out += '"';
  for (std::size_t i = 0; i < s.size(); ++i) {
    const auto c = static_cast<unsigned char>(s[i]);
    switch (c) {
      case '"': out += "\\\""; continue;
      case '\\': out += "\\\\"; continue;
      case '\n': out += "\\n"; continue;
      case '\r': out += "\\r"; continue;
      case '\t': out += "\\t"; continue;
      default: break;
    }
    if (c < 0x20 || c == 0x7f) {
      out += "\\u00";
      out += hex[c >> 4];
      out += hex[c & 0xf];
    } else if (c < 0x80) {
      out += static_cast<char>(c);
    } else if (const std::size_t n = utf8_sequence(s, i)) {
      out.append(s.substr(i, n));
      i += n - 1;
    } else {  // not UTF-8: the byte as its Latin-1 code point
      out += "\\u00";
      out += hex[c >> 4];
      out += hex[c & 0xf];
    }
  }
  out += '"';
}

void json(std::string& out, const Value& v) {
  std::visit(
      [&out](const auto& x) {
        using T = std::decay_t<decltype(x)>;
        if constexpr (std::is_same_v<T, std::int64_t>) {
          out += std::to_string(x);
        } else if constexpr (std::is_same_v<T, double> || std::is_same_v<T, float>) {
          if (x == 0 && std::signbit(x)) out += "-0.0";  // "-0" would read back as the integer 0
          else if (std::isfinite(x)) append_float(out, x);
          else out += "null";
        } else if constexpr (std::is_same_v<T, bool>) {
          out += x ? "true" : "false";
        } else if constexpr (std::is_same_v<T, std::string>) {
          append_json_string(out, x);
        } else if constexpr (std::is_same_v<T, Bytes>) {
          out += '[';
          for (std::size_t i = 0; i < x.size(); ++i) {
            if (i) out += ',';
            out += std::to_string(x[i]);
          }
          out += ']';
        } else if constexpr (std::is_same_v<T, Array>) {
          out += '[';
          for (std::size_t i = 0; i < x.size(); ++i) {
            if (i) out += ',';
            json(out, x[i]);
          }
          out += ']';
        } else {
          out += '{';
          for (std::size_t i = 0; i < x.fields.size(); ++i) {
            if (i) out += ',';
            append_json_string(out, x.fields[i].name);
            out += ':';
            json(out, x.fields[i].value);
          }
          out += '}';
        }
      },
      v.data);
}

// Scalars and arrays without structs fit on one line.
bool is_inline(const Value& v) {
  if (v.is<Struct>()) return false;
  if (const auto* a = std::get_if<Array>(&v.data))
    return a->empty() || is_inline(a->front());
  return true;
}

void inline_text(std::string& out, const Value& v, const TextOptions& o) {
  std::visit(
      [&](const auto& x) {
        using T = std::decay_t<decltype(x)>;
        if constexpr (std::is_same_v<T, std::int64_t>) {
          out += std::to_string(x);
        } else if constexpr (std::is_same_v<T, double> || std::is_same_v<T, float>) {
          append_float(out, x);
        } else if constexpr (std::is_same_v<T, bool>) {
          out += x ? "true" : "false";
        } else if constexpr (std::is_same_v<T, std::string>) {
          append_json_string(out, x);
        } else if constexpr (std::is_same_v<T, Bytes>) {
          static const char* hex = "0123456789abcdef";
          out += "<" + std::to_string(x.size()) + " bytes";
          const std::size_t shown = o.max_array == 0 ? x.size() : std::min(x.size(), o.max_array);
          if (shown) out += ':';
          for (std::size_t i = 0; i < shown; ++i) {
            out += ' ';
            out += hex[x[i] >> 4];
            out += hex[x[i] & 0xf];
          }
          if (shown < x.size()) out += " ...";
          out += '>';
        } else if constexpr (std::is_same_v<T, Array>) {
          out += '[';
          const std::size_t shown = o.max_array == 0 ? x.size() : std::min(x.size(), o.max_array);
          for (std::size_t i = 0; i < shown; ++i) {
            if (i) out += ", ";
            inline_text(out, x[i], o);
          }
          if (shown < x.size()) out += ", ... (" + std::to_string(x.size() - shown) + " more)";
          out += ']';
        } else {
          out += "{...}";
        }
      },
      v.data);
}

void block_text(std::string& out, const Value& v, const TextOptions& o, int level);

void entry_text(std::string& out, std::string_view label, const Value& v, const TextOptions& o, int level) {
  out.append(static_cast<std::size_t>(level * o.indent), ' ');
  out += label;
  out += ':';
  if (is_inline(v)) {
    out += ' ';
    inline_text(out, v, o);
    out += '\n';
  } else {
    if (const auto* a = std::get_if<Array>(&v.data)) out += " [" + std::to_string(a->size()) + "]";
    out += '\n';
    block_text(out, v, o, level + 1);
  }
}

void block_text(std::string& out, const Value& v, const TextOptions& o, int level) {
  if (const auto* s = std::get_if<Struct>(&v.data)) {
    for (const Field& f : s->fields) entry_text(out, f.name, f.value, o, level);
    return;
  }
  const Array& a = v.as<Array>();
  const std::size_t shown = o.max_array == 0 ? a.size() : std::min(a.size(), o.max_array);
  for (std::size_t i = 0; i < shown; ++i) entry_text(out, "[" + std::to_string(i) + "]", a[i], o, level);
  if (shown < a.size()) {
    out.append(static_cast<std::size_t>(level * o.indent), ' ');
    out += "... (" + std::to_string(a.size() - shown) + " more)\n";
  }
}

}  // namespace

std::string to_json(const Value& value) {
  std::string out;
  json(out, value);
  return out;
}

std::string to_text(const Value& value, const TextOptions& options) {
  std::string out;
  if (is_inline(value)) {
    inline_text(out, value, options);
    out += '\n';
  } else {
    block_text(out, value, options, 0);
  }
  return out;
}

}  // namespace lcmx::types
