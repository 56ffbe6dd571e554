#include "monitor_model.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

namespace lcmx::cli::monitor {
namespace {

using Endpoint = lcmx_msgs::endpoint_t;

double seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

std::string hex64(std::uint64_t v) {
  char b[24];
  std::snprintf(b, sizeof b, "0x%016llx", static_cast<unsigned long long>(v));
  return b;
}

std::string join(const std::set<std::string>& s, const char* sep) {
  std::string o;
  for (const auto& x : s) o += (o.empty() ? "" : sep) + x;
  return o;
}

}  // namespace

const char* column_name(Column c) {
  static const char* const names[] = {"channel", "type", "publishers", "path", "Hz",
                                      "jitter",  "bandwidth", "drops", "age"};
  return names[static_cast<int>(c)];
}

std::string human(double v) {
  char b[32];
  if (v >= 1e9) std::snprintf(b, sizeof b, "%.1fG", v / 1e9);
  else if (v >= 1e6) std::snprintf(b, sizeof b, "%.1fM", v / 1e6);
  else if (v >= 1e3) std::snprintf(b, sizeof b, "%.1fk", v / 1e3);
  else std::snprintf(b, sizeof b, "%.0f", v);
  return b;
}

Model::Model(const types::TypeRegistry* registry, Clock::duration window, std::size_t history,
             Clock::time_point start)
    : registry_(registry), window_(window), history_(history), created_(start) {}

Model::Chan& Model::chan_locked(std::string_view channel) {
  auto it = chans_.find(channel);
  if (it == chans_.end()) it = chans_.emplace(std::string(channel), Chan{}).first;
  return it->second;
}

void Model::on_message(std::string_view channel, std::span<const std::byte> data, Clock::time_point t) {
  std::lock_guard lock(mu_);
  auto& c = chan_locked(channel);
  ++c.open.n;
  c.open.bytes += data.size();
  if (c.last) {
    const double dt = seconds(t - *c.last);
    ++c.open.intervals;
    c.open.sum_dt += dt;
    c.open.sum_dt2 += dt * dt;
  }
  c.last = t;
  ++c.messages;
  c.last_size = data.size();
  c.fingerprint = types::message_fingerprint(data.data(), data.size());
  if (!opened_.empty() && channel == opened_) {
    latest_.assign(data.begin(), data.end());
    latest_new_ = true;
  }
}

void Model::tick(Clock::time_point now) {
  std::lock_guard lock(mu_);
  const double period = seconds(now - (last_tick_ ? *last_tick_ : created_));
  for (auto& [name, c] : chans_) {
    Sample s = c.open;
    s.start = last_tick_ ? *last_tick_ : created_;
    s.end = now;
    c.open = Sample{};
    c.window.push_back(s);
    while (!c.window.empty() && now - c.window.front().end >= window_) c.window.pop_front();
    if (period > 0) {
      c.history.push_back(static_cast<double>(s.n) / period);
      while (c.history.size() > history_) c.history.pop_front();
    }
  }
  last_tick_ = now;
}

void Model::set_topology(const std::vector<discovery::Participant>& ps, std::uint64_t self) {
  std::lock_guard lock(mu_);
  for (auto& [name, c] : chans_) {
    c.publishers.clear();
    c.beacon_types.clear();
    c.announced = false;
  }
  for (const auto& p : ps) {
    const auto& b = p.beacon;
    if (static_cast<std::uint64_t>(b.participant_id) == self) continue;
    char host[8];
    std::snprintf(host, sizeof host, "%04llx", static_cast<unsigned long long>(b.host_id) & 0xffffu);
    for (const auto& e : b.endpoints) {
      if (e.kind != Endpoint::KIND_PUBLISHER) continue;
      auto& c = chan_locked(e.topic);
      c.announced = true;
      c.publishers.insert(b.process_name + "[" + std::to_string(b.pid) + "]@" + host);
      if (e.fingerprint != 0 && !e.type_name.empty()) c.beacon_types.insert(e.type_name);
    }
  }
}

void Model::set_stats(const std::vector<std::pair<std::string, SubscriberStats>>& stats) {
  std::lock_guard lock(mu_);
  for (const auto& [name, st] : stats) {
    auto& c = chan_locked(name);
    c.drops = st.drops;
    c.paths.clear();
    for (const auto& pair : st.publishers) {
      c.paths.insert(to_string(pair.path));
      if (pair.publisher_participant == 0) c.publishers.insert("LCM sender");
    }
  }
}

std::string Model::type_name(const std::string& channel, std::optional<std::uint64_t> fp) const {
  if (fp && registry_ != nullptr)
    if (const auto* t = registry_->find(*fp)) return t->full_name();
  auto it = chans_.find(channel);
  if (it != chans_.end() && !it->second.beacon_types.empty()) return join(it->second.beacon_types, "|");
  if (fp) return hex64(*fp);
  return "?";
}

std::vector<Row> Model::rows(Clock::time_point now) const {
  std::lock_guard lock(mu_);
  std::vector<Row> out;
  for (const auto& [name, c] : chans_) {
    if (filter_ && !std::regex_search(name, *filter_)) continue;
    if (c.messages == 0 && !c.announced) continue;  // a publisher that left before sending
    Row r;
    r.channel = name;
    r.type = type_name(name, c.fingerprint);
    r.publishers = join(c.publishers, " ");
    r.paths = join(c.paths, ",");
    r.drops = c.drops;
    r.messages = c.messages;
    r.last_size = c.last_size;
    r.age_s = c.last ? seconds(now - *c.last) : -1;
    std::uint64_t n = 0, bytes = 0, intervals = 0;
    double sum = 0, sum2 = 0;
    for (const auto& s : c.window) {
      n += s.n;
      bytes += s.bytes;
      intervals += s.intervals;
      sum += s.sum_dt;
      sum2 += s.sum_dt2;
    }
    // Rates over the closed samples: from the start of the first to the end of the last.
    if (!c.window.empty()) {
      const double dur = seconds(c.window.back().end - c.window.front().start);
      if (dur > 0) {
        r.hz = static_cast<double>(n) / dur;
        r.bytes_per_s = static_cast<double>(bytes) / dur;
      }
    }
    if (intervals >= 2) {
      const double mean = sum / static_cast<double>(intervals);
      const double var = std::max(0.0, sum2 / static_cast<double>(intervals) - mean * mean);
      r.jitter_ms = std::sqrt(var) * 1e3;
    }
    out.push_back(std::move(r));
  }
  const auto key = [this](const Row& a, const Row& b) -> int {  // <0, 0, >0
    auto cmp = [](auto x, auto y) { return x < y ? -1 : (y < x ? 1 : 0); };
    switch (sort_) {
      case Column::channel: return 0;
      case Column::type: return cmp(a.type, b.type);
      case Column::publishers: return cmp(a.publishers, b.publishers);
      case Column::path: return cmp(a.paths, b.paths);
      case Column::hz: return cmp(a.hz, b.hz);
      case Column::jitter: return cmp(a.jitter_ms, b.jitter_ms);
      case Column::bandwidth: return cmp(a.bytes_per_s, b.bytes_per_s);
      case Column::drops: return cmp(a.drops, b.drops);
      case Column::age: return cmp(a.age_s, b.age_s);
    }
    return 0;
  };
  std::sort(out.begin(), out.end(), [&](const Row& a, const Row& b) {
    int k = key(a, b);
    if (k == 0) k = a.channel < b.channel ? -1 : (b.channel < a.channel ? 1 : 0);
    return descending_ ? k > 0 : k < 0;
  });
  return out;
}

void Model::set_sort(Column c, bool descending) {
  sort_ = c;
  descending_ = descending;
}

void Model::set_filter(const std::string& expression) {
  std::optional<std::regex> re;
  if (!expression.empty()) re.emplace(expression, std::regex::ECMAScript | std::regex::icase);
  std::lock_guard lock(mu_);
  filter_ = std::move(re);
  filter_text_ = expression;
}

void Model::open(const std::string& channel) {
  std::lock_guard lock(mu_);
  opened_ = channel;
  latest_.clear();
  latest_new_ = false;
}

void Model::close() { open(""); }

std::optional<std::vector<std::byte>> Model::take_latest() {
  std::lock_guard lock(mu_);
  if (!latest_new_) return std::nullopt;
  latest_new_ = false;
  return latest_;
}

std::vector<double> Model::rate_history(const std::string& channel) const {
  std::lock_guard lock(mu_);
  auto it = chans_.find(channel);
  if (it == chans_.end()) return {};
  return {it->second.history.begin(), it->second.history.end()};
}

// ---- tree ----

namespace {

std::string scalar_text(const types::Value& v) {
  char b[64];
  if (v.is<std::int64_t>()) return std::to_string(v.as<std::int64_t>());
  if (v.is<double>()) {
    std::snprintf(b, sizeof b, "%.9g", v.as<double>());
    return b;
  }
  if (v.is<float>()) {
    std::snprintf(b, sizeof b, "%.7g", static_cast<double>(v.as<float>()));
    return b;
  }
  if (v.is<bool>()) return v.as<bool>() ? "true" : "false";
  if (v.is<std::string>()) {
    std::string o = "\"";
    for (char c : v.as<std::string>()) {
      if (c == '\n') o += "\\n";
      else if (static_cast<unsigned char>(c) < 0x20) o += '?';
      else o += c;
    }
    return o + "\"";
  }
  return "";
}

struct TreeBuilder {
  const std::set<std::string>& toggled;
  std::size_t fold_over, max_elements;
  std::vector<TreeLine> out;

