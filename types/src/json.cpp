// JSON text -> Value tree of a StructType (from_json), driven by the schema. The JSON syntax is
// nlohmann/json's (Debian's nlohmann-json3-dev, header-only, private to this file); the rules
// of what a field accepts are here (value.hpp, from_json).
#include <nlohmann/json.hpp>

#include <cmath>
#include <limits>
#include <optional>
#include <set>
#include <unordered_map>

#include "lcmx/types/value.hpp"

namespace lcmx::types {
namespace {

using Json = nlohmann::json;

constexpr int kMaxDepth = 64;                              // nested structs, as the codec
constexpr std::size_t kZeroBudget = std::size_t{1} << 26;  // elements made for arrays not given

std::string kind_of(const Json& j) {
  switch (j.type()) {
    case Json::value_t::null: return "null";
    case Json::value_t::object: return "an object";
    case Json::value_t::array: return "an array";
    case Json::value_t::string: return "a string";
    case Json::value_t::boolean: return "a boolean";
    case Json::value_t::number_integer:
    case Json::value_t::number_unsigned: return "an integer";
    case Json::value_t::number_float: return "a number with a fraction";
    default: return "something else";
  }
}

std::string short_text(const Json& j) {
  std::string s = j.dump(-1, ' ', false, Json::error_handler_t::replace);
  if (s.size() > 40) s = s.substr(0, 37) + "...";
  return s;
}

struct Range {
  std::int64_t lo, hi;
};
Range range_of(Primitive p) {
  switch (p) {
    case Primitive::int8: return {INT8_MIN, INT8_MAX};
    case Primitive::int16: return {INT16_MIN, INT16_MAX};
    case Primitive::int32: return {INT32_MIN, INT32_MAX};
    case Primitive::byte: return {0, 255};
    default: return {std::numeric_limits<std::int64_t>::min(), std::numeric_limits<std::int64_t>::max()};
  }
}

// Per struct being converted: the value of each size member (given, or taken from the first
// array that uses it) and where it came from, for errors.
struct Sizes {
  std::vector<std::optional<std::int64_t>> value;  // by member index
  std::vector<std::string> source;                 // "given", or the array's path
};

class Converter {
 public:
  Struct structure(const StructType& t, const Json& j) {
    if (!j.is_object()) fail("expected an object (" + t.full_name() + "), got " + kind_of(j));
    if (++depth_ > kMaxDepth) fail("nesting deeper than " + std::to_string(kMaxDepth) + " structs");
    // Every key must be a member.
    for (auto it = j.begin(); it != j.end(); ++it) {
      if (t.find_member(it.key())) continue;
      path_.push_back(it.key());
      std::string names;
      for (const Member& m : t.members) names += (names.empty() ? "" : ", ") + m.name;
      fail("no such field in " + t.full_name() + " (its fields: " + (names.empty() ? "none" : names) + ")");
    }
    Sizes sizes;
    sizes.value.resize(t.members.size());
    sizes.source.resize(t.members.size());
    // Size members given explicitly first, then the lengths of the arrays given.
    for (std::size_t i = 0; i < t.members.size(); ++i) {
      const Member& m = t.members[i];
      if (!is_size_member(t, i)) continue;
      auto it = j.find(m.name);
      if (it == j.end()) continue;
      path_.push_back(m.name);
      sizes.value[i] = scalar(m, *it).as<std::int64_t>();
      if (*sizes.value[i] < 0) fail("a size cannot be negative (" + std::to_string(*sizes.value[i]) + ")");
      sizes.source[i] = "given";
      path_.pop_back();
    }
    for (const Member& m : t.members) {
      if (m.dims.empty()) continue;
      auto it = j.find(m.name);
      if (it == j.end()) continue;
      path_.push_back(m.name);
      lengths(t, m, 0, *it, sizes);
      path_.pop_back();
    }
    Struct s;
    s.type = &t;
    s.fields.reserve(t.members.size());
    for (std::size_t i = 0; i < t.members.size(); ++i) {
      const Member& m = t.members[i];
      path_.push_back(m.name);
      auto it = j.find(m.name);
      Value v;
      if (sizes.value[i]) v = *sizes.value[i];
      else if (it != j.end()) v = m.dims.empty() ? scalar(m, *it) : array(m, 0, *it, sizes);
      else v = m.dims.empty() ? zero_scalar(m) : zero_array(t, m, 0, sizes);
      s.fields.push_back({m.name, std::move(v)});
      path_.pop_back();
    }
    --depth_;
    return s;
  }

  [[noreturn]] void fail(const std::string& what) const { throw Error("from_json: " + path() + ": " + what); }

 private:
  std::string path() const {
    std::string s;
    for (const std::string& p : path_) {
      if (!p.empty() && p[0] == '[') s += p;
      else s += (s.empty() ? "" : ".") + p;
    }
    return s.empty() ? "(message)" : s;
  }

