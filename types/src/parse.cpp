// The `.lcm` type language: tokenizer, recursive-descent parser, lcm-gen's per-struct hash.
// Grammar (lcm-gen's, lcmgen/lcmgen.c):
//   file   := { "package" NAME ";" | "struct" NAME "{" { member } "}" }
//   member := "const" CTYPE NAME "=" VALUE { "," NAME "=" VALUE } ";"
//           | TYPE NAME { "[" SIZE "]" } { "," NAME { "[" SIZE "]" } } ";"
// Comments (// and /* */) may appear anywhere between tokens.
#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cfloat>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <sstream>

#include "lcmx/types/schema.hpp"

namespace lcmx::types {

ParseError::ParseError(std::string file, int line, int column, const std::string& message)
    : Error(file + ":" + std::to_string(line) + ":" + std::to_string(column) + ": " + message),
      file_(std::move(file)), line_(line), column_(column), message_(message) {}

std::string_view to_string(Primitive p) noexcept {
  switch (p) {
    case Primitive::int8: return "int8_t";
    case Primitive::int16: return "int16_t";
    case Primitive::int32: return "int32_t";
    case Primitive::int64: return "int64_t";
    case Primitive::float32: return "float";
    case Primitive::float64: return "double";
    case Primitive::string: return "string";
    case Primitive::boolean: return "boolean";
    case Primitive::byte: return "byte";
  }
  return "?";
}

std::optional<Primitive> primitive_from_name(std::string_view name) noexcept {
  static constexpr Primitive all[] = {Primitive::int8,    Primitive::int16,   Primitive::int32,
                                      Primitive::int64,   Primitive::float32, Primitive::float64,
                                      Primitive::string,  Primitive::boolean, Primitive::byte};
  for (Primitive p : all)
    if (to_string(p) == name) return p;
  return std::nullopt;
}

const Member* StructType::find_member(std::string_view member_name) const noexcept {
  for (const Member& m : members)
    if (m.name == member_name) return &m;
  return nullptr;
}

namespace {

// ---- lcm-gen's hash (lcmgen.c hash_update / hash_string_update / lcm_struct_hash) ----
// v = ((v << 8) ^ (v >> 55)) + c on int64 with an arithmetic right shift, and c a (signed)
// char: lengths and dimension counts are truncated to a char as lcm-gen passes them.
std::int64_t hash_update(std::int64_t v, signed char c) {
  const auto u = static_cast<std::uint64_t>(v);
  const auto shifted = static_cast<std::uint64_t>(v >> 55);  // arithmetic (C++20)
  return static_cast<std::int64_t>(((u << 8) ^ shifted) + static_cast<std::uint64_t>(std::int64_t{c}));
}

std::int64_t hash_string(std::int64_t v, std::string_view s) {
  v = hash_update(v, static_cast<signed char>(s.size()));
  for (char c : s) v = hash_update(v, static_cast<signed char>(c));
  return v;
}

bool is_integer_type(Primitive p) {
  return p == Primitive::int8 || p == Primitive::int16 || p == Primitive::int32 ||
         p == Primitive::int64;
}

bool is_identifier(std::string_view s) {
  if (s.empty() || !(std::isalpha(static_cast<unsigned char>(s[0])) || s[0] == '_')) return false;
  return std::all_of(s.begin(), s.end(),
                     [](char c) { return std::isalnum(static_cast<unsigned char>(c)) || c == '_'; });
}

// A dotted name: identifiers separated by single dots.
bool is_type_name(std::string_view s) {
  std::size_t start = 0;
  while (true) {
    const std::size_t dot = s.find('.', start);
    if (!is_identifier(s.substr(start, dot == std::string_view::npos ? dot : dot - start)))
      return false;
    if (dot == std::string_view::npos) return true;
    start = dot + 1;
  }
}

struct Token {
  std::string text;  // empty at end of file
  int line = 0, column = 0;
  bool eof() const { return text.empty(); }
};

class Lexer {
 public:
  Lexer(std::string_view text, const std::string& file) : text_(text), file_(file) {}

