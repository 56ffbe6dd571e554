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

#include "lcmx/types/detail/text.hpp"

namespace lcmx::cli {

namespace detail {
using types::detail::utf8_at;

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
// message strings: the same function, lcmx/types/detail/text.hpp), so the output is always
// valid UTF-8.
inline std::string json_text(std::string_view s) {
  std::string o;
  types::detail::append_json_string(o, s, types::detail::C1Controls::escape);
  return o;
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
