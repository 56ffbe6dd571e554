// Helpers shared by record/play/log (apps/lcmx/*_cmd.cpp).
#pragma once

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <ctime>
#include <regex>
#include <string>
#include <vector>

#include "safe_text.hpp"

namespace lcmx::cli {

// Channel selection as lcm-logger's -c: a regular expression (ECMAScript) that must match
// the whole name, minus any of the exclude expressions. Throws std::regex_error on a bad one.
class ChannelFilter {
 public:
  ChannelFilter(const std::string& include, const std::vector<std::string>& exclude) {
    include_ = std::regex(include, std::regex::ECMAScript | std::regex::optimize);
    for (const auto& x : exclude) exclude_.emplace_back(x, std::regex::ECMAScript | std::regex::optimize);
  }
  bool operator()(const std::string& channel) const {
    if (!std::regex_match(channel, include_)) return false;
    for (const auto& x : exclude_)
      if (std::regex_match(channel, x)) return false;
    return true;
  }

 private:
  std::regex include_;
  std::vector<std::regex> exclude_;
};

// JSON string literal (safe_text.hpp json_text: also DEL, C1 controls and non-UTF-8 bytes escaped).
inline std::string json_str(const std::string& s) { return json_text(s); }

inline std::string fmt(const char* f, double v) {
  char b[64];
  std::snprintf(b, sizeof b, f, v);
  return b;
}

inline std::int64_t wall_us() {
  timespec ts{};
  clock_gettime(CLOCK_REALTIME, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000 + ts.tv_nsec / 1000;
}

// "2026-11-23 07:41:30.123456" in local time.
inline std::string format_us(std::int64_t us) {
  const std::time_t t = static_cast<std::time_t>(us / 1'000'000);
  std::tm tm{};
  localtime_r(&t, &tm);
  char b[64];
  const std::size_t n = std::strftime(b, sizeof b, "%Y-%m-%d %H:%M:%S", &tm);
  std::snprintf(b + n, sizeof b - n, ".%06lld", static_cast<long long>(((us % 1'000'000) + 1'000'000) % 1'000'000));
  return b;
}

}  // namespace lcmx::cli
