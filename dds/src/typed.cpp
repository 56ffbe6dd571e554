#include "lcmx/dds/typed.hpp"

#include <dds/ddsc/dds_opcodes.h>

#include <cstring>
#include <deque>
#include <map>

#include "lcmx/dds/idl.hpp"
#include "lcmx/types/value.hpp"

namespace lcmx::dds {

using types::Primitive;

// One struct's layout in sample memory.
struct TypedType::Layout {
  struct Field {
    const types::Member* member = nullptr;
    std::size_t index = 0;               // in StructType::members
    std::size_t offset = 0;
    const Layout* nested = nullptr;      // a struct element's layout
    std::size_t elem_size = 0, elem_align = 1;
    std::size_t count = 1;               // fixed arrays: elements in all dimensions
    bool sequence = false;               // x[n]
  };
  const types::StructType* type = nullptr;
  std::size_t size = 0, align = 1;
  std::vector<Field> fields;
};

namespace {

using Layout = TypedType::Layout;

// The opcodes as plain integers (they are enumerators of different enums in dds_opcodes.h).
constexpr std::uint32_t kADR = DDS_OP_ADR, kRTS = DDS_OP_RTS, kEXT = DDS_OP_TYPE_EXT, kSEQ = DDS_OP_TYPE_SEQ,
                        kARR = DDS_OP_TYPE_ARR, kSubSTU = DDS_OP_SUBTYPE_STU;

constexpr std::size_t kSeqSize = sizeof(dds_sequence_t);
constexpr std::size_t kSeqAlign = alignof(dds_sequence_t);

std::size_t prim_size(Primitive p) {
  switch (p) {
    case Primitive::int8: case Primitive::byte: case Primitive::boolean: return 1;
    case Primitive::int16: return 2;
    case Primitive::int32: case Primitive::float32: return 4;
    case Primitive::int64: case Primitive::float64: return 8;
    case Primitive::string: return sizeof(char*);
  }
  return 1;
}

std::size_t round_up(std::size_t v, std::size_t a) { return (v + a - 1) / a * a; }

// The opcode bits of a primitive, as TYPE (scalar) or SUBTYPE (array/sequence element).
std::uint32_t prim_type(Primitive p, bool sub) {
  std::uint32_t t = 0, flags = 0;
  switch (p) {
    case Primitive::int8: t = DDS_OP_VAL_1BY; flags = DDS_OP_FLAG_SGN; break;
    case Primitive::byte: t = DDS_OP_VAL_1BY; break;
    case Primitive::boolean: t = DDS_OP_VAL_BLN; break;
    case Primitive::int16: t = DDS_OP_VAL_2BY; flags = DDS_OP_FLAG_SGN; break;
    case Primitive::int32: t = DDS_OP_VAL_4BY; flags = DDS_OP_FLAG_SGN; break;
    case Primitive::int64: t = DDS_OP_VAL_8BY; flags = DDS_OP_FLAG_SGN; break;
    case Primitive::float32: t = DDS_OP_VAL_4BY; flags = DDS_OP_FLAG_FP; break;
    case Primitive::float64: t = DDS_OP_VAL_8BY; flags = DDS_OP_FLAG_FP; break;
    case Primitive::string: t = DDS_OP_VAL_STR; break;
  }
  return (sub ? (t << 8) : (t << 16)) | flags;
}

// Builds the layouts (one per struct type, shared) of `t` and what it nests.
const Layout* layout_of(const types::StructType& t, std::map<const types::StructType*, Layout*>& done,
                        std::vector<std::unique_ptr<Layout>>& owned) {
  if (auto it = done.find(&t); it != done.end()) return it->second;
  auto l = std::make_unique<Layout>();
  l->type = &t;
  Layout* raw = l.get();
  owned.push_back(std::move(l));
  done[&t] = raw;
  std::size_t off = 0;
  for (std::size_t i = 0; i < t.members.size(); ++i) {
    const auto& m = t.members[i];
    Layout::Field f;
    f.member = &m;
    f.index = i;
    if (m.nested) {
      f.nested = layout_of(*m.nested, done, owned);
      f.elem_size = f.nested->size;
      f.elem_align = f.nested->align;
    } else {
      f.elem_size = f.elem_align = prim_size(*m.primitive);
    }
    std::size_t size = f.elem_size, align = f.elem_align;
    if (!m.dims.empty() && m.dims[0].variable) {
      f.sequence = true;
      size = kSeqSize;
      align = kSeqAlign;
    } else {
      for (const auto& d : m.dims) f.count *= static_cast<std::size_t>(d.fixed);
      size = f.elem_size * f.count;
    }
    off = round_up(off, align);
    f.offset = off;
    off += size;
    raw->align = std::max(raw->align, align);
    raw->fields.push_back(f);
  }
  raw->size = std::max<std::size_t>(round_up(off, raw->align), 1);
  return raw;
}

// Opcodes: the top-level struct, then each nested struct once as a subroutine (as idlc does);
// jumps are patched once every subroutine's place is known.
class OpsBuilder {
 public:
  explicit OpsBuilder(std::vector<std::uint32_t>& ops) : ops_(ops) {}

