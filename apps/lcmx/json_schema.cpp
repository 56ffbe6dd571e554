#include "json_schema.hpp"

#include <algorithm>
#include <cstdio>
#include <vector>

#include "log_common.hpp"

namespace lcmx::cli {
namespace {

std::string primitive_schema(types::Primitive p) {
  using P = types::Primitive;
  switch (p) {
    case P::int8: return R"({"type":"integer","minimum":-128,"maximum":127})";
    case P::int16: return R"({"type":"integer","minimum":-32768,"maximum":32767})";
    case P::int32: return R"({"type":"integer","minimum":-2147483648,"maximum":2147483647})";
    case P::int64:
      return R"({"type":"integer","minimum":-9223372036854775808,"maximum":9223372036854775807})";
    case P::byte: return R"({"type":"integer","minimum":0,"maximum":255})";
    case P::float32:
    case P::float64:
      // "number" alone: Foxglove's reader takes no type lists (see json_schema.hpp).
      return R"({"type":"number","description":")" + std::string(types::to_string(p)) +
             R"x(; NaN and infinities are written as null (JSON has no such numbers)"})x";
    case P::boolean: return R"({"type":"boolean"})";
    case P::string: return R"({"type":"string"})";
  }
  return "{}";
}

// Builds schemas inline; a type met again inside itself (LCM allows recursion through
// variable-length arrays) becomes a "$ref": "#" for the root, "#/$defs/<full name>" otherwise.
struct Builder {
  const types::StructType* root = nullptr;
  std::vector<const types::StructType*> stack;   // types being inlined, outermost first
  std::vector<const types::StructType*> needed;  // $defs to emit
  std::string struct_schema(const types::StructType& t, bool top);
  std::string member_schema(const types::StructType& owner, const types::Member& m, std::size_t d);
};

// The schema of member `m` from dimension `d` inwards.
std::string Builder::member_schema(const types::StructType& owner, const types::Member& m, std::size_t d) {
  if (d == m.dims.size()) {
    if (m.primitive) return primitive_schema(*m.primitive);
    if (m.nested == nullptr) return "{}";
    if (std::find(stack.begin(), stack.end(), m.nested) != stack.end()) {
      if (m.nested == root) return R"({"$ref":"#"})";
      if (std::find(needed.begin(), needed.end(), m.nested) == needed.end()) needed.push_back(m.nested);
      return R"({"$ref":)" + json_str("#/$defs/" + m.nested->full_name()) + "}";
    }
    return struct_schema(*m.nested, false);
  }
  const auto& dim = m.dims[d];
  std::string s = R"({"type":"array","items":)" + member_schema(owner, m, d + 1);
  if (dim.variable) {
    s += R"(,"description":)" + json_str("length: the value of member " + owner.members.at(dim.size_member).name);
  } else {
    const auto n = std::to_string(dim.fixed);
    s += R"(,"minItems":)" + n + R"(,"maxItems":)" + n;
  }
  return s + "}";
}

std::string Builder::struct_schema(const types::StructType& t, bool top) {
  stack.push_back(&t);
  std::string s = "{";
  if (top) s += R"("$schema":"https://json-schema.org/draft/2020-12/schema",)";
  s += R"("title":)" + json_str(t.full_name());
  char fp[24];
  std::snprintf(fp, sizeof fp, "0x%016llx", static_cast<unsigned long long>(t.fingerprint));
  std::string desc = "LCM type " + t.full_name() + ", fingerprint " + fp;
  if (!t.file.empty()) desc += ", " + t.file + ":" + std::to_string(t.line);
  if (!t.constants.empty()) {
    desc += "; constants:";
    for (const auto& c : t.constants) desc += " " + c.name + "=" + c.text;
  }
  s += R"(,"description":)" + json_str(desc) + R"(,"type":"object","properties":{)";
  for (std::size_t i = 0; i < t.members.size(); ++i)
    s += (i ? "," : "") + json_str(t.members[i].name) + ":" + member_schema(t, t.members[i], 0);
  s += R"(},"required":[)";
  for (std::size_t i = 0; i < t.members.size(); ++i) s += (i ? "," : "") + json_str(t.members[i].name);
  s += R"(],"additionalProperties":false)";
  stack.pop_back();
  if (top) {
    // $defs of the recursive types met (each may need others).
    std::string defs;
    for (std::size_t i = 0; i < needed.size(); ++i) {
      stack = {needed[i]};
      std::string d = struct_schema(*needed[i], false);
      defs += (i ? "," : "") + json_str(needed[i]->full_name()) + ":" + d;
    }
    stack.clear();
    if (!defs.empty()) s += R"(,"$defs":{)" + defs + "}";
  }
  return s + "}";
}

// Why Foxglove's JSON Schema reader cannot show `t`, or "".
std::string foxglove_problem(const types::StructType& t, std::vector<const types::StructType*>& stack) {
  if (std::find(stack.begin(), stack.end(), &t) != stack.end()) return t.full_name() + " contains itself";
  stack.push_back(&t);
  std::string why;
  for (const auto& m : t.members) {
    if (m.dims.size() > 1) why = "multi-dimensional array " + t.full_name() + "." + m.name;
    else if (m.nested) why = foxglove_problem(*m.nested, stack);
    if (!why.empty()) break;
  }
  stack.pop_back();
  return why;
}

}  // namespace

std::string foxglove_unsupported(const types::StructType& type) {
  std::vector<const types::StructType*> stack;
  return foxglove_problem(type, stack);
}

std::string json_schema(const types::StructType& type) {
  Builder b;
  b.root = &type;
  return b.struct_schema(type, true);
}

}  // namespace lcmx::cli
