// The TOML validation shared by lcmx's config files (the Message Bridge's, bridge/src/config.cpp,
// and the DDS gateway's, dds/src/config.cpp): parse with toml++ behind a pre-scan that keeps
// it clear of a toml++ 3.3.0 bug, and check keys one by one with errors that name the file,
// the key path and the line. Installed, not stable (detail/).
//
// Errors: every function throws bridge::ConfigError ("file: key: what (line N)").
// Needs toml++ (Debian: libtomlplusplus-dev) in the including target.
#pragma once

#include <arpa/inet.h>

#include <algorithm>
#include <cstdint>
#include <filesystem>
#include <initializer_list>
#include <string>
#include <string_view>
#include <toml++/toml.h>
#include <vector>

#include "lcmx/bridge/config.hpp"

namespace lcmx::bridge::detail {

// 1..max characters of [A-Za-z0-9_-].
inline bool valid_name(std::string_view s, std::size_t max) {
  if (s.empty() || s.size() > max) return false;
  return std::all_of(s.begin(), s.end(), [](char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' || c == '-';
  });
}

inline bool valid_ipv4(const std::string& s) {
  in_addr a{};
  return ::inet_pton(AF_INET, s.c_str(), &a) == 1;
}

// toml++ 3.3.0 (Debian 12) reaches __builtin_unreachable() (undefined behaviour) when it asks
// whether a non-ASCII character is whitespace (its is_non_ascii_horizontal_whitespace has no
// case for most code points; upstream marzer/tomlplusplus#190 and #295, fixed after 3.3.0),
// which it does wherever it scans a bare token, a key or the whitespace after a line-ending
// backslash: `name = "a"é`, `x = 3.o[".ƹ`, `s = """` + newline + `# """é` (found by
// fuzz_bridge_config, three times). Telling those places apart means lexing exactly as toml++
// does, so the rule is simple instead: non-ASCII characters only in comment lines (first
// non-blank character '#'). Such a line is a comment in every state in which toml++ goes on
// reading, except inside a multi-line string (a single-line string or an inline table cannot
// span lines: toml++ stops at the newline with an error). So a file with a multi-line string
// delimiter (""" or ''', anywhere) must be ASCII throughout. With ASCII input toml++ never
// reaches that code: escapes decode into string values, never into a whitespace test. lcmx's
// keys and values (names, addresses, channel globs, key paths) are ASCII. Returns the 1-based
// line of the first refused non-ASCII byte, or 0.
inline std::size_t refused_non_ascii_line(std::string_view t) {
  const bool multi_line_strings =
      t.find(R"(""")") != std::string_view::npos || t.find("'''") != std::string_view::npos;
  std::size_t line = 1;
  for (std::size_t i = 0; i < t.size(); ++line) {
    const std::size_t end = std::min(t.find('\n', i), t.size());
    const std::size_t first = t.find_first_not_of(" \t", i);
    const bool comment = !multi_line_strings && first < end && t[first] == '#';
    if (!comment)
      for (std::size_t k = i; k < end; ++k)
        if (static_cast<unsigned char>(t[k]) >= 0x80) return line;
    i = end + 1;
  }
  return 0;
}

// The pre-scan above, then toml::parse. Throws ConfigError "file: line N: what".
inline toml::table parse_toml(std::string_view text, const std::filesystem::path& file) {
  if (const auto line = refused_non_ascii_line(text))
    throw ConfigError(file.string() + ": line " + std::to_string(line) +
                      ": a non-ASCII character (allowed only in comment lines, and nowhere in a file with a "
                      "multi-line string)");
  try {
    return toml::parse(text, file.string());
  } catch (const toml::parse_error& e) {
    throw ConfigError(file.string() + ": line " + std::to_string(e.source().begin.line) + ": " +
                      std::string(e.description()));
  }
}

// Errors name the file, the key path and, when known, the line.
class Checker {
 public:
  explicit Checker(std::filesystem::path file) : file_(std::move(file)) {}

  [[noreturn]] void fail(const std::string& key, const std::string& what, const toml::node* at = nullptr) const {
    std::string msg = file_.string() + ": " + key + ": " + what;
    if (at && at->source().begin.line > 0) msg += " (line " + std::to_string(at->source().begin.line) + ")";
    throw ConfigError(msg);
  }

  // Every key of `t` must be in `known`.
  void only(const toml::table& t, const std::string& prefix, std::initializer_list<std::string_view> known) const {
    for (auto&& [k, v] : t) {
      if (std::find(known.begin(), known.end(), k.str()) == known.end()) {
        std::string list;
        for (auto x : known) list += (list.empty() ? "" : ", ") + std::string(x);
        fail(prefix + std::string(k.str()), "unknown key (expected one of: " + list + ")", &v);
      }
    }
  }

  std::string string(const toml::table& t, const std::string& prefix, std::string_view key, bool required,
                     std::string def = {}) const {
    const toml::node* n = t.get(key);
    if (!n) {
      if (required) fail(prefix + std::string(key), "missing (required)");
      return def;
    }
    if (!n->is_string()) fail(prefix + std::string(key), "must be a string", n);
    return n->as_string()->get();
  }

  std::int64_t integer(const toml::table& t, const std::string& prefix, std::string_view key, bool required,
                       std::int64_t def, std::int64_t lo, std::int64_t hi) const {
    const toml::node* n = t.get(key);
    if (!n) {
      if (required) fail(prefix + std::string(key), "missing (required)");
      return def;
    }
    const std::string range = "must be an integer from " + std::to_string(lo) + " to " + std::to_string(hi);
    if (!n->is_integer()) fail(prefix + std::string(key), range, n);
    const std::int64_t v = n->as_integer()->get();
    if (v < lo || v > hi) fail(prefix + std::string(key), range + " (got " + std::to_string(v) + ")", n);
    return v;
  }

  bool boolean(const toml::table& t, const std::string& prefix, std::string_view key, bool def) const {
    const toml::node* n = t.get(key);
    if (!n) return def;
    if (!n->is_boolean()) fail(prefix + std::string(key), "must be true or false", n);
    return n->as_boolean()->get();
  }

  std::vector<std::string> strings(const toml::table& t, const std::string& prefix, std::string_view key,
                                   bool required, std::vector<std::string> def = {}) const {
    const toml::node* n = t.get(key);
    if (!n) {
      if (required) fail(prefix + std::string(key), "missing (required)");
      return def;
    }
    const toml::array* a = n->as_array();
    if (!a) fail(prefix + std::string(key), "must be an array of strings", n);
    std::vector<std::string> out;
    for (std::size_t i = 0; i < a->size(); ++i) {
      const toml::node& e = *a->get(i);
      if (!e.is_string())
        fail(prefix + std::string(key) + "[" + std::to_string(i) + "]", "must be a string", &e);
      out.push_back(e.as_string()->get());
    }
    return out;
  }

  // An array of tables ([[x]] or [ {..}, {..} ]); empty if absent.
  std::vector<const toml::table*> tables(const toml::table& t, const std::string& prefix, std::string_view key) const {
    std::vector<const toml::table*> out;
    const toml::node* n = t.get(key);
    if (!n) return out;
    const toml::array* a = n->as_array();
    if (!a) fail(prefix + std::string(key), "must be an array of tables ([[" + std::string(key) + "]])", n);
    for (std::size_t i = 0; i < a->size(); ++i) {
      const toml::node& e = *a->get(i);
      if (!e.is_table())
        fail(prefix + std::string(key) + "[" + std::to_string(i) + "]", "must be a table", &e);
      out.push_back(e.as_table());
    }
    return out;
  }

  // A path from the file: relative ones are relative to the file's folder.
  std::filesystem::path path(const std::string& value) const {
    std::filesystem::path p(value);
    if (p.is_relative()) p = file_.parent_path() / p;
    return p;
  }

 private:
  std::filesystem::path file_;
};

}  // namespace lcmx::bridge::detail
