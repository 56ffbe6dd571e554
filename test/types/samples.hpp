// Shared by the lcmx::types tests: the corpus registry, lcm-gen messages of every corpus type,
// random trees, round-trip helpers.
#pragma once

#include <catch2/catch.hpp>

#include <functional>
#include <random>

#include "corpus_a/arrays_t.hpp"
#include "corpus_a/path_t.hpp"
#include "corpus_a/primitives_t.hpp"
#include "corpus_b/scene_t.hpp"
#include "corpus_b/tree_t.hpp"
#include "lcmx/types/types.hpp"
#include "plain_t.hpp"

namespace samples {

using namespace lcmx::types;


inline const TypeRegistry& corpus() {
  static const TypeRegistry r = TypeRegistry::load({LCMX_TYPES_CORPUS});
  return r;
}

template <class T>
std::vector<std::uint8_t> lcm_encode(const T& msg) {
  std::vector<std::uint8_t> out(static_cast<std::size_t>(msg.getEncodedSize()));
  REQUIRE(msg.encode(out.data(), 0, static_cast<int>(out.size())) == static_cast<int>(out.size()));
  return out;
}

// lcm-gen encodes, we decode, we encode: the same bytes; and lcm-gen decodes ours.
template <class T>
inline Value round_trip(const TypeRegistry& r, const T& msg) {
  const std::vector<std::uint8_t> theirs = lcm_encode(msg);
  Value tree = decode(r, theirs.data(), theirs.size());
  const StructType& t = *tree.as<Struct>().type;
  CHECK(encode(t, tree) == theirs);
  T back;
  CHECK(back.decode(theirs.data(), 0, static_cast<int>(theirs.size())) == static_cast<int>(theirs.size()));
  return tree;
}

inline void fill(corpus_a::point_t& p, double base) {
  p.x = base;
  p.y = -base * 2.5;
  p.z = 1e-300 * base;
}

inline corpus_a::primitives_t make_primitives() {
  corpus_a::primitives_t p;
  p.i8 = -128;
  p.i16 = -30000;
  p.i32 = 0x7fffffff;
  p.i64 = static_cast<int64_t>(0x8000000000000001ULL);
  p.f32 = -3.25e-7f;
  p.f64 = 6.02214076e23;
  p.text = "caf\xc3\xa9 \"quoted\"\n";
  p.flag = 1;
  p.octet = 0xfe;
  p.a = 1;
  p.b = -2;
  p.c = 3;
  return p;
}

inline corpus_a::arrays_t make_arrays() {
  corpus_a::arrays_t a;
  a.n8 = 3;
  a.n16 = 2;
  a.n32 = 4;
  a.n64 = 5;
  for (int i = 0; i < 3; ++i) a.fixed[i] = -i * 1000;
  for (int i = 0; i < 4; ++i) a.hexsized[i] = static_cast<int8_t>(i - 2);
  a.var = {0.5, -1.0, 3e10, 1.0 / 3};
  a.blob = {0, 1, 0x7f, 0x80, 0xff};
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j) a.grid[i][j] = static_cast<float>(i * 10 + j) / 7.0f;
  a.mixed.assign(3, std::vector<int16_t>(4));
  a.mixed2.assign(4, std::vector<int16_t>(3));
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 4; ++j) a.mixed[i][j] = a.mixed2[j][i] = static_cast<int16_t>(i * 100 - j);
  a.flags = {1, 0};
  a.names = {"", "one", "two words", "\xe2\x82\xac"};
  a.table = {{"a", "b"}, {"c", ""}};
  a.cube.assign(4, std::vector<std::vector<int32_t>>(3, std::vector<int32_t>(2)));
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 2; ++k) a.cube[i][j][k] = i * 100 + j * 10 + k;
  a.image.assign(3, std::vector<uint8_t>(2));
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 2; ++j) a.image[i][j] = static_cast<uint8_t>(200 + i * 2 + j);
  a.longs = {INT64_MIN, 0, INT64_MAX};
  a.more_longs[0] = 42;
  a.more_longs[1] = -42;
  return a;
}

inline corpus_a::path_t make_path(int n) {
  corpus_a::path_t p;
  p.num_points = n;
  p.points.resize(static_cast<std::size_t>(n));
  for (int i = 0; i < n; ++i) fill(p.points[static_cast<std::size_t>(i)], i + 0.5);
  for (int i = 0; i < 4; ++i) fill(p.corners[i], -i);
  fill(p.origin, 7);
  p.grid.assign(2, std::vector<corpus_a::point_t>(static_cast<std::size_t>(n)));
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < n; ++j) fill(p.grid[static_cast<std::size_t>(i)][static_cast<std::size_t>(j)], i * j);
  return p;
}