  // Next token, comments and whitespace skipped. Throws ParseError for an unterminated comment
  // or a character that starts no token.
  Token next() {
    skip();
    Token t;
    t.line = line_;
    t.column = column_;
    if (pos_ >= text_.size()) return t;
    const char c = text_[pos_];
    if (std::string_view("{}[];,=").find(c) != std::string_view::npos) {
      t.text = std::string(1, c);
      advance();
      return t;
    }
    // A word: identifiers, dotted names, numbers (with sign, hex, exponent).
    auto word_char = [](char ch) {
      return std::isalnum(static_cast<unsigned char>(ch)) || ch == '_' || ch == '.' ||
             ch == '-' || ch == '+';
    };
    if (!word_char(c))
      throw ParseError(file_, t.line, t.column, std::string("unexpected character '") + c + "'");
    while (pos_ < text_.size() && word_char(text_[pos_])) {
      t.text.push_back(text_[pos_]);
      advance();
    }
    return t;
  }

 private:
  void advance() {
    if (text_[pos_] == '\n') {
      ++line_;
      column_ = 1;
    } else {
      ++column_;
    }
    ++pos_;
  }
  void skip() {
    while (pos_ < text_.size()) {
      const char c = text_[pos_];
      if (std::isspace(static_cast<unsigned char>(c))) {
        advance();
      } else if (c == '/' && pos_ + 1 < text_.size() && text_[pos_ + 1] == '/') {
        while (pos_ < text_.size() && text_[pos_] != '\n') advance();
      } else if (c == '/' && pos_ + 1 < text_.size() && text_[pos_ + 1] == '*') {
        const int line = line_, column = column_;
        advance();
        advance();
        while (true) {
          if (pos_ + 1 >= text_.size())
            throw ParseError(file_, line, column, "comment '/*' is never closed");
          if (text_[pos_] == '*' && text_[pos_ + 1] == '/') {
            advance();
            advance();
            break;
          }
          advance();
        }
      } else {
        return;
      }
    }
  }

  std::string_view text_;
  const std::string& file_;
  std::size_t pos_ = 0;
  int line_ = 1, column_ = 1;
};

class Parser {
 public:
  Parser(std::string_view text, const std::string& file) : lexer_(text, file), file_(file) {
    take();
  }

  std::vector<StructType> parse_all() {
    std::vector<StructType> out;
    while (!tok_.eof()) {
      if (tok_.text == "package") {
        take();
        const Token name = expect_word("a package name");
        if (!is_type_name(name.text)) fail(name, "invalid package name '" + name.text + "'");
        package_ = name.text;
        expect(";");
      } else if (tok_.text == "struct") {
        const Token kw = take();
        StructType s = parse_struct(kw);
        for (const StructType& prior : out)
          if (prior.name == s.name && prior.package == s.package)
            fail(kw, "type '" + s.full_name() + "' is declared twice in this file (first at line " +
                         std::to_string(prior.line) + ")");
        out.push_back(std::move(s));
      } else if (tok_.text == "enum") {
        fail(tok_, "'enum' is not supported (lcm-gen's C++ emitter has no enums)");
      } else {
        fail(tok_, "expected 'package' or 'struct', found '" + tok_.text + "'");
      }
    }
    return out;
  }

 private:
  [[noreturn]] void fail(const Token& at, const std::string& message) const {
    throw ParseError(file_, at.line, at.column, message);
  }
  Token take() {
    Token t = std::move(tok_);
    tok_ = lexer_.next();
    return t;
  }
  bool accept(std::string_view s) {
    if (tok_.text != s) return false;
    take();
    return true;
  }
  void expect(std::string_view s) {
    if (tok_.eof()) fail(tok_, "expected '" + std::string(s) + "', found end of file");
    if (tok_.text != s) fail(tok_, "expected '" + std::string(s) + "', found '" + tok_.text + "'");
    take();
  }
  Token expect_word(const std::string& what) {
    if (tok_.eof()) fail(tok_, "expected " + what + ", found end of file");
    if (tok_.text.size() == 1 && std::string_view("{}[];,=").find(tok_.text[0]) != std::string_view::npos)
      fail(tok_, "expected " + what + ", found '" + tok_.text + "'");
    return take();
  }
  Token expect_identifier(const std::string& what) {
    Token t = expect_word(what);
    if (!is_identifier(t.text))
      fail(t, "invalid " + what + " '" + t.text + "' (must be [A-Za-z_][A-Za-z0-9_]*)");
    return t;
  }

