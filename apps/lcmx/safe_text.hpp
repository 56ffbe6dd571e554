// Text from the network or a file, made safe to print (issue 34 item 6). Every name the tools
// print that they did not make themselves — process, node, channel, topic, type, service and
// bridge names, addresses, error texts of other participants, names read from a log file — may
// hold bytes a terminal acts on (an escape sequence that retitles the window, moves the cursor,
// rewrites earlier lines, or answers back on the terminal's input), and a CSV cell may hold a
// formula a spreadsheet runs. Beacons, status messages and log files are written by whoever can
// send on the group or write the file, so the tools escape them at the point they print.
//
//   printable(s)  for text output: every verb's lines, tables, the monitor's screen;
//   json_text(s)  a JSON string literal (RFC 8259), also safe on a terminal;
//   formula_safe(s) a text cell of a CSV file, neutralised against formula injection.
#pragma once

#include <cstdio>
#include <string>
#include <string_view>

namespace lcmx::cli {

namespace detail {
// Length of the valid UTF-8 sequence at s[i] (1 for ASCII), or 0 when the bytes there are
// not UTF-8 (a stray continuation byte, an overlong form, a surrogate, past U+10FFFF, cut).
// `cp` receives the code point.
inline std::size_t utf8_at(std::string_view s, std::size_t i, char32_t& cp) {
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

inline void append_escape(std::string& o, const char* format, unsigned v) {
  char b[12];
  std::snprintf(b, sizeof b, format, v);
  o += b;
}
}  // namespace detail

// `s` for a terminal: C0 controls (newline, tab and ESC included) and DEL as \xNN, C1 controls
// (U+0080..U+009F, which some terminals act on like ESC [) as \u0080.., a byte that is not
// UTF-8 as \xNN, and the backslash as \\ (so a backslash in the output always starts an
// escape). Printable ASCII and every other valid UTF-8 character are left as they are.
inline std::string printable(std::string_view s) {
  std::string o;
  o.reserve(s.size());
  for (std::size_t i = 0; i < s.size();) {
    char32_t cp = 0;
    const std::size_t n = detail::utf8_at(s, i, cp);
    if (n == 0) {
      detail::append_escape(o, "\\x%02x", static_cast<unsigned char>(s[i]));
      ++i;
      continue;
    }
    if (cp == '\\') o += "\\\\";
    else if (cp < 0x20 || cp == 0x7f) detail::append_escape(o, "\\x%02x", static_cast<unsigned>(cp));
    else if (cp >= 0x80 && cp <= 0x9f) detail::append_escape(o, "\\u%04x", static_cast<unsigned>(cp));
    else o.append(s.substr(i, n));
    i += n;
  }
  return o;
}

// A JSON string literal of `s`, quotes included: the escapes JSON requires (", \, C0 controls),
// and DEL and the C1 controls as \u escapes too (valid JSON that no terminal acts on); a byte
// that is not UTF-8 becomes \u00XX, its Latin-1 code point (as lcmx::types::to_json writes
// message strings), so the output is always valid UTF-8.
inline std::string json_text(std::string_view s) {
  std::string o = "\"";
  for (std::size_t i = 0; i < s.size();) {
    char32_t cp = 0;
    std::size_t n = detail::utf8_at(s, i, cp);
    if (n == 0) {
      cp = static_cast<unsigned char>(s[i]);
      n = 1;
      detail::append_escape(o, "\\u%04x", static_cast<unsigned>(cp));
      i += n;
      continue;
    }
    switch (cp) {
      case '"': o += "\\\""; break;
      case '\\': o += "\\\\"; break;
      case '\n': o += "\\n"; break;
      case '\r': o += "\\r"; break;
      case '\t': o += "\\t"; break;
      default:
        if (cp < 0x20 || cp == 0x7f || (cp >= 0x80 && cp <= 0x9f))
          detail::append_escape(o, "\\u%04x", static_cast<unsigned>(cp));
        else
          o.append(s.substr(i, n));
    }
    i += n;
  }
  return o + "\"";
}

// A text value for a CSV cell, neutralised against formula injection (OWASP "CSV injection"):
// a cell starting with =, +, -, @, a tab or CR is what a spreadsheet (Excel, LibreOffice Calc,
// Google Sheets) may run as a formula (=HYPERLINK(...), =cmd|...), so it gets a leading
// apostrophe, which spreadsheets take as "text" and do not display. For text only: numbers the
// exporter writes itself (a negative one starts with -) are data and go through unchanged.
// Quoting (RFC 4180) is the CSV writer's, after this.
inline std::string formula_safe(std::string_view s) {
  if (!s.empty() && (s[0] == '=' || s[0] == '+' || s[0] == '-' || s[0] == '@' || s[0] == '\t' || s[0] == '\r'))
    return "'" + std::string(s);
  return std::string(s);
}

}  // namespace lcmx::cli
