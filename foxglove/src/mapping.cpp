#include "mapping.hpp"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <vector>

namespace lcmx::foxglove::detail {

using types::Member;
using types::Primitive;
using types::StructType;
using types::Value;

// ---- base64, JSON text ----

namespace {
constexpr char kB64[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

void append_int(std::string& out, std::int64_t v) {
  char b[24];
  auto r = std::to_chars(b, b + sizeof b, v);
  out.append(b, r.ptr);
}
template <class F>
void append_float(std::string& out, F v) {
  if (!std::isfinite(v)) {
    out += "null";
    return;
  }
  char b[40];
  auto r = std::to_chars(b, b + sizeof b, v);
  out.append(b, r.ptr);
}

// Length of the valid UTF-8 sequence at s[i], 0 if invalid: well-formed as Unicode's table 3-7
// says (no overlong form, no surrogate U+D800..U+DFFF, nothing above U+10FFFF).
std::size_t utf8_len(std::string_view s, std::size_t i) {
  const auto c = static_cast<unsigned char>(s[i]);
  std::size_t n = c < 0x80 ? 1 : (c >> 5) == 6 ? 2 : (c >> 4) == 14 ? 3 : (c >> 3) == 30 ? 4 : 0;
  if (n == 0 || i + n > s.size()) return 0;
  for (std::size_t k = 1; k < n; ++k)
    if ((static_cast<unsigned char>(s[i + k]) >> 6) != 2) return 0;
  if (n == 1) return 1;
  const auto c1 = static_cast<unsigned char>(s[i + 1]);
  if (n == 2 && c < 0xC2) return 0;                    // overlong
  if (c == 0xE0 && c1 < 0xA0) return 0;                // overlong
  if (c == 0xED && c1 >= 0xA0) return 0;               // a surrogate
  if (c == 0xF0 && c1 < 0x90) return 0;                // overlong
  if (c > 0xF4 || (c == 0xF4 && c1 >= 0x90)) return 0;  // above U+10FFFF
  return n;
}
}  // namespace

namespace {
// Every 12-bit value as its two base64 characters: three bytes are two lookups.
struct PairTable {
  char c[4096][2];
  constexpr PairTable() : c() {
    for (int i = 0; i < 4096; ++i) {
      c[i][0] = kB64[i >> 6];
      c[i][1] = kB64[i & 63];
    }
  }
};
constexpr PairTable kPairs;
}  // namespace

void base64_append(std::string& out, const std::uint8_t* d, std::size_t n) {
  const std::size_t start = out.size();
  out.resize(start + (n + 2) / 3 * 4);
  char* o = out.data() + start;
  std::size_t i = 0;
  for (; i + 3 <= n; i += 3) {
    const std::uint32_t v = (std::uint32_t{d[i]} << 16) | (std::uint32_t{d[i + 1]} << 8) | d[i + 2];
    std::memcpy(o, kPairs.c[v >> 12], 2);
    std::memcpy(o + 2, kPairs.c[v & 0xfff], 2);
    o += 4;
  }
  if (n - i == 1) {
    const std::uint32_t v = std::uint32_t{d[i]} << 16;
    *o++ = kB64[v >> 18];
    *o++ = kB64[(v >> 12) & 63];
    *o++ = '=';
    *o++ = '=';
  } else if (n - i == 2) {
    const std::uint32_t v = (std::uint32_t{d[i]} << 16) | (std::uint32_t{d[i + 1]} << 8);
    *o++ = kB64[v >> 18];
    *o++ = kB64[(v >> 12) & 63];
    *o++ = kB64[(v >> 6) & 63];
    *o++ = '=';
  }
}

types::Bytes base64_decode(std::string_view t) {
  int rev[256];
  std::fill(std::begin(rev), std::end(rev), -1);
  for (int i = 0; i < 64; ++i) rev[static_cast<unsigned char>(kB64[i])] = i;
  while (!t.empty() && t.back() == '=') t.remove_suffix(1);
  if (t.size() % 4 == 1) throw types::Error("base64: bad length");
  types::Bytes out;
  out.reserve(t.size() * 3 / 4);
  std::uint32_t acc = 0;
  int bits = 0;
  for (char ch : t) {
    const int v = rev[static_cast<unsigned char>(ch)];
    if (v < 0) throw types::Error("base64: invalid character");
    acc = (acc << 6) | static_cast<std::uint32_t>(v);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out.push_back(static_cast<std::uint8_t>((acc >> bits) & 0xff));
    }
  }
  return out;
}

void json_string_append(std::string& out, std::string_view s) {
  out += '"';
  for (std::size_t i = 0; i < s.size();) {
    const auto c = static_cast<unsigned char>(s[i]);
    if (c == '"' || c == '\\') {
      out += '\\';
      out += static_cast<char>(c);
      ++i;
    } else if (c < 0x20) {
      char b[8];
      std::snprintf(b, sizeof b, "\\u%04x", c);
      out += b;
      ++i;
    } else if (c < 0x80) {
      out += static_cast<char>(c);
      ++i;
    } else if (const auto n = utf8_len(s, i); n > 0) {
      out.append(s.substr(i, n));
      i += n;
    } else {
      char b[8];
      std::snprintf(b, sizeof b, "\\u%04x", c);
      out += b;
      ++i;
    }
  }
  out += '"';
}

namespace {
std::string jstr(std::string_view s) {
  std::string o;
  json_string_append(o, s);
  return o;
}

std::string hex64(std::uint64_t v) {
  char b[24];
  std::snprintf(b, sizeof b, "0x%016llx", static_cast<unsigned long long>(v));
  return b;
}

// ---- schemas ----

std::string primitive_schema(Primitive p) {
  switch (p) {
    case Primitive::int8:
    case Primitive::int16:
    case Primitive::int32:
    case Primitive::int64:
    case Primitive::byte: return R"({"type":"integer"})";
    case Primitive::float32:
    case Primitive::float64:
      return R"({"type":"number","description":")" + std::string(types::to_string(p)) +
             R"(; NaN and infinities are null"})";
    case Primitive::boolean: return R"({"type":"boolean"})";
    case Primitive::string: return R"({"type":"string"})";
  }
  return "{}";
}

