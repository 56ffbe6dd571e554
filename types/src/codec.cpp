// LCM's encoding (big-endian, lcm_coretypes.h) of a Value tree, both ways, driven by the schema.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <unordered_map>

#include "lcmx/types/value.hpp"

namespace lcmx::types {

const Value* Struct::find(std::string_view name) const noexcept {
  for (const Field& f : fields)
    if (f.name == name) return &f.value;
  return nullptr;
}
Value* Struct::find(std::string_view name) noexcept {
  for (Field& f : fields)
    if (f.name == name) return &f.value;
  return nullptr;
}

namespace {

constexpr int kMaxDepth = 64;  // nested structs; deeper only in hostile recursive messages

// "a.b[3].c" for errors, built only when one is thrown.
struct PathItem {
  std::string_view name;  // a member, or empty for an array index
  std::size_t index = 0;
};
std::string format_path(const std::vector<PathItem>& path) {
  std::string s;
  for (const PathItem& p : path) {
    if (!p.name.empty()) {
      if (!s.empty()) s += '.';
      s += p.name;
    } else {
      s += '[' + std::to_string(p.index) + ']';
    }
  }
  return s.empty() ? "(message)" : s;
}

std::string hex64(std::uint64_t v) {
  static const char* digits = "0123456789abcdef";
  std::string s = "0x";
  for (int i = 60; i >= 0; i -= 4) s += digits[(v >> i) & 0xf];
  return s;
}

// Smallest encoding of one element of `m` below dimension `dim` (0 when a variable dimension
// below it may be empty).
std::size_t element_min_size(const Member& m, std::size_t dim) {
  std::size_t count = 1;
  for (std::size_t i = dim; i < m.dims.size(); ++i) {
    if (m.dims[i].variable) return 0;
    count *= static_cast<std::size_t>(m.dims[i].fixed);  // <= 2^31 each; checked below
    if (count > (std::size_t{1} << 40)) return std::size_t{1} << 40;
  }
  const std::size_t element = m.primitive ? min_encoded_size(*m.primitive) : m.nested->min_encoded_size;
  if (element != 0 && count > (std::size_t{1} << 48) / element) return std::size_t{1} << 48;
  return count * element;
}

class Decoder {
 public:
  Decoder(const std::uint8_t* p, std::size_t size)
      : p_(p), left_(size), budget_(16 * size + 4096) {}

  Struct decode_struct(const StructType& t) {
    if (++depth_ > kMaxDepth) fail("nesting deeper than " + std::to_string(kMaxDepth) + " structs");
    Struct s;
    s.type = &t;
    s.fields.reserve(t.members.size());
    for (const Member& m : t.members) {
      path_.push_back({m.name, 0});
      Value v = m.dims.empty() ? scalar(m) : array(m, 0, s);
      s.fields.push_back({m.name, std::move(v)});
      path_.pop_back();
    }
    --depth_;
    return s;
  }

  std::size_t left() const { return left_; }

  [[noreturn]] void fail(const std::string& what) const {
    throw Error("decode: " + format_path(path_) + ": " + what);
  }

 private:
  void need(std::size_t n) {
    if (left_ < n)
      fail("message truncated (" + std::to_string(n) + " bytes needed, " + std::to_string(left_) + " left)");
  }
  std::uint64_t be(std::size_t n) {
    need(n);
    std::uint64_t v = 0;
    for (std::size_t i = 0; i < n; ++i) v = (v << 8) | p_[i];
    p_ += n;
    left_ -= n;
    return v;
  }
  void charge(std::size_t nodes) {
    if (nodes > budget_) fail("more elements than a message of this size can hold (hostile sizes?)");
    budget_ -= nodes;
  }

