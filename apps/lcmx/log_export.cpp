// `lcmx log export FILE`: an LCM event log to MCAP (json messages, jsonschema schemas from the
// `.lcm` files) or to CSV files (one per channel), decoding messages with run-time types
// (lcmx::types, --types / LCMX_TYPES_PATH) found by the fingerprint in their first 8 bytes.
//
// Messages whose fingerprint is in no `.lcm` file of the type path, or that do not decode,
// are skipped and counted per channel (reported at the end, with the fingerprints seen): a
// consumer of the export sees only well-typed data. Damaged logs are exported up to the damage
// and past it where the reader finds the next event; every damaged range is reported.
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cctype>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <set>
#include <sstream>
#include <utility>

#include "json_schema.hpp"
#include "lcmx/log/eventlog.hpp"
#include "lcmx/types/types.hpp"
#include "log_cmds.hpp"
#include "log_common.hpp"
#include "mcap_writer.hpp"

namespace lcmx::cli {
namespace {

namespace fs = std::filesystem;

// Fixed-size arrays of at most this many elements become one CSV column per element.
constexpr std::size_t kExpandMax = 64;

struct ExportOptions {
  std::string file, output, format = "mcap", channel = ".*";
  std::vector<std::string> exclude, types, fields;
  bool force = false, quiet = false, json = false;
};
ExportOptions g_export;

std::string hex_fp(std::uint64_t fp) {
  char b[24];
  std::snprintf(b, sizeof b, "0x%016llx", static_cast<unsigned long long>(fp));
  return b;
}

// ---- CSV ----

std::string csv_cell(const std::string& s) {
  if (s.find_first_of(",\"\r\n") == std::string::npos && (s.empty() || (s.front() != ' ' && s.back() != ' '))) return s;
  std::string o = "\"";
  for (char c : s) {
    if (c == '"') o += '"';
    o += c;
  }
  return o + "\"";
}

// A scalar as a CSV cell: integers in decimal, floats shortest round-trip (nan, inf, -inf),
// booleans true/false, strings as they are unless they start like a formula (=, +, -, @, tab,
// CR: then with a leading apostrophe, safe_text.hpp formula_safe); anything else as its JSON
// (an array or a struct: starts with [ or {).
std::string scalar_cell(const types::Value& v) {
  if (const auto* d = std::get_if<double>(&v.data))
    if (!std::isfinite(*d)) return std::isnan(*d) ? "nan" : (*d > 0 ? "inf" : "-inf");
  if (const auto* f = std::get_if<float>(&v.data))
    if (!std::isfinite(*f)) return std::isnan(*f) ? "nan" : (*f > 0 ? "inf" : "-inf");
  if (const auto* s = std::get_if<std::string>(&v.data)) return formula_safe(*s);
  return types::to_json(v);
}

bool expandable(const types::Member& m) {
  std::size_t n = 1;
  for (const auto& d : m.dims) {
    if (d.variable || d.fixed <= 0) return false;
    n *= static_cast<std::size_t>(d.fixed);
    if (n > kExpandMax) return false;
  }
  return true;
}

// Flattens a struct into columns: with s == nullptr the headers, else the cells, in the same
// order. Scalars are one column each ("a.b"), fixed arrays of at most kExpandMax elements one
// per element ("c[0][1]", structs inside flattened too), other arrays one column of JSON.
void flat_struct(const types::StructType& t, const types::Struct* s, const std::string& prefix,
                 std::vector<std::string>& out);

void flat_member(const types::Member& m, const types::Value* v, std::size_t d, const std::string& name,
                 std::vector<std::string>& out) {
  if (d == m.dims.size()) {
    if (m.primitive || m.nested == nullptr) out.push_back(v ? scalar_cell(*v) : name);
    else flat_struct(*m.nested, v ? &v->as<types::Struct>() : nullptr, name + ".", out);
    return;
  }
  if (d == 0 && !expandable(m)) {
    out.push_back(v ? types::to_json(*v) : name);
    return;
  }
  for (std::int64_t i = 0; i < m.dims[d].fixed; ++i) {
    const auto idx = static_cast<std::size_t>(i);
    const std::string n = name + "[" + std::to_string(i) + "]";
    if (v == nullptr) {
      flat_member(m, nullptr, d + 1, n, out);
    } else if (const auto* a = std::get_if<types::Array>(&v->data)) {
      flat_member(m, &a->at(idx), d + 1, n, out);
    } else {
      const types::Value b{static_cast<std::int64_t>(v->as<types::Bytes>().at(idx))};
      flat_member(m, &b, d + 1, n, out);
    }
  }
}

void flat_struct(const types::StructType& t, const types::Struct* s, const std::string& prefix,
                 std::vector<std::string>& out) {
  for (std::size_t i = 0; i < t.members.size(); ++i)
    flat_member(t.members[i], s ? &s->fields.at(i).value : nullptr, 0, prefix + t.members[i].name, out);
}

// Checks a --fields path against a type: "" if it names something a message of `t` has (an
// index into a variable array may still be out of range in a given message: an empty cell),
// else why not.
std::string check_path(const types::StructType& t, const std::string& path) {
  if (path.empty()) return "empty field name";
  const types::StructType* cur = &t;
  std::size_t pos = 0;
  while (true) {
    if (cur == nullptr) return "'" + path + "': " + path.substr(0, pos - 1) + " is not a struct";
    const auto end = path.find_first_of(".[", pos);
    const std::string name = path.substr(pos, end == std::string::npos ? std::string::npos : end - pos);
    const auto* m = cur->find_member(name);
    if (m == nullptr) return "no field '" + name + "' in " + cur->full_name() + " ('" + path + "')";
    pos = end == std::string::npos ? path.size() : end;
    std::size_t k = 0;
    while (pos < path.size() && path[pos] == '[') {
      const auto close = path.find(']', pos);
      if (close == std::string::npos) return "'" + path + "': missing ]";
      const std::string idx = path.substr(pos + 1, close - pos - 1);
      if (idx.empty() || idx.find_first_not_of("0123456789") != std::string::npos)
        return "'" + path + "': bad index [" + idx + "]";
      if (k >= m->dims.size()) return "'" + path + "': " + name + " has " + std::to_string(m->dims.size()) + " dimension(s)";
      if (!m->dims[k].variable && std::stoll(idx) >= m->dims[k].fixed)
        return "'" + path + "': index " + idx + " out of range (" + name + " has " + std::to_string(m->dims[k].fixed) + ")";
      ++k;
      pos = close + 1;
    }
    if (pos == path.size()) return "";
    if (path[pos] != '.') return "'" + path + "': unexpected '" + path.substr(pos, 1) + "'";
    if (k != m->dims.size()) return "'" + path + "': " + name + " is an array: index it before '.'";
    cur = m->nested;
    ++pos;
  }
}

std::string file_safe(const std::string& channel) {
  std::string s;
  for (char c : channel)
    s += (std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == '-') ? c : '_';
  if (s.empty() || s[0] == '.') s.insert(s.begin(), '_');
  return s;
}

// ---- the export ----

struct ChannelReport {
  std::set<std::string> types;  // full names exported
  std::uint64_t exported = 0, unknown = 0, unknown_bytes = 0, undecodable = 0;
  std::set<std::uint64_t> unknown_fps;  // first few
  bool short_messages = false;          // some were shorter than a fingerprint
  std::string first_error;
  std::vector<std::string> outputs;
};

// Where decoded messages go: one implementation per format.
class Sink {
 public:
  virtual ~Sink() = default;
  // Throws std::runtime_error for a bad --fields (exit 2) or I/O errors.
  virtual void write(const eventlog::Event& e, const types::StructType& t, const types::Value& v,
                     ChannelReport& rep) = 0;
  virtual void close() = 0;
};

class UsageError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

class McapSink : public Sink {
 public:
  explicit McapSink(const std::string& path) : w_(McapWriter::open(path)), path_(path) {}
  void write(const eventlog::Event& e, const types::StructType& t, const types::Value& v, ChannelReport& rep) override {
    auto key = std::make_pair(e.channel, t.fingerprint);
    auto it = channels_.find(key);
    if (it == channels_.end()) {
      auto s = schemas_.find(t.fingerprint);
      if (s == schemas_.end()) {
        s = schemas_.emplace(t.fingerprint, w_.add_schema(t.full_name(), "jsonschema", json_schema(t))).first;
        if (auto why = foxglove_unsupported(t); !why.empty()) notes_.push_back(t.full_name() + ": " + why);
      }
      const auto id = w_.add_channel(s->second, e.channel, "json",
                                     {{"lcm_type", t.full_name()}, {"lcm_fingerprint", hex_fp(t.fingerprint)}});
      it = channels_.emplace(key, id).first;
      if (rep.outputs.empty()) rep.outputs.push_back(path_);
    }
    const std::uint64_t ns = e.timestamp_us > 0 ? static_cast<std::uint64_t>(e.timestamp_us) * 1000u : 0;
    json_ = types::to_json(v);
    w_.add_message(it->second, static_cast<std::uint32_t>(e.number), ns, ns, json_);
  }
  void close() override { w_.close(); }
  // Types whose messages Foxglove cannot show, and why.
  const std::vector<std::string>& notes() const { return notes_; }