  StructType parse_struct(const Token& kw) {
    StructType s;
    s.file = file_;
    s.line = kw.line;
    s.package = package_;
    const Token name = expect_word("a struct name");
    if (!is_type_name(name.text)) fail(name, "invalid struct name '" + name.text + "'");
    s.name = name.text;
    if (const auto dot = s.name.rfind('.'); dot != std::string::npos) {  // `struct pkg.name_t`
      s.package = s.name.substr(0, dot);
      s.name = s.name.substr(dot + 1);
    }
    expect("{");
    while (!accept("}")) {
      if (tok_.eof()) fail(tok_, "end of file inside struct '" + s.name + "' (missing '}')");
      if (tok_.text == "const") {
        take();
        parse_const(s);
      } else if (tok_.text == "struct" || tok_.text == "enum") {
        fail(tok_, "nested '" + tok_.text + "' declarations are not supported by LCM");
      } else {
        parse_members(s);
      }
    }
    s.base_hash = base_hash(s);
    return s;
  }

  void check_new_name(const StructType& s, const Token& name) const {
    if (s.find_member(name.text))
      fail(name, "duplicate member name '" + name.text + "' in struct '" + s.name + "'");
    for (const Constant& c : s.constants)
      if (c.name == name.text)
        fail(name, "duplicate member name '" + name.text + "' in struct '" + s.name + "'");
  }

  void parse_const(StructType& s) {
    const Token type_tok = expect_word("a constant type");
    const auto type = primitive_from_name(type_tok.text);
    if (!type || *type == Primitive::string || *type == Primitive::boolean || *type == Primitive::byte)
      fail(type_tok, "invalid type '" + type_tok.text +
                         "' for a constant (int8_t, int16_t, int32_t, int64_t, float, double)");
    do {
      const Token name = expect_identifier("constant name");
      check_new_name(s, name);
      expect("=");
      const Token value = expect_word("a constant value");
      Constant c;
      c.type = *type;
      c.name = name.text;
      c.text = value.text;
      const char* begin = value.text.c_str();
      char* end = nullptr;
      errno = 0;
      if (is_integer_type(*type)) {
        const long long v = std::strtoll(begin, &end, 0);
        if (end == begin || *end != '\0') fail(value, "expected an integer value, found '" + value.text + "'");
        std::int64_t lo = std::numeric_limits<std::int64_t>::min(), hi = std::numeric_limits<std::int64_t>::max();
        if (*type == Primitive::int8) lo = INT8_MIN, hi = INT8_MAX;
        if (*type == Primitive::int16) lo = INT16_MIN, hi = INT16_MAX;
        if (*type == Primitive::int32) lo = INT32_MIN, hi = INT32_MAX;
        if (errno == ERANGE || v < lo || v > hi)
          fail(value, "value " + value.text + " out of range for " + type_tok.text);
        c.integer = v;
      } else {
        const double v = std::strtod(begin, &end);
        if (end == begin || *end != '\0')
          fail(value, "expected a floating point value, found '" + value.text + "'");
        if (*type == Primitive::float32 && (v > FLT_MAX || v < -FLT_MAX))
          fail(value, "value " + value.text + " out of range for float");
        c.floating = v;
      }
      s.constants.push_back(std::move(c));
    } while (accept(","));
    expect(";");
  }