  Value scalar(const Member& m) {
    if (!m.primitive) return decode_struct(*m.nested);
    switch (*m.primitive) {
      case Primitive::int8: return std::int64_t{static_cast<std::int8_t>(be(1))};
      case Primitive::byte: return static_cast<std::int64_t>(be(1));
      case Primitive::boolean: return be(1) != 0;
      case Primitive::int16: return std::int64_t{static_cast<std::int16_t>(be(2))};
      case Primitive::int32: return std::int64_t{static_cast<std::int32_t>(be(4))};
      case Primitive::int64: return static_cast<std::int64_t>(be(8));
      case Primitive::float32: {
        const auto bits = static_cast<std::uint32_t>(be(4));
        float f;
        std::memcpy(&f, &bits, 4);
        return f;
      }
      case Primitive::float64: {
        const std::uint64_t bits = be(8);
        double d;
        std::memcpy(&d, &bits, 8);
        return d;
      }
      case Primitive::string: {
        const auto len = static_cast<std::int32_t>(be(4));  // includes the NUL
        if (len < 1) fail("string length " + std::to_string(len) + " (must be >= 1)");
        need(static_cast<std::size_t>(len));
        std::string s(reinterpret_cast<const char*>(p_), static_cast<std::size_t>(len) - 1);
        p_ += len;  // the NUL is skipped unchecked, as lcm-gen's decoders do
        left_ -= static_cast<std::size_t>(len);
        return s;
      }
    }
    fail("bad primitive");
  }

  Value array(const Member& m, std::size_t dim, const Struct& s) {
    const Dimension& d = m.dims[dim];
    std::int64_t n = d.fixed;
    if (d.variable) {
      n = s.fields[d.size_member].value.as<std::int64_t>();
      if (n < 0) fail("negative array size " + std::to_string(n) + " (from '" + m.dims[dim].size + "')");
    }
    const auto count = static_cast<std::size_t>(n);
    const std::size_t min = element_min_size(m, dim + 1);
    if (min != 0 && count > left_ / min)
      fail("message truncated: " + std::to_string(count) + " elements need at least " +
           std::to_string(min) + " bytes each, " + std::to_string(left_) + " left");
    const bool last = dim + 1 == m.dims.size();
    if (last && m.primitive == Primitive::byte) {
      need(count);
      charge(1);
      Bytes b(p_, p_ + count);
      p_ += count;
      left_ -= count;
      return b;
    }
    charge(count);
    Array a;
    a.reserve(count);
    for (std::size_t i = 0; i < count; ++i) {
      path_.push_back({{}, i});
      a.push_back(last ? scalar(m) : array(m, dim + 1, s));
      path_.pop_back();
    }
    return a;
  }

  const std::uint8_t* p_;
  std::size_t left_;
  std::size_t budget_;  // Values still allowed (bounds memory for zero-size elements)
  int depth_ = 0;
  std::vector<PathItem> path_;
};

class Encoder {
 public:
  explicit Encoder(std::vector<std::uint8_t>& out) : out_(out) {}

  void encode_struct(const StructType& t, const Value& v) {
    if (!v.is<Struct>()) fail("expected a struct " + t.full_name());
    if (++depth_ > kMaxDepth) fail("nesting deeper than " + std::to_string(kMaxDepth) + " structs");
    const Struct& s = v.as<Struct>();
    std::vector<const Value*> values(t.members.size());
    for (std::size_t i = 0; i < t.members.size(); ++i) {
      const Member& m = t.members[i];
      if (i < s.fields.size() && s.fields[i].name == m.name) {
        values[i] = &s.fields[i].value;
      } else {
        values[i] = s.find(m.name);
      }
      if (!values[i]) {
        path_.push_back({m.name, 0});
        fail("missing field of " + t.full_name());
      }
    }
    if (s.fields.size() != t.members.size()) {
      for (const Field& f : s.fields) {
        path_.push_back({f.name, 0});
        if (!t.find_member(f.name)) fail("no such field in " + t.full_name());
        path_.pop_back();
      }
      fail("a field is given twice");
    }
    for (std::size_t i = 0; i < t.members.size(); ++i) {
      const Member& m = t.members[i];
      path_.push_back({m.name, 0});
      if (m.dims.empty()) {
        scalar(m, *values[i]);
      } else {
        array(m, 0, *values[i], values);
      }
      path_.pop_back();
    }
    --depth_;
  }