 private:
  McapWriter w_;
  std::vector<std::string> notes_;
  std::string path_;
  std::map<std::uint64_t, std::uint16_t> schemas_;
  std::map<std::pair<std::string, std::uint64_t>, std::uint16_t> channels_;
  std::string json_;
};

class CsvSink : public Sink {
 public:
  CsvSink(std::string dir, std::vector<std::string> fields, bool force)
      : dir_(std::move(dir)), fields_(std::move(fields)), force_(force) {}
  void write(const eventlog::Event& e, const types::StructType& t, const types::Value& v, ChannelReport& rep) override {
    auto key = std::make_pair(e.channel, t.fingerprint);
    auto it = files_.find(key);
    if (it == files_.end()) it = files_.emplace(key, open(e.channel, t, rep)).first;
    auto& f = *it->second;
    cells_.clear();
    if (fields_.empty()) {
      flat_struct(t, &v.as<types::Struct>(), "", cells_);
    } else {
      for (const auto& p : fields_) {
        try {
          cells_.push_back(scalar_cell(types::field(v, p)));
        } catch (const types::Error&) {
          cells_.emplace_back();  // an index beyond this message's variable array
        }
      }
    }
    line_ = std::to_string(e.timestamp_us);
    for (const auto& c : cells_) line_ += "," + csv_cell(c);
    line_ += "\n";
    f.out.write(line_.data(), static_cast<std::streamsize>(line_.size()));
    if (!f.out) throw std::runtime_error("cannot write " + f.path + ": " + std::strerror(errno));
  }
  void close() override {
    for (auto& [k, f] : files_) {
      f->out.close();
      if (!f->out) throw std::runtime_error("cannot write " + f->path + ": " + std::strerror(errno));
    }
  }

