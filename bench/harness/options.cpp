#include "options.hpp"

#include <sched.h>

#include <cctype>
#include <cstdio>
#include <iostream>
#include <stdexcept>

namespace lcmxbench {

int bad_options(const std::string& program, const std::string& text) {
  std::cerr << program << ": " << text << "\n";
  return kExitBadOptions;
}

std::size_t parse_size(const std::string& text, std::size_t min_bytes) {
  std::size_t pos = 0;
  double v = 0;
  try {
    v = std::stod(text, &pos);
  } catch (const std::exception&) {
    throw std::invalid_argument("bad size '" + text + "'");
  }
  std::string unit = text.substr(pos);
  for (auto& c : unit) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  double mul = 1;
  if (unit == "K" || unit == "KB" || unit == "KIB") mul = 1024;
  else if (unit == "M" || unit == "MB" || unit == "MIB") mul = 1024.0 * 1024;
  else if (!unit.empty() && unit != "B") throw std::invalid_argument("bad size '" + text + "'");
  const auto bytes = static_cast<std::size_t>(v * mul);
  if (v < 0 || bytes < min_bytes || bytes > (64u << 20))
    throw std::invalid_argument("size '" + text + "' out of " + std::to_string(min_bytes) + " B..64 MB");
  return bytes;
}

CLI::Option* add_pin_option(CLI::App& app, std::string& pin, const std::vector<std::string>& choices,
                            const std::string& help) {
  return app.add_option("--pin", pin, help)->check(CLI::IsMember(choices))->capture_default_str();
}

Pinning pinning(const std::string& pin) {
  if (pin == "same") return {0, 0};
  if (pin == "split") return {0, 1};
  return {};
}

std::optional<std::string> split_unavailable() {
  cpu_set_t mine;
  if (::sched_getaffinity(0, sizeof mine, &mine) != 0 || !CPU_ISSET(0, &mine) || !CPU_ISSET(1, &mine))
    return "--pin split needs CPUs 0 and 1, and this process may not use both (taskset, cgroup, or 1 CPU)";
  return std::nullopt;
}

bool help_asked(int argc, char** argv) {
  for (int i = 1; i < argc; ++i)
    if (std::string(argv[i]) == "--help" || std::string(argv[i]) == "-h") return true;
  return false;
}

int usage(const char* text, bool asked) {
  std::fputs(text, asked ? stdout : stderr);
  return asked ? 0 : kExitBadOptions;
}

CLI::Option* add_wait_option(CLI::App& app, std::string& wait, const std::string& help) {
  return app.add_option("--wait", wait, help)
      ->check(CLI::IsMember({"block", "spin", "adaptive", "busy"}))
      ->capture_default_str();
}

lcmx::WaitStrategy wait_strategy(const std::string& name) {
  if (name == "spin") return lcmx::WaitStrategy::spin_then_block;
  if (name == "adaptive") return lcmx::WaitStrategy::adaptive;
  if (name == "busy") return lcmx::WaitStrategy::busy_poll;
  return lcmx::WaitStrategy::block;
}

}  // namespace lcmxbench