  static bool is_size_member(const StructType& t, std::size_t index) {
    for (const Member& m : t.members)
      for (const Dimension& d : m.dims)
        if (d.variable && d.size_member == index) return true;
    return false;
  }

  // Checks the length of every dimension of a given array against fixed sizes and size
  // members, setting size members not known yet. Visits every sub-array (not the elements
  // of the last dimension).
  void lengths(const StructType& t, const Member& m, std::size_t dim, const Json& j, Sizes& sizes) {
    if (!j.is_array()) fail("expected an array, got " + kind_of(j));
    const Dimension& d = m.dims[dim];
    const auto n = static_cast<std::int64_t>(j.size());
    if (!d.variable) {
      if (n != d.fixed)
        fail("has " + std::to_string(n) + " elements, the type says " + std::to_string(d.fixed) + " ([" + d.size + "])");
    } else {
      auto& known = sizes.value[d.size_member];
      const Member& size_member = t.members[d.size_member];
      if (known && *known != n) {
        const std::string& from = sizes.source[d.size_member];
        fail("has " + std::to_string(n) + " elements but its size '" + d.size + "' is " + std::to_string(*known) +
             (from == "given" ? " (given)" : " (the length of " + from + ")"));
      }
      if (!known) {
        const Range r = range_of(*size_member.primitive);
        if (n > r.hi)
          fail("has " + std::to_string(n) + " elements: too many for its size member '" + d.size + "' (" +
               std::string(to_string(*size_member.primitive)) + ")");
        known = n;
        sizes.source[d.size_member] = path();
      }
    }
    if (dim + 1 == m.dims.size()) return;
    for (std::size_t i = 0; i < j.size(); ++i) {
      path_.push_back("[" + std::to_string(i) + "]");
      lengths(t, m, dim + 1, j[i], sizes);
      path_.pop_back();
    }
  }

  Value array(const Member& m, std::size_t dim, const Json& j, const Sizes& sizes) {
    // lengths() checked every dimension already.
    const bool last = dim + 1 == m.dims.size();
    if (last && m.primitive == Primitive::byte) {
      Bytes b;
      b.reserve(j.size());
      for (std::size_t i = 0; i < j.size(); ++i) {
        path_.push_back("[" + std::to_string(i) + "]");
        b.push_back(static_cast<std::uint8_t>(integer(j[i], Primitive::byte)));
        path_.pop_back();
      }
      return b;
    }
    Array a;
    a.reserve(j.size());
    for (std::size_t i = 0; i < j.size(); ++i) {
      path_.push_back("[" + std::to_string(i) + "]");
      a.push_back(last ? scalar(m, j[i]) : array(m, dim + 1, j[i], sizes));
      path_.pop_back();
    }
    return a;
  }

  void charge(std::size_t n) {
    if (n > budget_)
      fail("arrays not given would be zero-filled with more than 2^26 elements (size members too large?)");
    budget_ -= n;
  }

  // An array not given: its fixed sizes and size members' values (0 when unknown), zeros.
  Value zero_array(const StructType& t, const Member& m, std::size_t dim, const Sizes& sizes) {
    const Dimension& d = m.dims[dim];
    const std::int64_t n64 = d.variable ? sizes.value[d.size_member].value_or(0) : d.fixed;
    const auto n = static_cast<std::size_t>(n64);
    const bool last = dim + 1 == m.dims.size();
    charge(std::max<std::size_t>(n, 1));
    if (last && m.primitive == Primitive::byte) return Bytes(n, 0);
    Array a;
    a.reserve(n);
    for (std::size_t i = 0; i < n; ++i) a.push_back(last ? zero_scalar(m) : zero_array(t, m, dim + 1, sizes));
    return a;
  }

  // Values in a tree (a Bytes vector counts its length).
  static std::size_t nodes(const Value& v) {
    if (const auto* b = std::get_if<Bytes>(&v.data)) return 1 + b->size();
    std::size_t n = 1;
    if (const auto* a = std::get_if<Array>(&v.data))
      for (const Value& e : *a) n += nodes(e);
    if (const auto* s = std::get_if<Struct>(&v.data))
      for (const Field& f : s->fields) n += nodes(f.value);
    return n;
  }

  Value zero_scalar(const Member& m) {
    if (!m.primitive) {
      // One zero tree per nested type (zero_value bounds it to 2^24 nodes), copied and charged
      // by its size for every element.
      auto it = zeros_.find(m.nested);
      if (it == zeros_.end()) {
        Value z = zero_value(*m.nested);
        const std::size_t n = nodes(z);
        it = zeros_.emplace(m.nested, std::make_pair(std::move(z), n)).first;
      }
      charge(it->second.second);
      return it->second.first;
    }
    switch (*m.primitive) {
      case Primitive::float32: return 0.0f;
      case Primitive::float64: return 0.0;
      case Primitive::boolean: return false;
      case Primitive::string: return std::string();
      default: return std::int64_t{0};
    }
  }

