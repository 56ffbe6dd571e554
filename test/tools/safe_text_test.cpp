// apps/lcmx/safe_text.hpp: what the tools do to names from the network or a file before they
// print them (issue 34 item 6): escapes for a terminal, JSON strings, CSV cells.
#include <catch2/catch.hpp>

#include <string>

#include "safe_text.hpp"

using lcmx::cli::formula_safe;
using lcmx::cli::json_text;
using lcmx::cli::printable;

TEST_CASE("printable: every byte a terminal acts on is escaped, text is left alone", "[tools][trust]") {
  CHECK(printable("CAMERA_FRONT") == "CAMERA_FRONT");
  CHECK(printable("caf\xc3\xa9 \xe2\x89\xa5 \xf0\x9f\x9a\x97") == "caf\xc3\xa9 \xe2\x89\xa5 \xf0\x9f\x9a\x97");  // UTF-8
  CHECK(printable("\x1b]0;owned\x07") == "\\x1b]0;owned\\x07");  // OSC: retitle the terminal
  CHECK(printable("a\nb\tc\rd") == "a\\x0ab\\x09c\\x0dd");           // no fake lines
  CHECK(printable(std::string("a\0b", 3)) == "a\\x00b");
  CHECK(printable("\x7f") == "\\x7f");
  CHECK(printable("\xc2\x9b" "2J") == "\\u009b2J");  // C1 CSI as UTF-8
  CHECK(printable("\x9b" "2J") == "\\x9b2J");        // C1 CSI as a raw byte: not UTF-8
  CHECK(printable("\xc3") == "\\xc3");               // a cut sequence
  CHECK(printable("\xc0\xaf") == "\\xc0\\xaf");      // overlong
  CHECK(printable("\xed\xa0\x80") == "\\xed\\xa0\\x80");  // a surrogate
  CHECK(printable("a\\x1b") == "a\\\\x1b");          // a backslash always starts an escape
  // Nothing left that a terminal acts on, whatever the input.
  std::string all;
  for (int c = 0; c < 256; ++c) all += static_cast<char>(c);
  const auto out = printable(all);
  for (unsigned char c : out) CHECK((c >= 0x20 && c < 0x7f));
}

TEST_CASE("json_text: valid JSON, valid UTF-8, no terminal control", "[tools][trust]") {
  CHECK(json_text("a\"b\\c") == "\"a\\\"b\\\\c\"");
  CHECK(json_text("\x1b[2J\n") == "\"\\u001b[2J\\n\"");
  CHECK(json_text("\x7f\xc2\x9b") == "\"\\u007f\\u009b\"");
  CHECK(json_text("\xff") == "\"\\u00ff\"");  // not UTF-8: its Latin-1 code point, as lcmx::types does
  CHECK(json_text("caf\xc3\xa9") == "\"caf\xc3\xa9\"");
}

TEST_CASE("formula_safe: a CSV text cell a spreadsheet would run is neutralised", "[tools][trust]") {
  for (const char* f : {"=HYPERLINK(\"http://x\",\"y\")", "+1+1", "-1+1", "@SUM(A1)", "\tx", "\rx", "=cmd|' /C calc'!A0"})
    CHECK(formula_safe(f) == "'" + std::string(f));
  CHECK(formula_safe("plain") == "plain");
  CHECK(formula_safe("") == "");
  CHECK(formula_safe("a=b") == "a=b");
}