  // Instructions emitted (what idlc puts in m_nops): one per member, one RTS per struct.
  std::uint32_t instructions = 0;

  void build(const Layout& top) {
    emit(top);
    while (!pending_.empty()) {
      const Layout* l = pending_.front();
      pending_.pop_front();
      if (!start_.count(l)) emit(*l);
    }
    for (const auto& fx : fixups_)
      ops_[fx.word] = (fx.insn_len << 16) | static_cast<std::uint32_t>(start_.at(fx.target) - fx.adr);
  }

 private:
  struct Fixup {
    std::size_t adr, word;
    std::uint32_t insn_len;
    const Layout* target;
  };

  void jump(std::size_t adr, std::uint32_t insn_len, const Layout* target) {
    fixups_.push_back({adr, ops_.size(), insn_len, target});
    ops_.push_back(0);
    pending_.push_back(target);
  }

  void emit(const Layout& l) {
    start_[&l] = ops_.size();
    instructions += static_cast<std::uint32_t>(l.fields.size()) + 1;
    for (const auto& f : l.fields) {
      const std::size_t adr = ops_.size();
      const auto off = static_cast<std::uint32_t>(f.offset);
      const bool prim = f.nested == nullptr;
      if (f.sequence) {
        if (prim) {
          ops_.insert(ops_.end(), {kADR | kSEQ | prim_type(*f.member->primitive, true), off});
        } else {
          ops_.insert(ops_.end(), {kADR | kSEQ | kSubSTU, off,
                                   static_cast<std::uint32_t>(f.elem_size)});
          jump(adr, 4, f.nested);
        }
      } else if (f.member->dims.empty()) {
        if (prim) {
          ops_.insert(ops_.end(), {kADR | prim_type(*f.member->primitive, false), off});
        } else {
          ops_.insert(ops_.end(), {kADR | kEXT, off});
          jump(adr, 3, f.nested);
        }
      } else {
        const auto n = static_cast<std::uint32_t>(f.count);
        if (prim) {
          ops_.insert(ops_.end(), {kADR | kARR | prim_type(*f.member->primitive, true), off, n});
        } else {
          ops_.insert(ops_.end(), {kADR | kARR | kSubSTU, off, n});
          jump(adr, 5, f.nested);
          ops_.push_back(static_cast<std::uint32_t>(f.elem_size));
        }
      }
    }
    ops_.push_back(kRTS);
  }

  std::vector<std::uint32_t>& ops_;
  std::map<const Layout*, std::size_t> start_;
  std::deque<const Layout*> pending_;
  std::vector<Fixup> fixups_;
};

// ---- LCM value tree -> sample memory ----

struct Writer {
  std::vector<std::unique_ptr<char[]>>& blocks;

  char* alloc(std::size_t n) {
    blocks.push_back(std::make_unique<char[]>(std::max<std::size_t>(n, 1)));  // value-initialised: zeroed
    return blocks.back().get();
  }

  template <class T>
  static void put(std::byte* dst, T v) {
    std::memcpy(dst, &v, sizeof v);
  }