bool is_byte_array(const Member& m) { return !m.dims.empty() && m.primitive == Primitive::byte; }

// "[3][n]" as declared.
std::string dims_text(const StructType& owner, const Member& m) {
  std::string s;
  for (const auto& d : m.dims)
    s += "[" + (d.variable ? owner.members.at(d.size_member).name : std::to_string(d.fixed)) + "]";
  return s;
}

struct SchemaBuilder {
  std::vector<const StructType*> stack;

  std::string element(const Member& m) {
    if (m.primitive) return primitive_schema(*m.primitive);
    if (m.nested == nullptr) return R"({"type":"object"})";
    if (std::find(stack.begin(), stack.end(), m.nested) != stack.end())
      return R"({"type":"object","description":)" +
             jstr("recursive LCM type " + m.nested->full_name() + " (not expanded in the schema)") + "}";
    return object(*m.nested, false);
  }

  std::string member(const StructType& owner, const Member& m) {
    if (m.dims.empty()) return element(m);
    std::int64_t total = 1;
    bool fixed = true;
    for (const auto& d : m.dims) {
      if (d.variable) fixed = false;
      else total *= d.fixed;
    }
    const std::string decl = std::string(m.primitive ? types::to_string(*m.primitive) : m.type_name) + " " +
                             m.name + dims_text(owner, m);
    if (is_byte_array(m))
      return R"({"type":"string","contentEncoding":"base64","description":)" +
             jstr("LCM " + decl + (m.dims.size() > 1 ? ", flattened row-major" : "") + ", base64") + "}";
    std::string s = R"({"type":"array","items":)" + element(m);
    if (fixed) s += R"(,"minItems":)" + std::to_string(total) + R"(,"maxItems":)" + std::to_string(total);
    s += R"(,"description":)" +
         jstr("LCM " + decl + (m.dims.size() > 1 ? ", flattened row-major (last index fastest)" : "")) + "}";
    return s;
  }

  std::string object(const StructType& t, bool top) {
    stack.push_back(&t);
    std::string s = "{";
    if (top) s += R"("title":)" + jstr(t.full_name()) + ",";
    std::string desc = "LCM type " + t.full_name() + ", fingerprint " + hex64(t.fingerprint);
    if (!t.constants.empty()) {
      desc += "; constants:";
      for (const auto& c : t.constants) desc += " " + c.name + "=" + c.text;
    }
    s += R"("description":)" + jstr(desc) + R"(,"type":"object","properties":{)";
    for (std::size_t i = 0; i < t.members.size(); ++i)
      s += (i ? "," : "") + jstr(t.members[i].name) + ":" + member(t, t.members[i]);
    s += "}}";
    stack.pop_back();
    return s;
  }
};

