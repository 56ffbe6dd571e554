// JSON and human-readable renderings of a Value tree.
#include <charconv>
#include <cmath>

#include "lcmx/types/detail/text.hpp"
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

void append_json_string(std::string& out, std::string_view s) {
  detail::append_json_string(out, s, detail::C1Controls::keep);
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
          // Text is for terminals (lcmx echo, lcmx action): the C1 controls escaped too, so a
          // string from the network cannot act like ESC [ on the user's terminal.
          detail::append_json_string(out, x, detail::C1Controls::escape);
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