  void elem(const Layout::Field& f, const types::Value& v, std::byte* dst) {
    if (f.nested) {
      structure(*f.nested, v.as<types::Struct>(), dst);
      return;
    }
    switch (*f.member->primitive) {
      case Primitive::int8: put(dst, static_cast<std::int8_t>(v.as<std::int64_t>())); break;
      case Primitive::byte: put(dst, static_cast<std::uint8_t>(v.as<std::int64_t>())); break;
      case Primitive::int16: put(dst, static_cast<std::int16_t>(v.as<std::int64_t>())); break;
      case Primitive::int32: put(dst, static_cast<std::int32_t>(v.as<std::int64_t>())); break;
      case Primitive::int64: put(dst, v.as<std::int64_t>()); break;
      case Primitive::float32: put(dst, v.as<float>()); break;
      case Primitive::float64: put(dst, v.as<double>()); break;
      case Primitive::boolean: put(dst, static_cast<std::uint8_t>(v.as<bool>() ? 1 : 0)); break;
      case Primitive::string: {
        const auto& s = v.as<std::string>();
        char* p = alloc(s.size() + 1);
        std::memcpy(p, s.data(), s.size());
        put(dst, p);
        break;
      }
    }
  }

  // Elements of dimension `dim` onwards, consecutively from `cursor`.
  void array(const Layout::Field& f, const types::Value& v, std::size_t dim, std::byte*& cursor) {
    const bool last = dim + 1 == f.member->dims.size();
    if (last && v.is<types::Bytes>()) {
      const auto& b = v.as<types::Bytes>();
      std::memcpy(cursor, b.data(), b.size());
      cursor += b.size();
      return;
    }
    for (const auto& e : v.as<types::Array>()) {
      if (last) {
        elem(f, e, cursor);
        cursor += f.elem_size;
      } else {
        array(f, e, dim + 1, cursor);
      }
    }
  }

  void structure(const Layout& l, const types::Struct& s, std::byte* base) {
    for (const auto& f : l.fields) {
      const types::Value& v = s.fields.at(f.index).value;
      std::byte* dst = base + f.offset;
      if (f.sequence) {
        const std::size_t n = v.is<types::Bytes>() ? v.as<types::Bytes>().size() : v.as<types::Array>().size();
        auto* buf = reinterpret_cast<std::byte*>(alloc(n * f.elem_size));
        std::byte* cursor = buf;
        array(f, v, 0, cursor);
        dds_sequence_t seq{};
        seq._maximum = seq._length = static_cast<std::uint32_t>(n);
        seq._buffer = reinterpret_cast<std::uint8_t*>(buf);
        seq._release = false;
        put(dst, seq);
      } else if (f.member->dims.empty()) {
        elem(f, v, dst);
      } else {
        std::byte* cursor = dst;
        array(f, v, 0, cursor);
      }
    }
  }
};

// ---- sample memory -> LCM value tree ----

struct Reader {
  template <class T>
  static T get(const std::byte* src) {
    T v;
    std::memcpy(&v, src, sizeof v);
    return v;
  }

  types::Value elem(const Layout::Field& f, const std::byte* src) {
    if (f.nested) return structure(*f.nested, src);
    switch (*f.member->primitive) {
      case Primitive::int8: return std::int64_t{get<std::int8_t>(src)};
      case Primitive::byte: return std::int64_t{get<std::uint8_t>(src)};
      case Primitive::int16: return std::int64_t{get<std::int16_t>(src)};
      case Primitive::int32: return std::int64_t{get<std::int32_t>(src)};
      case Primitive::int64: return get<std::int64_t>(src);
      case Primitive::float32: return get<float>(src);
      case Primitive::float64: return get<double>(src);
      case Primitive::boolean: return get<std::uint8_t>(src) != 0;
      case Primitive::string: {
        const char* p = get<const char*>(src);
        return std::string(p ? p : "");
      }
    }
    return std::int64_t{0};
  }