  std::int64_t integer(const Json& j, Primitive p) {
    const Range r = range_of(p);
    const std::string type(to_string(p));
    if (j.is_number_unsigned()) {
      const auto u = j.get<std::uint64_t>();
      if (u > static_cast<std::uint64_t>(r.hi)) fail(std::to_string(u) + " is out of range for " + type);
      return static_cast<std::int64_t>(u);
    }
    if (j.is_number_integer()) {
      const auto i = j.get<std::int64_t>();
      if (i < r.lo || i > r.hi) fail(std::to_string(i) + " is out of range for " + type);
      return i;
    }
    if (j.is_number_float()) {
      const double d = j.get<double>();
      if (std::trunc(d) != d) fail("expected an integer (" + type + "), got " + short_text(j));
      // [lo, hi] as doubles: -2^63 is exact, 2^63 is the first value above int64's range.
      if (d < static_cast<double>(r.lo) || d >= static_cast<double>(r.hi) + 1.0)
        fail(short_text(j) + " is out of range for " + type);
      return static_cast<std::int64_t>(d);
    }
    fail("expected an integer (" + type + "), got " + kind_of(j));
  }

  double floating(const Json& j, Primitive p) {
    if (j.is_number()) {
      const double d = j.get<double>();
      // Beyond float: what rounds to infinity (FLT_MAX + half its ulp and more; that tie rounds
      // up), so the shortest text of FLT_MAX itself (3.4028235e+38, a bit above it) still reads.
      static const double float_limit =
          static_cast<double>(std::numeric_limits<float>::max()) + std::ldexp(1.0, 103);
      if (p == Primitive::float32 && std::isfinite(d) && std::abs(d) >= float_limit)
        fail(short_text(j) + " is out of range for float");
      return d;
    }
    if (j.is_null()) return std::numeric_limits<double>::quiet_NaN();
    if (j.is_string()) {
      const auto& s = j.get_ref<const std::string&>();
      if (s == "nan" || s == "NaN") return std::numeric_limits<double>::quiet_NaN();
      if (s == "inf" || s == "+inf" || s == "infinity" || s == "Infinity") return std::numeric_limits<double>::infinity();
      if (s == "-inf" || s == "-infinity" || s == "-Infinity") return -std::numeric_limits<double>::infinity();
    }
    fail("expected a number (" + std::string(to_string(p)) + "; null, \"nan\", \"inf\", \"-inf\" for non-finite), got " +
         short_text(j));
  }

  Value scalar(const Member& m, const Json& j) {
    if (!m.primitive) return structure(*m.nested, j);
    switch (*m.primitive) {
      case Primitive::int8:
      case Primitive::int16:
      case Primitive::int32:
      case Primitive::int64:
      case Primitive::byte: return integer(j, *m.primitive);
      case Primitive::float32: return static_cast<float>(floating(j, Primitive::float32));
      case Primitive::float64: return floating(j, Primitive::float64);
      case Primitive::boolean:
        if (!j.is_boolean()) fail("expected true or false, got " + short_text(j));
        return j.get<bool>();
      case Primitive::string:
        if (!j.is_string()) fail("expected a string, got " + kind_of(j));
        return j.get<std::string>();
    }
    fail("bad primitive");
  }

  std::vector<std::string> path_;
  int depth_ = 0;
  std::size_t budget_ = kZeroBudget;
  std::unordered_map<const StructType*, std::pair<Value, std::size_t>> zeros_;
};

// nlohmann's what() is "[json.exception.parse_error.101] parse error at line 1, column 5: ...".
std::string without_id(const char* what) {
  std::string s = what;
  if (!s.empty() && s[0] == '[') {
    if (const auto close = s.find("] "); close != std::string::npos) s.erase(0, close + 2);
  }
  return s;
}

}  // namespace

Value from_json(const StructType& type, std::string_view json) {
  // Duplicate keys are an error (nlohmann keeps the last one silently).
  std::vector<std::set<std::string>> keys;
  std::optional<std::string> duplicate;
  const Json::parser_callback_t check = [&](int, Json::parse_event_t event, Json& parsed) {
    switch (event) {
      case Json::parse_event_t::object_start: keys.emplace_back(); break;
      case Json::parse_event_t::object_end:
        if (!keys.empty()) keys.pop_back();
        break;
      case Json::parse_event_t::key:
        if (!keys.empty() && !keys.back().insert(parsed.get<std::string>()).second && !duplicate)
          duplicate = parsed.get<std::string>();
        break;
      default: break;
    }
    return true;
  };
  Json j;
  try {
    j = Json::parse(json.begin(), json.end(), check);
  } catch (const Json::exception& e) {
    throw Error("from_json: invalid JSON: " + without_id(e.what()));
  }
  if (duplicate) throw Error("from_json: invalid JSON: the key '" + *duplicate + "' appears twice in one object");
  Converter c;
  return c.structure(type, j);
}

}  // namespace lcmx::types
