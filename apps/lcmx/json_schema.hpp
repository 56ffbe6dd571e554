// JSON Schema (draft 2020-12) of an LCM type, describing exactly what lcmx::types::to_json()
// emits for a message of that type (used as the `jsonschema` schema of `lcmx log export
// --format mcap`, whose messages are to_json() text):
//  - a struct is an object with every member required, no other property, in declaration
//    order; nested structs are inlined, titled with their full name; a type that contains
//    itself (through a variable-length array) is a "$ref" to "#" (the message's type) or to
//    "#/$defs/<package.name>";
//  - int8/int16/int32/int64 are "integer" with their type's minimum and maximum (int64 values
//    are written as exact decimal integers: readers that parse JSON numbers as doubles, like
//    JavaScript's, lose precision beyond 2^53);
//  - byte is "integer" 0..255, also inside byte arrays (arrays of numbers, not base64);
//  - float and double are "number"; to_json() writes NaN and infinities as null, which the
//    description says (a strict validator must accept null for "number": a type list
//    ["number","null"] would be exact, but Foxglove's reader rejects type lists);
//  - boolean is "boolean", string is "string";
//  - each array dimension is an "array"; fixed sizes set minItems = maxItems, variable ones
//    name their size member in the description.
#pragma once

#include <string>

#include "lcmx/types/schema.hpp"

namespace lcmx::cli {

// The schema as one line of JSON. Never throws for a type the registry resolved.
std::string json_schema(const types::StructType& type);

// Foxglove's JSON Schema reader (Foxglove/Lichtblick `parseJsonSchema`) knows objects with
// properties, booleans, strings, numbers and integers, and arrays of those — not arrays of
// arrays nor "$ref". Returns why a message of `type` cannot be shown there ("multi-dimensional
// array pkg.t.m", "pkg.t contains itself"), or "" when it can.
std::string foxglove_unsupported(const types::StructType& type);

}  // namespace lcmx::cli