  bool folded(const std::string& path, bool by_default) const { return by_default != (toggled.count(path) > 0); }

  void add(int depth, const std::string& label, const std::string& path, const types::Value& v) {
    const std::string name = label.empty() ? "" : label + ": ";
    if (v.is<types::Struct>()) {
      const auto& s = v.as<types::Struct>();
      const bool f = depth > 0 && folded(path, false);
      std::string t = s.type != nullptr ? s.type->full_name() : "struct";
      out.push_back({depth, path, name + t + (f ? " {...}" : ""), depth > 0, f});
      if (f) return;
      for (const auto& field : s.fields)
        add(depth + 1, field.name, path.empty() ? field.name : path + "." + field.name, field.value);
    } else if (v.is<types::Array>()) {
      const auto& a = v.as<types::Array>();
      const bool f = folded(path, a.size() > fold_over);
      std::string t = name + "[" + std::to_string(a.size()) + "]";
      if (f) {
        t += " {";
        for (std::size_t i = 0; i < a.size() && i < 4 && !a[i].is<types::Struct>() && !a[i].is<types::Array>(); ++i)
          t += (i ? ", " : "") + scalar_text(a[i]);
        t += a.empty() ? "}" : ", ...}";
      }
      out.push_back({depth, path, t, true, f});
      if (f) return;
      for (std::size_t i = 0; i < a.size(); ++i) {
        if (i == max_elements) {
          out.push_back({depth + 1, path + "[...]", "... " + std::to_string(a.size() - i) + " more", false, false});
          break;
        }
        add(depth + 1, "[" + std::to_string(i) + "]", path + "[" + std::to_string(i) + "]", a[i]);
      }
    } else if (v.is<types::Bytes>()) {
      const auto& b = v.as<types::Bytes>();
      const bool f = folded(path, true);
      std::string t = name + "bytes[" + std::to_string(b.size()) + "]";
      char h[4];
      if (f) {
        t += " {";
        for (std::size_t i = 0; i < b.size() && i < 8; ++i) {
          std::snprintf(h, sizeof h, "%02x", b[i]);
          t += (i ? " " : "") + std::string(h);
        }
        t += b.size() > 8 ? " ...}" : "}";
      }
      out.push_back({depth, path, t, true, f});
      if (f) return;
      for (std::size_t i = 0; i < b.size(); i += 16) {
        if (i / 16 == max_elements / 16 + 1) {
          out.push_back({depth + 1, path + "[...]", "... " + std::to_string(b.size() - i) + " more bytes", false, false});
          break;
        }
        char off[24];
        std::snprintf(off, sizeof off, "%06zx:", i);
        std::string line = off;
        for (std::size_t k = i; k < b.size() && k < i + 16; ++k) {
          std::snprintf(h, sizeof h, "%02x", b[k]);
          line += " " + std::string(h);
        }
        out.push_back({depth + 1, path + "@" + std::to_string(i), line, false, false});
      }
    } else {
      out.push_back({depth, path, name + scalar_text(v), false, false});
    }
  }
};

}  // namespace

std::vector<TreeLine> tree_lines(const types::Value& value, const std::set<std::string>& toggled,
                                 std::size_t fold_over, std::size_t max_elements) {
  TreeBuilder b{toggled, fold_over, max_elements, {}};
  b.add(0, "", "", value);
  return std::move(b.out);
}

std::string sparkline(const std::vector<double>& samples, std::size_t width, bool utf8) {
  static const char* const blocks[] = {" ", "\u2581", "\u2582", "\u2583", "\u2584",
                                       "\u2585", "\u2586", "\u2587", "\u2588"};
  static const char ascii[] = " .:-=+*#";
  const std::size_t n = std::min(width, samples.size());
  const auto first = samples.end() - static_cast<std::ptrdiff_t>(n);
  double top = 0;
  for (auto it = first; it != samples.end(); ++it) top = std::max(top, *it);
  std::string o;
  for (auto it = first; it != samples.end(); ++it) {
    const int levels = utf8 ? 8 : 7;
    int k = top > 0 ? static_cast<int>(std::lround(*it / top * levels)) : 0;
    if (*it > 0 && k == 0) k = 1;
    if (utf8) o += blocks[k];
    else o += ascii[k];
  }
  return o;
}

}  // namespace lcmx::cli::monitor