 private:
  [[noreturn]] void fail(const std::string& what) const {
    throw Error("encode: " + format_path(path_) + ": " + what);
  }
  void put(std::uint64_t v, std::size_t n) {
    for (std::size_t i = n; i-- > 0;) out_.push_back(static_cast<std::uint8_t>(v >> (8 * i)));
  }
  std::int64_t integer(const Value& v, std::int64_t lo, std::int64_t hi, std::string_view type) {
    if (!v.is<std::int64_t>()) fail("expected an integer (" + std::string(type) + ")");
    const std::int64_t i = v.as<std::int64_t>();
    if (i < lo || i > hi) fail(std::to_string(i) + " is out of range for " + std::string(type));
    return i;
  }
  double number(const Value& v) {
    if (v.is<double>()) return v.as<double>();
    if (v.is<float>()) return v.as<float>();
    if (v.is<std::int64_t>()) return static_cast<double>(v.as<std::int64_t>());
    fail("expected a number");
  }

  void scalar(const Member& m, const Value& v) {
    if (!m.primitive) return encode_struct(*m.nested, v);
    switch (*m.primitive) {
      case Primitive::int8: put(static_cast<std::uint64_t>(integer(v, INT8_MIN, INT8_MAX, "int8_t")), 1); return;
      case Primitive::byte: put(static_cast<std::uint64_t>(integer(v, 0, 255, "byte")), 1); return;
      case Primitive::int16: put(static_cast<std::uint64_t>(integer(v, INT16_MIN, INT16_MAX, "int16_t")), 2); return;
      case Primitive::int32: put(static_cast<std::uint64_t>(integer(v, INT32_MIN, INT32_MAX, "int32_t")), 4); return;
      case Primitive::int64:
        put(static_cast<std::uint64_t>(integer(v, std::numeric_limits<std::int64_t>::min(),
                                               std::numeric_limits<std::int64_t>::max(), "int64_t")), 8);
        return;
      case Primitive::boolean:
        if (!v.is<bool>()) fail("expected a boolean");
        put(v.as<bool>() ? 1 : 0, 1);
        return;
      case Primitive::float32: {
        const auto f = static_cast<float>(number(v));
        std::uint32_t bits;
        std::memcpy(&bits, &f, 4);
        put(bits, 4);
        return;
      }
      case Primitive::float64: {
        const double d = number(v);
        std::uint64_t bits;
        std::memcpy(&bits, &d, 8);
        put(bits, 8);
        return;
      }
      case Primitive::string: {
        if (!v.is<std::string>()) fail("expected a string");
        const std::string& s = v.as<std::string>();
        if (s.size() >= static_cast<std::size_t>(INT32_MAX)) fail("string too long");
        put(s.size() + 1, 4);
        out_.insert(out_.end(), s.begin(), s.end());
        out_.push_back(0);
        return;
      }
    }
  }

  void array(const Member& m, std::size_t dim, const Value& v, const std::vector<const Value*>& values) {
    const Dimension& d = m.dims[dim];
    std::int64_t expected = d.fixed;
    if (d.variable) expected = values[d.size_member]->as<std::int64_t>();  // encoded already: int
    const bool last = dim + 1 == m.dims.size();
    std::size_t n = 0;
    if (v.is<Bytes>() && last && m.primitive == Primitive::byte) {
      n = v.as<Bytes>().size();
    } else if (v.is<Array>()) {
      n = v.as<Array>().size();
    } else {
      fail("expected an array");
    }
    if (expected < 0 || static_cast<std::uint64_t>(expected) != n)
      fail("array has " + std::to_string(n) + " elements but its size " +
           (d.variable ? "member '" + d.size + "' is " : "is ") + std::to_string(expected));
    if (v.is<Bytes>()) {
      const Bytes& b = v.as<Bytes>();
      out_.insert(out_.end(), b.begin(), b.end());
      return;
    }
    const Array& a = v.as<Array>();
    for (std::size_t i = 0; i < n; ++i) {
      path_.push_back({{}, i});
      if (last) {
        scalar(m, a[i]);
      } else {
        array(m, dim + 1, a[i], values);
      }
      path_.pop_back();
    }
  }