// ---- messages ----

// Where a message's JSON goes: `out`, and, when `payload` is set, large byte arrays as shared
// parts of their own (base64 made once per message by `cache`).
struct JsonOut {
  std::string out;
  Payload* payload = nullptr;
  Base64Cache* cache = nullptr;

  // `"<base64 of data>"`.
  void bytes(const std::uint8_t* data, std::size_t size, bool stable) {
    out += '"';
    if (payload != nullptr && cache != nullptr && stable && size >= Base64Cache::kMin) {
      flush();
      payload->add(cache->get(data, size));
    } else {
      base64_append(out, data, size);
    }
    out += '"';
  }
  // `out` becomes a part of the payload.
  void flush() {
    if (payload == nullptr || out.empty()) return;
    payload->add(std::make_shared<const std::string>(std::move(out)));
    out.clear();
  }
};

void value_json(JsonOut& o, const Value& v);

// Leaves of a (possibly nested) array, row-major, as JSON array elements.
void flatten(JsonOut& o, const Value& v, bool& first) {
  if (const auto* a = std::get_if<types::Array>(&v.data)) {
    for (const auto& e : *a) flatten(o, e, first);
    return;
  }
  if (const auto* b = std::get_if<types::Bytes>(&v.data)) {  // only inside a flattened non-byte walk
    for (auto x : *b) {
      if (!first) o.out += ',';
      first = false;
      append_int(o.out, x);
    }
    return;
  }
  if (!first) o.out += ',';
  first = false;
  value_json(o, v);
}

void collect_bytes(const Value& v, types::Bytes& out) {
  if (const auto* b = std::get_if<types::Bytes>(&v.data)) out.insert(out.end(), b->begin(), b->end());
  else if (const auto* a = std::get_if<types::Array>(&v.data))
    for (const auto& e : *a) collect_bytes(e, out);
}

void struct_json(JsonOut& o, const types::Struct& s) {
  o.out += '{';
  for (std::size_t i = 0; i < s.fields.size(); ++i) {
    const auto& f = s.fields[i];
    if (i) o.out += ',';
    json_string_append(o.out, f.name);
    o.out += ':';
    const Member* m = s.type ? s.type->find_member(f.name) : nullptr;
    if (m != nullptr && is_byte_array(*m)) {
      if (const auto* b = std::get_if<types::Bytes>(&f.value.data)) {
        o.bytes(b->data(), b->size(), true);
      } else {
        types::Bytes all;
        collect_bytes(f.value, all);
        o.bytes(all.data(), all.size(), false);  // a temporary: not shared
      }
    } else if (f.value.is<types::Array>() || f.value.is<types::Bytes>()) {
      o.out += '[';
      bool first = true;
      flatten(o, f.value, first);
      o.out += ']';
    } else {
      value_json(o, f.value);
    }
  }
  o.out += '}';
}

void value_json(JsonOut& o, const Value& v) {
  std::visit(
      [&](const auto& x) {
        using T = std::decay_t<decltype(x)>;
        if constexpr (std::is_same_v<T, std::int64_t>) append_int(o.out, x);
        else if constexpr (std::is_same_v<T, double> || std::is_same_v<T, float>) append_float(o.out, x);
        else if constexpr (std::is_same_v<T, bool>) o.out += x ? "true" : "false";
        else if constexpr (std::is_same_v<T, std::string>) json_string_append(o.out, x);
        else if constexpr (std::is_same_v<T, types::Struct>) struct_json(o, x);
        else {
          o.out += '[';
          bool first = true;
          flatten(o, v, first);
          o.out += ']';
        }
      },
      v.data);
}

// ---- views ----

const Member* member_of(const StructType& t, std::string_view name) { return t.find_member(name); }
bool is_int_scalar(const Member* m) {
  return m && m->dims.empty() && m->primitive && *m->primitive != Primitive::float32 &&
         *m->primitive != Primitive::float64 && *m->primitive != Primitive::string &&
         *m->primitive != Primitive::boolean;
}
bool is_string_scalar(const Member* m) { return m && m->dims.empty() && m->primitive == Primitive::string; }
bool is_bytes_1d(const Member* m) { return m && m->dims.size() == 1 && m->primitive == Primitive::byte; }

