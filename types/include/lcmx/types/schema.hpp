#pragma once
// lcmx::types — LCM types read at run time from `.lcm` files: the schema, the parser, the
// fingerprint and the registry. Depends on nothing of lcmx (C++20 std only).
//
// Errors: everything here throws `types::Error` (or its `types::ParseError`, which carries the
// file, line and column of a bad `.lcm` file). "Not found" is a null pointer / empty optional.
// Thread safety: a TypeRegistry is immutable after it is built; concurrent const use is safe.
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

namespace lcmx::types {

// Registry, codec and rendering faults (unknown type, truncated or hostile message, a tree that
// does not fit its type). what() names the type, field or fingerprint involved.
class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(what) {}
};

// A bad `.lcm` file. what() is "file:line:col: message" (line and column from 1).
class ParseError : public Error {
 public:
  ParseError(std::string file, int line, int column, const std::string& message);
  const std::string& file() const noexcept { return file_; }
  int line() const noexcept { return line_; }
  int column() const noexcept { return column_; }
  const std::string& message() const noexcept { return message_; }

 private:
  std::string file_;
  int line_;
  int column_;
  std::string message_;
};

// LCM's primitive types. `byte` is unsigned (0..255), `boolean` one byte (non-zero = true).
enum class Primitive { int8, int16, int32, int64, float32, float64, string, boolean, byte };

// The `.lcm` spelling: "int8_t", ..., "float", "double", "string", "boolean", "byte".
std::string_view to_string(Primitive p) noexcept;
std::optional<Primitive> primitive_from_name(std::string_view name) noexcept;
// Fewest bytes one value takes encoded: 1, 2, 4 or 8; a string 5 (int32 length + its NUL).
std::size_t min_encoded_size(Primitive p) noexcept;

struct StructType;

struct Dimension {
  bool variable = false;   // [n] (an earlier integer member) rather than [4]
  std::string size;        // as written in the file: "4", "0x10", "n" (it is hashed as written)
  std::int64_t fixed = 0;  // !variable: the number of elements
  std::size_t size_member = 0;  // variable: index of the size member in StructType::members
};

struct Member {
  std::string name;
  // Primitive members: the primitive's name. Others: the package-qualified type name (a name
  // without '.' is taken to be in the declaring file's package, as lcm-gen does).
  std::string type_name;
  std::optional<Primitive> primitive;  // empty for a nested struct
  const StructType* nested = nullptr;  // set when the registry resolves names; else null
  std::vector<Dimension> dims;         // outermost first; empty for a scalar
  int line = 0, column = 0;            // where the member is declared
};

struct Constant {
  Primitive type = Primitive::int32;  // int8..int64, float, double
  std::string name;
  std::string text;            // the value as written ("0x7f", "-1", "2.5")
  std::int64_t integer = 0;    // integer constants
  double floating = 0.0;       // float/double constants
};

struct StructType {
  std::string package;  // "" when the file has no package
  std::string name;     // short name
  std::vector<Member> members;
  std::vector<Constant> constants;
  std::string file;  // declaring file (as given to the parser)
  int line = 0;      // line of `struct`
  std::int64_t base_hash = 0;     // lcm-gen's per-struct hash (members only, no nesting)
  std::uint64_t fingerprint = 0;  // lcm-gen's getHash(): set by TypeRegistry (recursive)
  std::size_t min_encoded_size = 0;  // smallest encoding without the 8-byte fingerprint

  std::string full_name() const { return package.empty() ? name : package + "." + name; }
  const Member* find_member(std::string_view member_name) const noexcept;
};

// Parses one `.lcm` file's text. `file` is only used in errors and StructType::file.
// Returns its structs in file order, with base_hash set (nested names not resolved).
// Throws: ParseError (syntax, an unknown or non-integer array size member, duplicate member,
// constant out of range, `enum` — not supported, lcm-gen's C++ emitter has no enums).
std::vector<StructType> parse(std::string_view text, const std::string& file);
// Reads and parses a file. Throws: Error if it cannot be read, ParseError.
std::vector<StructType> parse_file(const std::filesystem::path& path);

// lcm-gen's hash of one struct: member names, primitive type names, dimension modes and sizes.
std::int64_t base_hash(const StructType& type);

// The fingerprint at the front of an encoded message (first 8 bytes, big-endian), or empty if
// fewer than 8 bytes.
std::optional<std::uint64_t> message_fingerprint(const void* data, std::size_t size) noexcept;

// Type path: `.lcm` files, loaded and resolved together.
class TypeRegistry {
 public:
  TypeRegistry() = default;  // empty
  TypeRegistry(TypeRegistry&&) noexcept = default;
  TypeRegistry& operator=(TypeRegistry&&) noexcept = default;
  TypeRegistry(const TypeRegistry&) = delete;
  TypeRegistry& operator=(const TypeRegistry&) = delete;

  // Loads every path: a file is parsed whatever its name; a directory is searched recursively
  // for `*.lcm` (sorted, symlinked directories followed once). Then resolves nested type names
  // and computes every fingerprint.
  // Throws: Error for a missing path, an unknown nested type (naming it, the member and
  // file:line), two different definitions of one full name; ParseError for a bad file.
  // The same type defined identically in two files is kept once.
  static TypeRegistry load(const std::vector<std::filesystem::path>& paths);
  // Loads texts instead of files: pairs of (file name used in errors, contents).
  static TypeRegistry load_texts(const std::vector<std::pair<std::string, std::string>>& texts);

  // `LCMX_TYPES_PATH` split at ':' (empty entries skipped); empty if unset.
  static std::vector<std::filesystem::path> env_paths();
  // `--types` values when any were given (each may itself be a ':'-separated list), else
  // env_paths(). Convenience for the tools.
  static std::vector<std::filesystem::path> paths_or_env(const std::vector<std::string>& types_args);

  // By package-qualified name ("pkg.type"; a type without package by its short name).
  const StructType* find(std::string_view full_name) const noexcept;
  // By fingerprint. Types with identical layouts share one; the first loaded is returned.
  const StructType* find(std::uint64_t fingerprint) const noexcept;
  // find() that throws Error naming the type ("unknown type 'x.y' (not in the type path)").
  const StructType& at(std::string_view full_name) const;

  // Every type, in load order.
  const std::vector<std::unique_ptr<StructType>>& types() const noexcept { return types_; }
  std::size_t size() const noexcept { return types_.size(); }

 private:
  void add(std::vector<StructType> parsed);
  void resolve();

  std::vector<std::unique_ptr<StructType>> types_;  // stable addresses for Member::nested
  std::unordered_map<std::string, const StructType*> by_name_;
  std::unordered_map<std::uint64_t, const StructType*> by_fingerprint_;
};

}  // namespace lcmx::types