  std::vector<std::uint8_t>& out_;
  int depth_ = 0;
  std::vector<PathItem> path_;
};

// Nodes in a zero tree of `t` (variable arrays empty), saturated at `cap`; memoized per type.
std::size_t zero_nodes(const StructType& t, std::size_t cap, int depth,
                       std::unordered_map<const StructType*, std::size_t>& memo) {
  if (depth > kMaxDepth)
    throw Error("zero_value: " + t.full_name() + " nests deeper than " + std::to_string(kMaxDepth));
  if (auto it = memo.find(&t); it != memo.end()) return it->second;
  std::size_t total = 1;
  for (const Member& m : t.members) {
    std::size_t count = 1, nodes = 1;
    for (const Dimension& d : m.dims) {
      count = d.variable ? 0 : std::min(cap, count * static_cast<std::size_t>(d.fixed));
      nodes = std::min(cap, nodes + count);
    }
    if (count == 0) {  // an empty variable array (a recursive type's only way to nest itself)
      total = std::min(cap, total + nodes);
      continue;
    }
    const std::size_t element = m.primitive ? 1 : zero_nodes(*m.nested, cap, depth + 1, memo);
    total = std::min(cap, total + nodes + (count > cap / std::max<std::size_t>(element, 1) ? cap : count * element));
  }
  memo.emplace(&t, total);
  return total;
}

// zero_value's walk; `budget` bounds the nodes made (fixed arrays of huge types).
struct ZeroMaker {
  std::size_t budget = std::size_t{1} << 24;