std::int64_t int_field(const types::Struct& s, std::string_view name, std::int64_t dflt = 0) {
  const Value* v = s.find(name);
  return v && v->is<std::int64_t>() ? v->as<std::int64_t>() : dflt;
}
std::string string_field(const types::Struct& s, std::string_view name) {
  const Value* v = s.find(name);
  return v && v->is<std::string>() ? v->as<std::string>() : std::string();
}
// frame_id at the top or in a nested `header` struct.
std::string frame_id(const types::Struct& s) {
  if (const Value* v = s.find("frame_id"); v && v->is<std::string>()) return v->as<std::string>();
  if (const Value* h = s.find("header"); h && h->is<types::Struct>())
    return string_field(h->as<types::Struct>(), "frame_id");
  return {};
}
const types::Bytes* bytes_field(const types::Struct& s, std::string_view name) {
  const Value* v = s.find(name);
  return v && v->is<types::Bytes>() ? &v->as<types::Bytes>() : nullptr;
}

void stamp_json(std::string& out, std::uint64_t ns) {
  out += R"("timestamp":{"sec":)";
  append_int(out, static_cast<std::int64_t>(ns / 1'000'000'000));
  out += R"(,"nsec":)";
  append_int(out, static_cast<std::int64_t>(ns % 1'000'000'000));
  out += '}';
}

constexpr const char* kTimeSchema =
    R"({"type":"object","title":"time","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}})";
}  // namespace

std::string json_schema(const StructType& type) {
  SchemaBuilder b;
  return b.object(type, true);
}

std::shared_ptr<const std::string> Base64Cache::get(const std::uint8_t* data, std::size_t size) {
  for (const auto& e : entries_)
    if (e.data == data && e.size == size) return e.text;
  auto text = std::make_shared<std::string>();
  base64_append(*text, data, size);
  entries_.push_back({data, size, text});
  return text;
}

std::string to_json(const Value& value) {
  JsonOut o;
  value_json(o, value);
  return std::move(o.out);
}

Payload to_json(const Value& value, Base64Cache& cache) {
  Payload p;
  JsonOut o{{}, &p, &cache};
  value_json(o, value);
  o.flush();
  return p;
}

View view_of(const StructType& t) {
  const Member* data = member_of(t, "data");
  if (!is_bytes_1d(data)) return {};
  if (is_int_scalar(member_of(t, "width")) && is_int_scalar(member_of(t, "height")) &&
      is_string_scalar(member_of(t, "encoding")))
    return {ViewKind::raw_image, "foxglove.RawImage", "/image"};
  if (is_string_scalar(member_of(t, "format"))) return {ViewKind::compressed_image, "foxglove.CompressedImage", "/image"};
  const Member* fields = member_of(t, "fields");
  if (fields && fields->dims.size() == 1 && fields->primitive == Primitive::string &&
      is_int_scalar(member_of(t, "point_step")))
    return {ViewKind::point_cloud, "foxglove.PointCloud", "/points"};
  return {};
}

std::string view_schema(ViewKind kind) {
  const std::string ts = std::string(R"("timestamp":)") + kTimeSchema;
  const std::string data = R"("data":{"type":"string","contentEncoding":"base64"})";
  switch (kind) {
    case ViewKind::raw_image:
      return R"({"title":"foxglove.RawImage","description":"A raw image","type":"object","properties":{)" + ts +
             R"(,"frame_id":{"type":"string"},"width":{"type":"integer","minimum":0},"height":{"type":"integer","minimum":0},"encoding":{"type":"string"},"step":{"type":"integer","minimum":0},)" +
             data + "}}";
    case ViewKind::compressed_image:
      return R"({"title":"foxglove.CompressedImage","description":"A compressed image","type":"object","properties":{)" +
             ts + R"(,"frame_id":{"type":"string"},)" + data + R"(,"format":{"type":"string"}}})";
    case ViewKind::point_cloud: {
      const std::string vec3 =
          R"({"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}})";
      const std::string quat =
          R"({"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}})";
      return R"({"title":"foxglove.PointCloud","description":"A collection of N-dimensional points","type":"object","properties":{)" +
             ts + R"(,"frame_id":{"type":"string"},"pose":{"type":"object","properties":{"position":)" + vec3 +
             R"(,"orientation":)" + quat +
             R"(}},"point_stride":{"type":"integer","minimum":0},"fields":{"type":"array","items":{"type":"object","properties":{"name":{"type":"string"},"offset":{"type":"integer","minimum":0},"type":{"type":"integer"}}}},)" +
             data + "}}";
    }
    case ViewKind::none: break;
  }
  return "{}";
}