inline corpus_b::scene_t make_scene() {
  corpus_b::scene_t s;
  s.stamp.utime = 1700000000123456;
  s.stamp.frame = "map";
  s.paths[0] = make_path(2);
  s.paths[1] = make_path(0);
  s.n = 3;
  s.landmarks.resize(3);
  for (int i = 0; i < 3; ++i) fill(s.landmarks[static_cast<std::size_t>(i)], i * 3.0);
  s.prims = make_primitives();
  s.arrays = make_arrays();
  s.deep.one = 1;
  for (auto* l2 : {&s.deep.two, &s.deep.again}) {
    l2->two = 22;
    for (auto& l3 : l2->three) {
      l3.stamp.utime = 33;
      l3.stamp.frame = "deep";
      l3.value = 3.3;
    }
  }
  return s;
}

// A random tree of `t`: size members get small random values that the arrays follow.
inline Value random_tree(const StructType& t, std::mt19937& rng, int depth);

inline Value random_scalar(const Member& m, std::mt19937& rng, int depth) {
  if (!m.primitive) return random_tree(*m.nested, rng, depth + 1);
  std::uniform_int_distribution<std::int64_t> any(INT64_MIN, INT64_MAX);
  switch (*m.primitive) {
    case Primitive::int8: return any(rng) % 128;
    case Primitive::int16: return any(rng) % 32768;
    case Primitive::int32: return any(rng) % 2147483648LL;
    case Primitive::int64: return any(rng);
    case Primitive::byte: return static_cast<std::int64_t>(rng() % 256);
    case Primitive::boolean: return rng() % 2 == 0;
    case Primitive::float32: return std::uniform_real_distribution<float>(-1e6f, 1e6f)(rng);
    case Primitive::float64: return std::uniform_real_distribution<double>(-1e12, 1e12)(rng);
    case Primitive::string: {
      std::string s(rng() % 6, 'a');
      for (char& c : s) c = static_cast<char>(' ' + rng() % 95);
      return s;
    }
  }
  return std::int64_t{0};
}

inline Value random_array(const Member& m, std::size_t dim, const Struct& s, std::mt19937& rng, int depth) {
  const Dimension& d = m.dims[dim];
  const auto n = static_cast<std::size_t>(d.variable ? s.fields[d.size_member].value.as<std::int64_t>() : d.fixed);
  const bool last = dim + 1 == m.dims.size();
  if (last && m.primitive == Primitive::byte) {
    Bytes b(n);
    for (auto& x : b) x = static_cast<std::uint8_t>(rng());
    return b;
  }
  Array a;
  for (std::size_t i = 0; i < n; ++i)
    a.push_back(last ? random_scalar(m, rng, depth) : random_array(m, dim + 1, s, rng, depth));
  return a;
}

inline Value random_tree(const StructType& t, std::mt19937& rng, int depth) {
  std::vector<bool> is_size(t.members.size());
  for (const Member& m : t.members)
    for (const Dimension& d : m.dims)
      if (d.variable) is_size[d.size_member] = true;
  Struct s;
  s.type = &t;
  for (std::size_t i = 0; i < t.members.size(); ++i) {
    const Member& m = t.members[i];
    Value v;
    if (is_size[i]) {
      v = static_cast<std::int64_t>(depth > 2 ? 0 : rng() % 4);  // bounded recursion (tree_t)
    } else if (m.dims.empty()) {
      v = random_scalar(m, rng, depth);
    } else {
      v = random_array(m, 0, s, rng, depth);
    }
    s.fields.push_back({m.name, std::move(v)});
  }
  return s;
}

// We encode a random tree, lcm-gen decodes it and encodes it again: the same bytes; we decode
// those into the same tree (its encoding equal).
template <class T>
inline void random_round_trips(const TypeRegistry& r, const std::string& name) {
  INFO(name);
  const StructType& t = r.at(name);
  std::mt19937 rng(12345);
  for (int i = 0; i < 25; ++i) {
    const Value tree = random_tree(t, rng, 0);
    const std::vector<std::uint8_t> ours = encode(t, tree);
    T msg;
    REQUIRE(msg.decode(ours.data(), 0, static_cast<int>(ours.size())) == static_cast<int>(ours.size()));
    CHECK(lcm_encode(msg) == ours);
    CHECK(encode(t, decode(t, ours.data(), ours.size())) == ours);
  }
}

inline std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "(no error)";
}


}  // namespace samples
