// TypeRegistry: loading the type path, resolving nested names, fingerprints (lcm-gen's
// recursive _computeHash), minimum encoded sizes.
#include <algorithm>
#include <cstdlib>
#include <set>
#include <sstream>

#include "lcmx/types/schema.hpp"

namespace lcmx::types {
namespace fs = std::filesystem;

namespace {

// lcm-gen's _computeHash: a type already being hashed further up contributes 0; otherwise
// its base hash plus the recursive hash of every non-primitive member (once per member), then
// rotated left by one bit.
// Memoized: a type whose computation cut no cycle reaches no cycle, so its hash does not depend
// on the stack (without this, types nesting two members of the next type, 40 deep, would take
// 2^40 steps, as lcm-gen's generated code does once per process).
struct Walk {
  std::vector<const StructType*> stack;
  std::unordered_map<const StructType*, std::uint64_t> done;
  bool cut = false;  // a cycle was cut below the current type
};

std::uint64_t recursive_hash(const StructType& t, Walk& w) {
  if (std::find(w.stack.begin(), w.stack.end(), &t) != w.stack.end()) {
    w.cut = true;
    return 0;
  }
  if (auto it = w.done.find(&t); it != w.done.end()) return it->second;
  const bool outer_cut = w.cut;
  w.cut = false;
  w.stack.push_back(&t);
  auto h = static_cast<std::uint64_t>(t.base_hash);
  for (const Member& m : t.members)
    if (!m.primitive) h += recursive_hash(*m.nested, w);
  w.stack.pop_back();
  const std::uint64_t result = (h << 1) + ((h >> 63) & 1);
  if (!w.cut) w.done.emplace(&t, result);
  w.cut = w.cut || outer_cut;
  return result;
}

constexpr std::size_t kSizeCap = std::size_t{1} << 48;  // saturation for min sizes

std::size_t sat_add(std::size_t a, std::size_t b) { return std::min(kSizeCap, a + b); }
std::size_t sat_mul(std::size_t a, std::size_t b) {
  if (a == 0 || b == 0) return 0;
  return a > kSizeCap / b ? kSizeCap : std::min(kSizeCap, a * b);
}

// Smallest encoding of a struct (without fingerprint); a type on the stack counts 0 (only a
// variable-length array can hold a recursive type, and it may be empty). Memoized as above.
std::size_t min_size(const StructType& t, Walk& w) {
  if (std::find(w.stack.begin(), w.stack.end(), &t) != w.stack.end()) {
    w.cut = true;
    return 0;
  }
  if (auto it = w.done.find(&t); it != w.done.end()) return static_cast<std::size_t>(it->second);
  const bool outer_cut = w.cut;
  w.cut = false;
  w.stack.push_back(&t);
  std::size_t total = 0;
  for (const Member& m : t.members) {
    std::size_t count = 1;
    for (const Dimension& d : m.dims) count = d.variable ? 0 : sat_mul(count, static_cast<std::size_t>(d.fixed));
    if (count == 0) continue;
    const std::size_t element = m.primitive ? min_encoded_size(*m.primitive) : min_size(*m.nested, w);
    total = sat_add(total, sat_mul(count, element));
  }
  w.stack.pop_back();
  if (!w.cut) w.done.emplace(&t, total);
  w.cut = w.cut || outer_cut;
  return total;
}

bool same_definition(const StructType& a, const StructType& b) {
  if (a.base_hash != b.base_hash || a.members.size() != b.members.size()) return false;
  for (std::size_t i = 0; i < a.members.size(); ++i)
    if (a.members[i].type_name != b.members[i].type_name) return false;
  return true;
}

void collect(const fs::path& path, std::vector<fs::path>& files, std::set<fs::path>& seen_dirs) {
  std::error_code ec;
  const fs::file_status st = fs::status(path, ec);
  if (ec || !fs::exists(st)) throw Error("type path entry " + path.string() + " does not exist");
  if (!fs::is_directory(st)) {
    files.push_back(path);
    return;
  }
  const fs::path canonical = fs::canonical(path, ec);
  if (ec || !seen_dirs.insert(canonical).second) return;  // a directory reached twice
  std::vector<fs::directory_entry> entries;
  for (fs::directory_iterator it(path, fs::directory_options::skip_permission_denied, ec), end;
       !ec && it != end; it.increment(ec))
    entries.push_back(*it);
  if (ec) throw Error("cannot list type directory " + path.string() + ": " + ec.message());
  std::sort(entries.begin(), entries.end(),
            [](const auto& a, const auto& b) { return a.path() < b.path(); });
  for (const fs::directory_entry& e : entries) {
    std::error_code e_ec;
    if (e.is_directory(e_ec)) {
      collect(e.path(), files, seen_dirs);
    } else if (e.path().extension() == ".lcm" && e.is_regular_file(e_ec)) {
      files.push_back(e.path());
    }
  }
}

}  // namespace

void TypeRegistry::add(std::vector<StructType> parsed) {
  for (StructType& s : parsed) {
    const std::string name = s.full_name();
    if (auto it = by_name_.find(name); it != by_name_.end()) {
      if (same_definition(*it->second, s)) continue;
      throw Error("type '" + name + "' is defined differently in " + it->second->file + ":" +
                  std::to_string(it->second->line) + " and " + s.file + ":" + std::to_string(s.line));
    }
    types_.push_back(std::make_unique<StructType>(std::move(s)));
    by_name_.emplace(name, types_.back().get());
  }
}

void TypeRegistry::resolve() {
  for (auto& t : types_) {
    for (Member& m : t->members) {
      if (m.primitive) continue;
      const StructType* nested = find(m.type_name);
      if (!nested)
        throw Error(t->file + ":" + std::to_string(m.line) + ":" + std::to_string(m.column) +
                    ": unknown type '" + m.type_name + "' of member '" + t->full_name() + "." +
                    m.name + "' (not in the type path)");
      m.nested = nested;
    }
  }
  by_fingerprint_.clear();
  Walk hashes, sizes;
  for (auto& t : types_) {
    hashes.cut = sizes.cut = false;
    t->fingerprint = recursive_hash(*t, hashes);
    t->min_encoded_size = min_size(*t, sizes);
    by_fingerprint_.emplace(t->fingerprint, t.get());  // first one wins
  }
}

TypeRegistry TypeRegistry::load(const std::vector<fs::path>& paths) {
  std::vector<fs::path> files;
  std::set<fs::path> seen_dirs;
  for (const fs::path& p : paths) collect(p, files, seen_dirs);
  TypeRegistry r;
  std::set<fs::path> seen_files;
  for (const fs::path& f : files) {
    std::error_code ec;
    const fs::path canonical = fs::canonical(f, ec);
    if (!ec && !seen_files.insert(canonical).second) continue;
    r.add(parse_file(f));
  }
  r.resolve();
  return r;
}

TypeRegistry TypeRegistry::load_texts(const std::vector<std::pair<std::string, std::string>>& texts) {
  TypeRegistry r;
  for (const auto& [file, text] : texts) r.add(parse(text, file));
  r.resolve();
  return r;
}

std::vector<fs::path> TypeRegistry::env_paths() {
  std::vector<fs::path> out;
  const char* env = std::getenv("LCMX_TYPES_PATH");
  if (!env) return out;
  std::stringstream ss(env);
  std::string item;
  while (std::getline(ss, item, ':'))
    if (!item.empty()) out.emplace_back(item);
  return out;
}

std::vector<fs::path> TypeRegistry::paths_or_env(const std::vector<std::string>& types_args) {
  if (types_args.empty()) return env_paths();
  std::vector<fs::path> out;
  for (const std::string& arg : types_args) {
    std::stringstream ss(arg);
    std::string item;
    while (std::getline(ss, item, ':'))
      if (!item.empty()) out.emplace_back(item);
  }
  return out;
}

const StructType* TypeRegistry::find(std::string_view full_name) const noexcept {
  const auto it = by_name_.find(std::string(full_name));
  return it == by_name_.end() ? nullptr : it->second;
}

const StructType* TypeRegistry::find(std::uint64_t fingerprint) const noexcept {
  const auto it = by_fingerprint_.find(fingerprint);
  return it == by_fingerprint_.end() ? nullptr : it->second;
}

const StructType& TypeRegistry::at(std::string_view full_name) const {
  if (const StructType* t = find(full_name)) return *t;
  throw Error("unknown type '" + std::string(full_name) + "' (not in the type path)");
}

std::size_t min_encoded_size(Primitive p) noexcept {
  switch (p) {
    case Primitive::int8:
    case Primitive::boolean:
    case Primitive::byte: return 1;
    case Primitive::int16: return 2;
    case Primitive::int32:
    case Primitive::float32: return 4;
    case Primitive::int64:
    case Primitive::float64: return 8;
    case Primitive::string: return 5;  // int32 length (>= 1) + the terminating NUL
  }
  return 0;
}

}  // namespace lcmx::types