namespace {
std::optional<Payload> view_json(ViewKind kind, const Value& value, std::uint64_t stamp_ns, Base64Cache* cache) {
  if (!value.is<types::Struct>()) return std::nullopt;
  const auto& s = value.as<types::Struct>();
  const types::Bytes* data = bytes_field(s, "data");
  if (data == nullptr) return std::nullopt;
  Payload payload;
  JsonOut o{{}, &payload, cache};
  std::string& out = o.out;
  if (cache == nullptr) out.reserve(data->size() / 3 * 4 + 256);
  out += '{';
  stamp_json(out, stamp_ns);
  out += R"(,"frame_id":)";
  json_string_append(out, frame_id(s));
  switch (kind) {
    case ViewKind::raw_image: {
      const auto w = int_field(s, "width"), h = int_field(s, "height");
      std::int64_t step = int_field(s, "step", int_field(s, "stride", int_field(s, "row_stride", 0)));
      if (w <= 0 || h <= 0) return std::nullopt;
      if (step <= 0) step = static_cast<std::int64_t>(data->size()) / h;
      if (step <= 0) return std::nullopt;
      if (static_cast<std::uint64_t>(step) * static_cast<std::uint64_t>(h) > data->size()) return std::nullopt;
      out += R"(,"width":)";
      append_int(out, w);
      out += R"(,"height":)";
      append_int(out, h);
      out += R"(,"encoding":)";
      json_string_append(out, string_field(s, "encoding"));
      out += R"(,"step":)";
      append_int(out, step);
      break;
    }
    case ViewKind::compressed_image:
      out += R"(,"format":)";
      json_string_append(out, string_field(s, "format"));
      break;
    case ViewKind::point_cloud: {
      const Value* f = s.find("fields");
      const auto step = int_field(s, "point_step");
      if (f == nullptr || !f->is<types::Array>() || step <= 0) return std::nullopt;
      const auto& names = f->as<types::Array>();
      if (static_cast<std::int64_t>(names.size()) * 4 > step) return std::nullopt;
      out += R"(,"pose":{"position":{"x":0,"y":0,"z":0},"orientation":{"x":0,"y":0,"z":0,"w":1}},"point_stride":)";
      append_int(out, step);
      out += R"(,"fields":[)";
      for (std::size_t i = 0; i < names.size(); ++i) {
        if (i) out += ',';
        out += R"({"name":)";
        json_string_append(out, names[i].is<std::string>() ? names[i].as<std::string>() : std::string());
        out += R"(,"offset":)";
        append_int(out, static_cast<std::int64_t>(i) * 4);
        out += R"(,"type":7})";  // FLOAT32
      }
      out += ']';
      break;
    }
    case ViewKind::none: return std::nullopt;
  }
  out += R"(,"data":)";
  o.bytes(data->data(), data->size(), true);
  out += '}';
  o.flush();
  return payload;
}
}  // namespace

std::optional<std::string> to_view_json(ViewKind kind, const Value& value, std::uint64_t stamp_ns) {
  auto p = view_json(kind, value, stamp_ns, nullptr);
  if (!p) return std::nullopt;
  return p->joined();
}

std::optional<Payload> to_view_json(ViewKind kind, const Value& value, std::uint64_t stamp_ns, Base64Cache& cache) {
  return view_json(kind, value, stamp_ns, &cache);
}

bool has_utime(const StructType& type) {
  const Member* m = type.find_member("utime");
  return m && m->dims.empty() && m->primitive == Primitive::int64;
}

std::optional<std::uint64_t> utime_ns(const Value& value) {
  if (!value.is<types::Struct>()) return std::nullopt;
  const Value* v = value.as<types::Struct>().find("utime");
  if (v == nullptr || !v->is<std::int64_t>() || v->as<std::int64_t>() <= 0) return std::nullopt;
  return static_cast<std::uint64_t>(v->as<std::int64_t>()) * 1000u;
}