 private:
  struct File {
    std::string path;
    std::ofstream out;
  };
  std::unique_ptr<File> open(const std::string& channel, const types::StructType& t, ChannelReport& rep) {
    for (const auto& p : fields_)
      if (auto err = check_path(t, p); !err.empty())
        throw UsageError("--fields: channel " + channel + " (type " + t.full_name() + "): " + err);
    // CHANNEL.csv; a second type on one channel, or a name clash after replacing characters
    // that do not belong in file names, gets a suffix.
    std::string base = file_safe(channel);
    if (!rep.types.empty()) base += "@" + t.full_name();
    std::string name = base + ".csv";
    for (int n = 2; used_.count(name); ++n) name = base + "~" + std::to_string(n) + ".csv";
    used_.insert(name);
    auto f = std::make_unique<File>();
    f->path = (fs::path(dir_) / name).string();
    if (!force_ && fs::exists(f->path)) throw UsageError(f->path + " exists (use --force to overwrite)");
    f->out.open(f->path, std::ios::binary | std::ios::trunc);
    if (!f->out) throw std::runtime_error("cannot create " + f->path + ": " + std::strerror(errno));
    std::vector<std::string> headers;
    if (fields_.empty()) flat_struct(t, nullptr, "", headers);
    else headers = fields_;
    std::string h = "timestamp_us";
    for (const auto& c : headers) h += "," + csv_cell(c);
    h += "\n";
    f->out << h;
    rep.outputs.push_back(f->path);
    return f;
  }
  std::string dir_;
  std::vector<std::string> fields_;
  bool force_;
  std::map<std::pair<std::string, std::uint64_t>, std::unique_ptr<File>> files_;
  std::set<std::string> used_;
  std::vector<std::string> cells_;
  std::string line_;
};

std::vector<std::string> split_fields(const std::vector<std::string>& args) {
  std::vector<std::string> out;
  for (const auto& a : args) {
    // Commas separate fields, except inside [...] (none are valid there anyway).
    std::string cur;
    for (char c : a) {
      if (c == ',') {
        if (!cur.empty()) out.push_back(cur);
        cur.clear();
      } else if (c != ' ') {
        cur += c;
      }
    }
    if (!cur.empty()) out.push_back(cur);
  }
  return out;
}

int run_export() {
  auto o = g_export;
  const std::string me = "lcmx log export: ";
  types::TypeRegistry registry;
  try {
    const auto paths = types::TypeRegistry::paths_or_env(o.types);
    if (paths.empty()) {
      std::cerr << me << "no types: give --types DIR|FILE (.lcm files) or set LCMX_TYPES_PATH\n";
      return 2;
    }
    registry = types::TypeRegistry::load(paths);
  } catch (const std::exception& e) {
    std::cerr << me << e.what() << "\n";
    return 2;
  }
  const auto fields = split_fields(o.fields);
  if (!fields.empty() && o.format != "csv") {
    std::cerr << me << "--fields applies to --format csv only\n";
    return 2;
  }
  if (o.output.empty()) {
    fs::path p(o.file);
    o.output = o.format == "mcap" ? p.replace_extension(".mcap").string() : p.replace_extension("").string() + "_csv";
    if (o.output == o.file) o.output += o.format == "mcap" ? ".mcap" : "_csv";
  }
  std::unique_ptr<ChannelFilter> filter;
  try {
    filter = std::make_unique<ChannelFilter>(o.channel, o.exclude);
  } catch (const std::regex_error& e) {
    std::cerr << me << "bad channel expression: " << e.what() << "\n";
    return 2;
  }

  std::map<std::string, ChannelReport> report;
  std::uint64_t events = 0, exported = 0, filtered = 0;
  std::vector<eventlog::Damage> damage;
  std::uint64_t damage_count = 0, damaged_bytes = 0;
  std::vector<std::string> foxglove_notes;
  const bool progress = !o.quiet && ::isatty(STDERR_FILENO);
  try {
    auto reader = eventlog::Reader::open(o.file);
    std::unique_ptr<Sink> sink;
    if (std::error_code ec; fs::equivalent(o.output, o.file, ec)) {
      std::cerr << me << "the output " << o.output << " is the log itself\n";
      return 2;
    }
    if (o.format == "mcap") {
      if (!o.force && fs::exists(o.output)) {
        std::cerr << me << o.output << " exists (use --force to overwrite)\n";
        return 2;
      }
      sink = std::make_unique<McapSink>(o.output);
    } else {
      std::error_code ec;
      fs::create_directories(o.output, ec);
      if (!fs::is_directory(o.output)) {
        std::cerr << me << "cannot create directory " << o.output << (ec ? ": " + ec.message() : "") << "\n";
        return 1;
      }
      sink = std::make_unique<CsvSink>(o.output, fields, o.force);
    }
    eventlog::Event e;
    auto next_progress = std::chrono::steady_clock::now();
    while (reader.next(e)) {
      ++events;
      if (progress && (events & 255) == 0 && std::chrono::steady_clock::now() >= next_progress) {
        next_progress = std::chrono::steady_clock::now() + std::chrono::milliseconds(200);
        const double pct = reader.size() ? 100.0 * static_cast<double>(reader.position()) / static_cast<double>(reader.size()) : 0;
        std::cerr << "\rexporting " << o.file << ": " << fmt("%5.1f", pct) << " %  " << events << " events" << std::flush;
      }
      if (!(*filter)(e.channel)) {
        ++filtered;
        continue;
      }
      auto& rep = report[e.channel];
      const auto fp = types::message_fingerprint(e.data.data(), e.data.size());
      const types::StructType* t = fp ? registry.find(*fp) : nullptr;
      if (t == nullptr) {
        ++rep.unknown;
        rep.unknown_bytes += e.size;
        if (!fp) rep.short_messages = true;
        else if (rep.unknown_fps.size() < 8) rep.unknown_fps.insert(*fp);
        continue;
      }
      types::Value v;
      try {
        v = types::decode(*t, e.data.data(), e.data.size());
      } catch (const types::Error& err) {
        if (rep.undecodable++ == 0) rep.first_error = "event " + std::to_string(e.number) + ": " + err.what();
        continue;
      }
      sink->write(e, *t, v, rep);
      rep.types.insert(t->full_name());
      ++rep.exported;
      ++exported;
    }
    sink->close();
    if (const auto* m = dynamic_cast<const McapSink*>(sink.get())) foxglove_notes = m->notes();
    damage = reader.damage();
    damage_count = reader.damage_count();
    damaged_bytes = reader.damaged_bytes();
  } catch (const UsageError& e) {
    if (progress) std::cerr << "\n";
    std::cerr << me << e.what() << "\n";
    return 2;
  } catch (const std::exception& e) {
    if (progress) std::cerr << "\n";
    std::cerr << me << e.what() << "\n";
    // A failed export (a full disk) leaves no half-written files that look complete.
    std::set<std::string> partial;
    for (const auto& [ch, r] : report) partial.insert(r.outputs.begin(), r.outputs.end());
    for (const auto& path : partial) {
      std::error_code ec;
      if (fs::is_regular_file(path, ec) && fs::remove(path, ec)) std::cerr << me << "removed the partial output " << path << "\n";
    }
    return 1;
  }
  if (progress) std::cerr << "\r\033[Kexporting " << o.file << ": 100.0 %  " << events << " events\n";

  auto damage_text = [](const eventlog::Damage& d) {
    return d.kind == eventlog::Damage::Kind::truncated
               ? "the log ends with truncated bytes at offset " + std::to_string(d.offset) + " (" +
                     std::to_string(d.length) + " bytes): exported up to there"
               : "damaged log: " + std::to_string(d.length) + " bytes skipped at offset " + std::to_string(d.offset);
  };
  if (o.json) {
    std::ostringstream j;
    j << "{\"file\":" << json_str(o.file) << ",\"format\":" << json_str(o.format) << ",\"output\":" << json_str(o.output)
      << ",\"events\":" << events << ",\"exported\":" << exported << ",\"filtered_out\":" << filtered << ",\"channels\":[";
    bool first = true;
    for (const auto& [ch, r] : report) {
      j << (first ? "" : ",") << "{\"channel\":" << json_str(ch) << ",\"types\":[";
      bool f2 = true;
      for (const auto& t : r.types) j << (std::exchange(f2, false) ? "" : ",") << json_str(t);
      j << "],\"exported\":" << r.exported << ",\"unknown\":" << r.unknown << ",\"unknown_bytes\":" << r.unknown_bytes
        << ",\"unknown_fingerprints\":[";
      f2 = true;
      for (auto fp : r.unknown_fps) j << (std::exchange(f2, false) ? "" : ",") << json_str(hex_fp(fp));
      j << "],\"undecodable\":" << r.undecodable;
      if (!r.first_error.empty()) j << ",\"error\":" << json_str(r.first_error);
      j << ",\"outputs\":[";
      f2 = true;
      for (const auto& p : r.outputs) j << (std::exchange(f2, false) ? "" : ",") << json_str(p);
      j << "]}";
      first = false;
    }
    j << "],\"foxglove_unsupported\":[";
    for (std::size_t i = 0; i < foxglove_notes.size(); ++i) j << (i ? "," : "") << json_str(foxglove_notes[i]);
    j << "],\"damage_count\":" << damage_count << ",\"damaged_bytes\":" << damaged_bytes << ",\"damage\":[";
    for (std::size_t i = 0; i < damage.size(); ++i)
      j << (i ? "," : "") << "{\"kind\":\"" << eventlog::to_string(damage[i].kind) << "\",\"offset\":" << damage[i].offset
        << ",\"length\":" << damage[i].length << "}";
    j << "]}";
    std::cout << j.str() << std::endl;
  } else if (!o.quiet) {
    std::cout << "exported " << exported << " of " << events << " events to " << o.output
              << (o.format == "mcap" ? " (MCAP: json messages, jsonschema schemas)" : " (CSV, one file per channel)")
              << "\n";
    for (const auto& [ch, r] : report) {
      std::string types;
      for (const auto& t : r.types) types += (types.empty() ? "" : " | ") + t;
      std::cout << "  " << printable(ch) << "  [" << (types.empty() ? "-" : types) << "]  " << r.exported << " exported";
      if (r.unknown) {
        std::cout << ", " << r.unknown << " of unknown type skipped (" << r.unknown_bytes << " bytes; fingerprint";
        for (auto fp : r.unknown_fps) std::cout << " " << hex_fp(fp);
        if (r.short_messages) std::cout << " none: shorter than 8 bytes";
        std::cout << ")";
      }
      if (r.undecodable)
        std::cout << ", " << r.undecodable << " undecodable skipped (first: " << printable(r.first_error) << ")";
      std::cout << "\n";
    }
    if (filtered) std::cout << "  " << filtered << " events on channels left out by -c/-x\n";
  }
  if (!o.quiet)
    for (const auto& n : foxglove_notes)
      std::cerr << "lcmx log export: note: Foxglove's JSON Schema reader cannot show " << n
                << " (it has no arrays of arrays nor $ref); other readers can\n";
  for (const auto& d : damage) std::cerr << "lcmx log export: " << damage_text(d) << "\n";
  if (damage_count > damage.size())
    std::cerr << "lcmx log export: " << damage_count - damage.size() << " more damaged ranges not listed\n";
  if (events == 0) {
    std::cerr << me << o.file << " holds no readable event\n";
    return 1;
  }
  return 0;
}

}  // namespace

Verb add_log_export(CLI::App& log) {
  auto* c = log.add_subcommand(
      "export", "decode a log with run-time types (.lcm files) into MCAP (json + jsonschema) or CSV per channel");
  auto& o = g_export;
  c->add_option("file", o.file, "LCM log file")->required();
  c->add_option("--format", o.format, "mcap or csv")->check(CLI::IsMember({"mcap", "csv"}))->capture_default_str();
  c->add_option("-o,--output", o.output,
                "mcap: the file (default: FILE with extension .mcap); csv: the directory (default: FILE_csv)");
  c->add_option("--types", o.types, "`.lcm` file or directory (searched recursively); repeatable, ':'-separated "
                                    "lists too (default: LCMX_TYPES_PATH)")
      ->allow_extra_args(false);  // one value per --types: `--types DIR FILE` leaves FILE alone
  c->add_option("--fields", o.fields,
                "csv: columns to write, e.g. header.seq,position[0] (default: every field, flattened)")
      ->allow_extra_args(false);
  c->add_option("-c,--channel", o.channel, "export channels whose whole name matches this regular expression")
      ->capture_default_str();
  c->add_option("-x,--exclude", o.exclude, "leave out channels matching this expression (repeatable)")
      ->allow_extra_args(false);
  c->add_flag("-f,--force", o.force, "overwrite existing output files");
  c->add_flag("-q,--quiet", o.quiet, "no progress line (shown on a terminal) and no summary (errors and damage only)");
  c->add_flag("--json", o.json, "print the summary as JSON on stdout");
  return {c, [] { return run_export(); }};
}

}  // namespace lcmx::cli
