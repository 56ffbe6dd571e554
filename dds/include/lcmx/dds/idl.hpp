// LCM types as OMG IDL for Cyclone DDS's idlc (`lcmx idl`, docs/dds.md "Typed mode").
//
// Mapping: package a.b -> modules a::b; struct -> @final struct; int8_t int8, int16_t short,
// int32_t long, int64_t long long, float float, double double, boolean boolean, byte octet,
// string string; nested types by their IDL scoped name; x[3][4] (fixed sizes) -> x[3][4];
// x[n] (one variable dimension) -> sequence<T> x, with the size member n kept as a field.
// ROS 2 naming (`ros2`): modules a::b::msg::dds_ and type T_, as rmw_cyclonedds expects.
// Not supported (types::Error): a variable dimension together with other dimensions.
// Member names that are IDL keywords are escaped with '_' (IDL's escape; the field keeps its name).
#pragma once

#include <string>
#include <vector>

#include "lcmx/types/schema.hpp"

namespace lcmx::dds {

// Throws types::Error naming the type and member if `type` (or a type it nests) has a member
// typed mode cannot map.
void check_typed(const types::StructType& type);

// The DDS type name of `type`: "a::b::T", or "a::b::msg::dds_::T_" with ros2.
std::string dds_type_name(const types::StructType& type, bool ros2);

// IDL for `roots` and every type they nest, each once, nested types first. Throws types::Error
// (check_typed).
std::string to_idl(const std::vector<const types::StructType*>& roots, bool ros2);

}  // namespace lcmx::dds