std::string unknown_schema() {
  return R"({"title":"lcmx.unknown","description":"A message whose LCM fingerprint is in no .lcm file of the type path (lcmx foxglove --types): its fingerprint, size and bytes","type":"object","properties":{"fingerprint":{"type":"string","description":"the first 8 bytes, hex"},"size":{"type":"integer"},"data":{"type":"string","contentEncoding":"base64","description":"the whole LCM encoding, fingerprint included"}}})";
}

std::string unknown_json(std::uint64_t fingerprint, const std::uint8_t* data, std::size_t size) {
  std::string out = R"({"fingerprint":")" + hex64(fingerprint) + R"(","size":)";
  append_int(out, static_cast<std::int64_t>(size));
  out += R"(,"data":")";
  base64_append(out, data, size);
  out += "\"}";
  return out;
}

// ---- client JSON ----

namespace {
using nlohmann::json;

void normalize(json& obj, const StructType& t, const std::string& path, int depth);

// Rebuilds a flat array into nested arrays of the member's dimensions.
json reshape(const json& flat, const std::vector<std::int64_t>& dims, std::size_t d, std::size_t& at) {
  json out = json::array();
  for (std::int64_t i = 0; i < dims[d]; ++i) {
    if (d + 1 == dims.size()) out.push_back(flat.at(at++));
    else out.push_back(reshape(flat, dims, d + 1, at));
  }
  return out;
}

void normalize_member(json& obj, const StructType& t, const Member& m, const std::string& path, int depth) {
  auto it = obj.find(m.name);
  if (it == obj.end()) return;
  json& v = *it;
  const std::string here = path.empty() ? m.name : path + "." + m.name;
  if (!m.dims.empty()) {
    if (is_byte_array(m) && v.is_string()) {
      const auto bytes = base64_decode(v.get<std::string>());
      v = json(std::vector<int>(bytes.begin(), bytes.end()));
    }
    if (m.dims.size() > 1 && v.is_array() && (v.empty() || !v.front().is_array())) {
      // Flattened: the dimensions come from the fixed sizes and the size members given.
      std::vector<std::int64_t> dims;
      std::int64_t total = 1;
      for (const auto& d : m.dims) {
        std::int64_t n = d.fixed;
        if (d.variable) {
          const auto& sm = t.members.at(d.size_member).name;
          auto s = obj.find(sm);
          if (s == obj.end() || !s->is_number_integer())
            throw types::Error("from_json: " + here + ": a flattened array needs its size member '" + sm + "'");
          n = s->get<std::int64_t>();
        }
        if (n < 0) throw types::Error("from_json: " + here + ": negative size");
        dims.push_back(n);
        total *= n;
      }
      if (static_cast<std::int64_t>(v.size()) != total)
        throw types::Error("from_json: " + here + ": flattened array has " + std::to_string(v.size()) +
                           " elements, its dimensions make " + std::to_string(total));
      std::size_t at = 0;
      v = total == 0 ? json::array() : reshape(v, dims, 0, at);
    }
    if (m.nested != nullptr && v.is_array()) {
      // Structs inside (possibly nested) arrays.
      std::vector<json*> todo{&v};
      while (!todo.empty()) {
        json* a = todo.back();
        todo.pop_back();
        for (auto& e : *a) {
          if (e.is_array()) todo.push_back(&e);
          else if (e.is_object()) normalize(e, *m.nested, here + "[]", depth + 1);
        }
      }
    }
    return;
  }
  if (m.nested != nullptr && v.is_object()) normalize(v, *m.nested, here, depth + 1);
}

void normalize(json& obj, const StructType& t, const std::string& path, int depth) {
  if (depth > 64) throw types::Error("from_json: nested deeper than 64 structs");
  if (!obj.is_object()) return;  // from_json names the error
  for (const auto& m : t.members) normalize_member(obj, t, m, path, depth);
}
}  // namespace

types::Value from_foxglove_json(const StructType& type, std::string_view text) {
  json j;
  try {
    j = json::parse(text);
  } catch (const json::exception& e) {
    throw types::Error(std::string("from_json: invalid JSON: ") + e.what());
  }
  try {
    normalize(j, type, "", 0);
  } catch (const json::exception& e) {
    throw types::Error(std::string("from_json: ") + e.what());
  }
  return types::from_json(type, j.dump());
}

}  // namespace lcmx::foxglove::detail
