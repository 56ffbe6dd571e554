#pragma once
// lcmx::types — a decoded message as a tree, LCM's encoding of it (both ways), and its JSON
// and human-readable renderings.
//
// Errors: decode/encode throw types::Error naming the field (path like "a.b[3]") and what is
// wrong. A truncated or hostile message is an Error, never a crash: array counts are checked
// against the bytes left before anything is allocated, nesting depth is bounded.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>
#include <variant>
#include <vector>

#include "lcmx/types/schema.hpp"

namespace lcmx::types {

struct Value;
struct Field;

// A struct: its fields in declaration order.
struct Struct {
  const StructType* type = nullptr;  // null in a hand-built tree: encode() uses its own type
  std::vector<Field> fields;

  // The field called `name`, or null.
  const Value* find(std::string_view name) const noexcept;
  Value* find(std::string_view name) noexcept;
};

using Array = std::vector<Value>;
using Bytes = std::vector<std::uint8_t>;  // the innermost dimension of a `byte` array

// One node. Integers (int8..int64, scalar `byte`) are int64; `float` is float, `double`
// double; `boolean` bool. Arrays are Array, except the last dimension of a `byte` array, which
// is Bytes (an image is one vector, not millions of nodes).
struct Value {
  std::variant<std::int64_t, double, float, bool, std::string, Bytes, Array, Struct> data;

  Value();  // the integer 0 (defined below, where Field is complete: clang needs it)
  template <class T>
  Value(T&& v) requires(!std::is_same_v<std::remove_cvref_t<T>, Value>)  // NOLINT
      : data(std::forward<T>(v)) {}

  template <class T> bool is() const noexcept { return std::holds_alternative<T>(data); }
  template <class T> const T& as() const { return std::get<T>(data); }
  template <class T> T& as() { return std::get<T>(data); }
};

struct Field {
  std::string name;
  Value value;
};

inline Value::Value() : data(std::int64_t{0}) {}

// Decodes a whole message: the 8-byte fingerprint must be `type`'s, and every byte is used.
// Throws Error: fingerprint mismatch, truncated, trailing bytes, negative or absurd sizes.
Value decode(const StructType& type, const void* data, std::size_t size);
// Looks the type up by the message's fingerprint, then decode(). Throws Error for a message
// shorter than 8 bytes or an unknown fingerprint (the message names it in hex).
Value decode(const TypeRegistry& registry, const void* data, std::size_t size);

// Encodes `value` (a Struct of `type`) with the fingerprint in front (as lcm-gen's encode()).
// Every member must be present by name, no other field; integers in range of their type;
// floats from any number; array lengths equal to their size members' values (or fixed sizes).
// Throws Error naming the field otherwise.
std::vector<std::uint8_t> encode(const StructType& type, const Value& value);

// A tree of `type` with every field zero: numbers 0, strings "", variable arrays empty,
// fixed arrays full of zeros. Throws Error for a type of more than 2^24 nodes or nested
// deeper than 64.
Value zero_value(const StructType& type);

// The part of `value` at `path`: fields separated by '.', array elements by [index], e.g.
// "pose.position[2]", "points[0]", "data[10]" (an element of Bytes is an int64). Empty path:
// the whole value. Returns a copy. Throws Error naming the first part that does not exist
// ("no field 'q' in pose", "index 9 out of range (3 elements) at points[9]") or a bad path.
Value field(const Value& value, std::string_view path);

// One line of JSON: structs are objects (fields in order), arrays and Bytes are arrays of
// numbers, NaN/infinity are null, strings are escaped (invalid UTF-8 bytes become \u00XX).
std::string to_json(const Value& value);

// Parses one JSON object (as to_json writes it, or typed by hand) into a tree of `type`, ready
// for encode(). Rules:
//  - every key must be a field of its struct: an unknown one is an Error naming its path
//    ("from_json: pose.positon: no such field in lcmx_examples.pose_t (its fields: ...)");
//    a key given twice in one object is an Error;
//  - fields not given are zero (as zero_value), in nested structs too;
//  - integer fields (int8..int64, byte) take JSON integers in the type's range (a number with
//    a zero fraction, 2.0 or 1e3, counts as an integer); float/double take any number, and
//    null, "nan", "inf", "-inf" for non-finite values (to_json writes those as null); a float
//    beyond float's range is an Error; boolean takes true/false; string a JSON string;
//    a nested struct an object;
//  - arrays (byte arrays too) are JSON arrays. A fixed dimension must have exactly its length.
//    A variable dimension sets its size member from the array's length: the size member need
//    not be given; if it is, or if another array shares it, the lengths must agree (an Error
//    names both). An array not given takes its size member's value (0 if not known),
//    zero-filled (at most 2^26 elements made so).
// Throws Error "from_json: <path>: <what>" for all of the above, "from_json: invalid JSON: ..."
// (with line and column) for a syntax error. Nesting deeper than 64 structs is an Error.
Value from_json(const StructType& type, std::string_view json);

struct TextOptions {
  std::size_t max_array = 10;  // elements shown per array before "... (N more)"; 0 = all
  int indent = 2;              // spaces per nesting level
};
// Human-readable, one field per line, nested structs indented, long arrays abbreviated.
// Strings are JSON literals whose C0 and C1 controls are escaped (\u0080..\u009f too, unlike
// to_json): safe to print on a terminal. Ends with a newline.
std::string to_text(const Value& value, const TextOptions& options = {});

}  // namespace lcmx::types