  // `n` elements of the last dimension, or the dimensions from `dim` of a fixed array.
  types::Value array(const Layout::Field& f, std::size_t dim, std::size_t n, const std::byte*& cursor) {
    const bool last = dim + 1 == f.member->dims.size();
    if (last && f.member->primitive == Primitive::byte) {
      types::Bytes b(reinterpret_cast<const std::uint8_t*>(cursor), reinterpret_cast<const std::uint8_t*>(cursor) + n);
      cursor += n;
      return b;
    }
    types::Array a;
    a.reserve(n);
    for (std::size_t i = 0; i < n; ++i) {
      if (last) {
        a.push_back(elem(f, cursor));
        cursor += f.elem_size;
      } else {
        const auto next = static_cast<std::size_t>(f.member->dims[dim + 1].fixed);
        a.push_back(array(f, dim + 1, next, cursor));
      }
    }
    return a;
  }

  types::Value structure(const Layout& l, const std::byte* base) {
    types::Struct s;
    s.type = l.type;
    s.fields.resize(l.fields.size());
    std::map<std::size_t, std::pair<std::size_t, std::string>> sizes;  // size member -> (length, array)
    for (const auto& f : l.fields) {
      s.fields[f.index].name = f.member->name;
      const std::byte* src = base + f.offset;
      if (f.sequence) {
        const auto seq = get<dds_sequence_t>(src);
        const std::size_t n = seq._length;
        const auto* cursor = reinterpret_cast<const std::byte*>(seq._buffer);
        s.fields[f.index].value = array(f, 0, n, cursor);
        const std::size_t sm = f.member->dims[0].size_member;
        auto [it, fresh] = sizes.emplace(sm, std::make_pair(n, f.member->name));
        if (!fresh && it->second.first != n)
          throw types::Error(l.type->full_name() + ": sequences " + it->second.second + " (" +
                             std::to_string(it->second.first) + " elements) and " + f.member->name + " (" +
                             std::to_string(n) + ") share the size member " + l.type->members[sm].name);
      } else if (f.member->dims.empty()) {
        s.fields[f.index].value = elem(f, src);
      } else {
        const std::byte* cursor = src;
        s.fields[f.index].value = array(f, 0, static_cast<std::size_t>(f.member->dims[0].fixed), cursor);
      }
    }
    // LCM's size members follow the sequences' lengths.
    for (const auto& [sm, len] : sizes) s.fields[sm].value = static_cast<std::int64_t>(len.first);
    return s;
  }
};

}  // namespace

std::unique_ptr<TypedType> TypedType::create(const types::StructType& type, bool ros2) {
  check_typed(type);
  std::unique_ptr<TypedType> t(new TypedType());
  t->type_ = &type;
  t->name_ = dds::dds_type_name(type, ros2);
  std::map<const types::StructType*, Layout*> done;
  const Layout* top = layout_of(type, done, t->layouts_);
  // layout_of puts the top-level type first.
  OpsBuilder ops(t->ops_);
  ops.build(*top);
  t->desc_.reset(new dds_topic_descriptor_t{
      .m_size = static_cast<std::uint32_t>(top->size),
      .m_align = static_cast<std::uint32_t>(top->align),
      .m_flagset = 0,
      .m_nkeys = 0,
      .m_typename = t->name_.c_str(),
      .m_keys = nullptr,
      .m_nops = ops.instructions,
      .m_ops = t->ops_.data(),
      .m_meta = "",
      .type_information = {nullptr, 0},
      .type_mapping = {nullptr, 0},
      .restrict_data_representation = 0});
  return t;
}

TypedType::~TypedType() = default;

const dds_topic_descriptor_t* TypedType::descriptor() const noexcept { return desc_.get(); }

std::size_t TypedType::sample_size() const noexcept { return layouts_.front()->size; }

TypedType::Sample TypedType::from_lcm(std::span<const std::byte> lcm) const {
  const types::Value v = types::decode(*type_, lcm.data(), lcm.size());
  Sample s;
  s.memory_.resize((sample_size() + sizeof(std::max_align_t) - 1) / sizeof(std::max_align_t));
  Writer w{s.blocks_};
  w.structure(*layouts_.front(), v.as<types::Struct>(), reinterpret_cast<std::byte*>(s.memory_.data()));
  return s;
}

std::vector<std::uint8_t> TypedType::to_lcm(const void* sample) const {
  Reader r;
  const types::Value v = r.structure(*layouts_.front(), static_cast<const std::byte*>(sample));
  return types::encode(*type_, v);
}

}  // namespace lcmx::dds
