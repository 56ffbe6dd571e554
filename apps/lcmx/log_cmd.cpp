// `lcmx log info FILE`: what an LCM event log holds (duration, start/end, per channel count,
// sizes and rate) and where it is damaged. Reads headers only (data is skipped).
#include <algorithm>
#include <iostream>
#include <map>
#include <sstream>

#include "lcmx/log/eventlog.hpp"
#include "log_cmds.hpp"
#include "log_common.hpp"

namespace lcmx::cli {
namespace {

struct LogOptions {
  std::string file;
  bool json = false;
};
LogOptions g_log;
CLI::App* g_info = nullptr;
Verb g_export_verb;  // log export (log_export.cpp)

struct Stats {
  std::uint64_t count = 0, bytes = 0;
  std::size_t min = SIZE_MAX, max = 0;
  std::int64_t first_ts = 0, last_ts = 0;
};

int run_info() {
  const auto& o = g_log;
  std::map<std::string, Stats> ch;
  std::uint64_t events = 0, size = 0, damaged_bytes = 0, damage_count = 0;
  std::int64_t first_ts = 0, last_ts = 0, min_ts = INT64_MAX, max_ts = INT64_MIN;
  std::uint64_t backwards = 0;  // timestamps lower than the previous event's
  std::vector<eventlog::Damage> damage;
  try {
    eventlog::ReaderOptions ro;
    ro.data_prefix = 0;
    auto r = eventlog::Reader::open(o.file, ro);
    eventlog::Event e;
    std::int64_t prev = INT64_MIN;
    while (r.next(e)) {
      if (events == 0) first_ts = e.timestamp_us;
      last_ts = e.timestamp_us;
      min_ts = std::min(min_ts, e.timestamp_us);
      max_ts = std::max(max_ts, e.timestamp_us);
      if (e.timestamp_us < prev) ++backwards;
      prev = e.timestamp_us;
      ++events;
      auto& s = ch[e.channel];
      if (s.count == 0) s.first_ts = e.timestamp_us;
      s.last_ts = e.timestamp_us;
      ++s.count;
      s.bytes += e.size;
      s.min = std::min(s.min, e.size);
      s.max = std::max(s.max, e.size);
    }
    damage = r.damage();
    damage_count = r.damage_count();
    damaged_bytes = r.damaged_bytes();
    size = r.size();
  } catch (const std::exception& e) {
    std::cerr << "lcmx log info: " << e.what() << "\n";
    return 1;
  }
  (void)first_ts;
  (void)last_ts;
  const double duration = events ? static_cast<double>(max_ts - min_ts) / 1e6 : 0.0;
  auto rate = [&](const Stats& s) {
    return duration > 0 ? static_cast<double>(s.count) / duration : 0.0;
  };
  if (o.json) {
    std::ostringstream j;
    j << "{\"file\":" << json_str(o.file) << ",\"bytes\":" << size << ",\"events\":" << events;
    if (events)
      j << ",\"start_us\":" << min_ts << ",\"end_us\":" << max_ts << ",\"start\":" << json_str(format_us(min_ts))
        << ",\"end\":" << json_str(format_us(max_ts));
    j << ",\"duration_s\":" << fmt("%.6f", duration) << ",\"timestamps_backwards\":" << backwards
      << ",\"channels\":[";
    bool first = true;
    for (const auto& [name, s] : ch) {
      j << (first ? "" : ",") << "{\"channel\":" << json_str(name) << ",\"count\":" << s.count
        << ",\"bytes\":" << s.bytes << ",\"size_min\":" << s.min << ",\"size_mean\":"
        << fmt("%.1f", static_cast<double>(s.bytes) / static_cast<double>(s.count)) << ",\"size_max\":" << s.max
        << ",\"rate_hz\":" << fmt("%.3f", rate(s)) << "}";
      first = false;
    }
    j << "],\"damage_count\":" << damage_count << ",\"damaged_bytes\":" << damaged_bytes << ",\"damage\":[";
    for (std::size_t i = 0; i < damage.size(); ++i)
      j << (i ? "," : "") << "{\"kind\":\"" << eventlog::to_string(damage[i].kind) << "\",\"offset\":"
        << damage[i].offset << ",\"length\":" << damage[i].length << "}";
    j << "]}";
    std::cout << j.str() << std::endl;
    return 0;
  }
  std::cout << "file:       " << o.file << " (" << size << " bytes)\n"
            << "events:     " << events << "\n";
  if (events) {
    std::cout << "start:      " << format_us(min_ts) << "\n"
              << "end:        " << format_us(max_ts) << "\n";
  }
  std::cout << "duration:   " << fmt("%.3f", duration) << " s\n"
            << "channels:   " << ch.size() << "\n";
  if (backwards) std::cout << "note:       " << backwards << " events have an earlier timestamp than the one before\n";
  if (events == 0 && size > 0 && damaged_bytes == size)
    std::cout << "note:       no LCM event anywhere in it: not an LCM log (or wholly damaged)\n";
  if (!ch.empty()) {
    char line[256];
    std::snprintf(line, sizeof line, "  %-40s %10s %10s %10s %12s %10s\n", "channel", "count", "rate Hz",
                  "min B", "mean B", "max B");
    std::cout << line;
    for (const auto& [name, s] : ch) {
      std::snprintf(line, sizeof line, "  %-40s %10llu %10.2f %10zu %12.1f %10zu\n", printable(name).c_str(),
                    static_cast<unsigned long long>(s.count), rate(s), s.min,
                    static_cast<double>(s.bytes) / static_cast<double>(s.count), s.max);
      std::cout << line;
    }
  }
  if (damage_count == 0) {
    std::cout << "damage:     none\n";
  } else {
    std::cout << "damage:     " << damage_count << " damaged region(s), " << damaged_bytes << " bytes\n";
    for (const auto& d : damage)
      std::cout << "  " << eventlog::to_string(d.kind) << " at offset " << d.offset << ", " << d.length
                << " bytes" << (d.kind == eventlog::Damage::Kind::truncated ? " (the file ends inside an event)" : "")
                << "\n";
  }
  return 0;
}

}  // namespace

int run_log();

Verb add_log(CLI::App& app, const Globals&) {
  auto* c = app.add_subcommand("log", "inspect and export LCM log files (lcm-logger's or lcmx record's)");
  c->require_subcommand(1);
  g_info = c->add_subcommand("info", "duration, start/end, per channel count, sizes and rate; damage");
  g_info->add_option("file", g_log.file, "LCM log file")->required();
  g_info->add_flag("--json", g_log.json, "print as JSON");
  g_export_verb = add_log_export(*c);
  return {c, [] { return run_log(); }};
}

int run_log() {
  if (g_info->parsed()) return run_info();
  if (g_export_verb.command->parsed()) return g_export_verb.run();
  return 2;
}

}  // namespace lcmx::cli