  void parse_members(StructType& s) {
    const Token type_tok = expect_word("a type name");
    const auto prim = primitive_from_name(type_tok.text);
    if (!prim && !is_type_name(type_tok.text))
      fail(type_tok, "invalid type name '" + type_tok.text + "'");
    std::string type_name = type_tok.text;
    if (!prim && type_name.find('.') == std::string::npos && !package_.empty())
      type_name = package_ + "." + type_name;  // lcm-gen: the file's current package
    do {
      const Token name = expect_identifier("member name");
      check_new_name(s, name);
      Member m;
      m.name = name.text;
      m.type_name = type_name;
      m.primitive = prim;
      m.line = name.line;
      m.column = name.column;
      while (accept("[")) {
        const Token size = expect_word("an array size");
        m.dims.push_back(parse_dimension(s, size));
        expect("]");
      }
      s.members.push_back(std::move(m));
    } while (accept(","));
    expect(";");
  }

  Dimension parse_dimension(const StructType& s, const Token& size) const {
    Dimension d;
    d.size = size.text;
    if (std::isdigit(static_cast<unsigned char>(size.text[0]))) {
      char* end = nullptr;
      errno = 0;
      const long long v = std::strtoll(size.text.c_str(), &end, 0);
      if (*end != '\0') fail(size, "invalid array size '" + size.text + "'");
      if (errno == ERANGE || v <= 0 || v > INT32_MAX)
        fail(size, "array size " + size.text + " must be > 0 and fit an int32_t");
      d.fixed = v;
      return d;
    }
    if (!is_identifier(size.text))
      fail(size, "invalid array size '" + size.text + "' (a number or an earlier integer member)");
    for (const Constant& c : s.constants) {
      if (c.name != size.text) continue;
      // Newer lcm-gen: a constant as size is a fixed dimension, hashed as the constant's text.
      if (!is_integer_type(c.type)) fail(size, "array size constant '" + c.name + "' must be an integer");
      if (c.integer <= 0 || c.integer > INT32_MAX)
        fail(size, "array size constant '" + c.name + "' must be > 0 and fit an int32_t");
      d.fixed = c.integer;
      d.size = c.text;
      return d;
    }
    for (std::size_t i = 0; i < s.members.size(); ++i) {
      const Member& m = s.members[i];
      if (m.name != size.text) continue;
      if (!m.dims.empty()) fail(size, "array size '" + size.text + "' must not be an array");
      if (!m.primitive || !is_integer_type(*m.primitive))
        fail(size, "array size '" + size.text + "' must be an integer member (int8_t..int64_t), not " +
                       m.type_name);
      d.variable = true;
      d.size_member = i;
      return d;
    }
    fail(size, "unknown array size '" + size.text +
                   "': size members must be declared before the array that uses them");
  }

  Lexer lexer_;
  const std::string& file_;
  Token tok_;
  std::string package_;
};

}  // namespace

std::int64_t base_hash(const StructType& type) {
  std::int64_t v = 0x12345678;
  for (const Member& m : type.members) {
    v = hash_string(v, m.name);
    if (m.primitive) v = hash_string(v, to_string(*m.primitive));
    v = hash_update(v, static_cast<signed char>(m.dims.size()));
    for (const Dimension& d : m.dims) {
      v = hash_update(v, d.variable ? 1 : 0);  // lcm-gen: LCM_CONST = 0, LCM_VAR = 1
      v = hash_string(v, d.size);
    }
  }
  return v;
}

std::vector<StructType> parse(std::string_view text, const std::string& file) {
  return Parser(text, file).parse_all();
}

std::vector<StructType> parse_file(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error("cannot read type file " + path.string());
  std::ostringstream ss;
  ss << in.rdbuf();
  if (in.bad()) throw Error("cannot read type file " + path.string());
  return parse(ss.str(), path.string());
}

std::optional<std::uint64_t> message_fingerprint(const void* data, std::size_t size) noexcept {
  if (size < 8) return std::nullopt;
  const auto* p = static_cast<const std::uint8_t*>(data);
  std::uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | p[i];
  return v;
}

}  // namespace lcmx::types
