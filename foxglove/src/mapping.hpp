// How LCM types and messages look to a Foxglove client (docs/foxglove.md "Schemas", "Images"):
//  - json_schema(): the JSON Schema of a `.lcm` struct within what Foxglove's and Lichtblick's
//    readers accept (root object, one `type` per field, no `$ref`, no arrays of arrays);
//  - to_json(): a decoded message in the same shape (multi-dimensional arrays flattened
//    row-major, byte arrays as base64 strings, NaN/infinities as null); as one string, or as a
//    Payload whose large byte arrays are shared parts (an image and its view encode it once);
//  - views: a struct shaped like an image or a point cloud is also shown as a foxglove.RawImage,
//    foxglove.CompressedImage or foxglove.PointCloud message;
//  - raw: the documented form of a message whose type is in no `.lcm` file;
//  - from_foxglove_json(): JSON written by a client (Publish panel, service call) into a tree of
//    the type, accepting this file's shape and lcmx's own (types::to_json's).
// Pure functions, no state, any thread (a Base64Cache is one thread's). Errors: types::Error
// (from_foxglove_json names the field).
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "lcmx/types/types.hpp"
#include "payload.hpp"

namespace lcmx::foxglove::detail {

// Base64 (RFC 4648, with padding), as JSON Schema's contentEncoding "base64".
void base64_append(std::string& out, const std::uint8_t* data, std::size_t size);
// Throws types::Error on a character outside the alphabet or a bad length.
types::Bytes base64_decode(std::string_view text);

// `s` as a JSON string literal; invalid UTF-8 bytes become \u00XX (as types::to_json).
void json_string_append(std::string& out, std::string_view s);

// The JSON Schema (a JSON text) of `type` for a Foxglove channel named by its full name.
std::string json_schema(const types::StructType& type);

// The base64 of one decoded message's byte arrays of at least kMin bytes, made once: keyed by
// the bytes' address in the message's tree, so it lives no longer than that tree.
class Base64Cache {
 public:
  static constexpr std::size_t kMin = 64 * 1024;
  std::shared_ptr<const std::string> get(const std::uint8_t* data, std::size_t size);

 private:
  struct Entry {
    const std::uint8_t* data;
    std::size_t size;
    std::shared_ptr<const std::string> text;
  };
  std::vector<Entry> entries_;
};

// The message as one JSON object matching json_schema(type). `value` is a Struct of `type`.
std::string to_json(const types::Value& value);
Payload to_json(const types::Value& value, Base64Cache& cache);

// Viewer-specific shapes a struct may also be shown as.
enum class ViewKind { none, raw_image, compressed_image, point_cloud };
struct View {
  ViewKind kind = ViewKind::none;
  const char* schema_name = "";  // "foxglove.RawImage", ...
  const char* topic_suffix = "";  // the view's topic is CHANNEL + suffix ("/image", "/points")
};
// The view of `type` by the documented convention, or kind none.
View view_of(const types::StructType& type);
// The view's JSON Schema (foxglove's own schema of that message).
std::string view_schema(ViewKind kind);
// The message of `value` in the view's shape; `stamp_ns` is its timestamp. nullopt if this
// message does not fit (e.g. data shorter than height * step).
std::optional<std::string> to_view_json(ViewKind kind, const types::Value& value, std::uint64_t stamp_ns);
std::optional<Payload> to_view_json(ViewKind kind, const types::Value& value, std::uint64_t stamp_ns,
                                    Base64Cache& cache);

// `utime` (int64 microseconds since the epoch) at the top of the type: the message's timestamp
// in nanoseconds; nullopt if the type has none or it is not positive.
bool has_utime(const types::StructType& type);
std::optional<std::uint64_t> utime_ns(const types::Value& value);

// Messages whose fingerprint is in no `.lcm` file: schema "lcmx.unknown".
inline constexpr const char* kUnknownSchemaName = "lcmx.unknown";
std::string unknown_schema();
std::string unknown_json(std::uint64_t fingerprint, const std::uint8_t* data, std::size_t size);

// A client's JSON into a tree of `type` (for types::encode). Beside types::from_json's rules:
// a byte array may be a base64 string, and a multi-dimensional array may be given flattened.
types::Value from_foxglove_json(const types::StructType& type, std::string_view json);

}  // namespace lcmx::foxglove::detail