  void charge(const StructType& t, std::size_t n) {
    if (n > budget) throw Error("zero_value: " + t.full_name() + " has more than 2^24 elements");
    budget -= n;
  }
  Value array(const StructType& t, const Member& m, std::size_t dim, int depth) {
    const Dimension& d = m.dims[dim];
    const auto n = d.variable ? 0 : static_cast<std::size_t>(d.fixed);
    const bool last = dim + 1 == m.dims.size();
    charge(t, last && m.primitive == Primitive::byte ? 1 : n);
    if (last && m.primitive == Primitive::byte) return Bytes(n, 0);
    Array a;
    a.reserve(n);
    for (std::size_t i = 0; i < n; ++i) a.push_back(last ? scalar(m, depth) : array(t, m, dim + 1, depth));
    return a;
  }
  Value scalar(const Member& m, int depth) {
    if (!m.primitive) return structure(*m.nested, depth + 1);
    switch (*m.primitive) {
      case Primitive::float32: return 0.0f;
      case Primitive::float64: return 0.0;
      case Primitive::boolean: return false;
      case Primitive::string: return std::string();
      default: return std::int64_t{0};
    }
  }
  Value structure(const StructType& t, int depth) {
    if (depth > kMaxDepth)
      throw Error("zero_value: " + t.full_name() + " nests deeper than " + std::to_string(kMaxDepth));
    charge(t, t.members.size());
    Struct s;
    s.type = &t;
    for (const Member& m : t.members)
      s.fields.push_back({m.name, m.dims.empty() ? scalar(m, depth) : array(t, m, 0, depth)});
    return s;
  }
};

}  // namespace

Value decode(const StructType& type, const void* data, std::size_t size) {
  const auto fp = message_fingerprint(data, size);
  if (!fp) throw Error("decode: message of " + std::to_string(size) + " bytes has no fingerprint (< 8 bytes)");
  if (*fp != type.fingerprint)
    throw Error("decode: fingerprint " + hex64(*fp) + " is not " + type.full_name() + "'s (" +
                hex64(type.fingerprint) + ")");
  Decoder d(static_cast<const std::uint8_t*>(data) + 8, size - 8);
  Value v = d.decode_struct(type);
  if (d.left() != 0)
    throw Error("decode: " + std::to_string(d.left()) + " trailing bytes after a " + type.full_name());
  return v;
}

Value decode(const TypeRegistry& registry, const void* data, std::size_t size) {
  const auto fp = message_fingerprint(data, size);
  if (!fp) throw Error("decode: message of " + std::to_string(size) + " bytes has no fingerprint (< 8 bytes)");
  const StructType* t = registry.find(*fp);
  if (!t) throw Error("decode: unknown fingerprint " + hex64(*fp) + " (no type in the type path has it)");
  return decode(*t, data, size);
}

std::vector<std::uint8_t> encode(const StructType& type, const Value& value) {
  std::vector<std::uint8_t> out;
  out.reserve(8 + std::min<std::size_t>(type.min_encoded_size, std::size_t{1} << 20));
  for (int i = 7; i >= 0; --i) out.push_back(static_cast<std::uint8_t>(type.fingerprint >> (8 * i)));
  Encoder(out).encode_struct(type, value);
  return out;
}

Value field(const Value& value, std::string_view path) {
  const Value* v = &value;
  std::size_t i = 0;
  std::string done;  // the path walked so far, for errors
  auto bad = [&](const std::string& why) { throw Error("field '" + std::string(path) + "': " + why); };
  while (i < path.size()) {
    if (path[i] == '[') {
      const std::size_t close = path.find(']', i);
      if (close == std::string_view::npos || close == i + 1) bad("expected [index]");
      std::size_t index = 0;
      for (std::size_t k = i + 1; k < close; ++k) {
        if (path[k] < '0' || path[k] > '9' || index > (std::size_t{1} << 40)) bad("bad index '" + std::string(path.substr(i + 1, close - i - 1)) + "'");
        index = index * 10 + static_cast<std::size_t>(path[k] - '0');
      }
      const std::string parent = done.empty() ? "(message)" : done;
      done += std::string(path.substr(i, close + 1 - i));
      const bool last = close + 1 == path.size();
      if (const auto* b = std::get_if<Bytes>(&v->data)) {
        if (index >= b->size())
          bad("index " + std::to_string(index) + " out of range (" + std::to_string(b->size()) + " elements) at " + done);
        if (!last) bad(done + " is a byte, it has no parts");
        return static_cast<std::int64_t>((*b)[index]);
      }
      const auto* a = std::get_if<Array>(&v->data);
      if (!a) bad(parent + " is not an array");
      if (index >= a->size())
        bad("index " + std::to_string(index) + " out of range (" + std::to_string(a->size()) + " elements) at " + done);
      v = &(*a)[index];
      i = close + 1;
      continue;
    }
    if (path[i] == '.') {
      if (done.empty() || i + 1 >= path.size()) bad("misplaced '.'");
      ++i;
    }
    std::size_t end = i;
    while (end < path.size() && path[end] != '.' && path[end] != '[') ++end;
    const std::string_view name = path.substr(i, end - i);
    if (name.empty()) bad("empty field name");
    const auto* s = std::get_if<Struct>(&v->data);
    if (!s) bad((done.empty() ? "(message)" : done) + " is not a struct");
    const Value* next = s->find(name);
    if (!next)
      bad("no field '" + std::string(name) + "' in " +
          (done.empty() ? (s->type ? s->type->full_name() : "(message)") : done));
    done += (done.empty() ? "" : ".") + std::string(name);
    v = next;
    i = end;
  }
  return *v;
}

Value zero_value(const StructType& type) {
  constexpr std::size_t cap = std::size_t{1} << 24;
  std::unordered_map<const StructType*, std::size_t> memo;
  if (zero_nodes(type, cap + 1, 0, memo) > cap)  // counted first: nothing is allocated
    throw Error("zero_value: " + type.full_name() + " has more than 2^24 elements");
  return ZeroMaker{}.structure(type, 0);
}

}  // namespace lcmx::types
