// Command-line conventions every benchmark shares (bench/harness; bench/README.md "The harness"):
//  - CLI11, `--help` on every program (and on the helpers driven by scripts);
//  - sizes as "1K", "6M", "1500" (K = 1024, M = 1024*1024);
//  - `--pin none|same|split`, `--wait block|spin|adaptive|busy`, `--markdown FILE`, `--csv FILE`
//    with the same meaning everywhere;
//  - a bad option is one line on stderr, "<program>: <what is wrong>", and exit status 2; a run
//    that could not measure something exits 1; an interrupted one 128 + the signal.
// The children's options (--role and what it needs) are hidden from --help.
#pragma once

#include <CLI/CLI.hpp>

#include <cstddef>
#include <optional>
#include <string>
#include <vector>

#include "lcmx/core.hpp"

namespace lcmxbench {

inline constexpr int kExitBadOptions = 2;

// "<program>: <text>" on stderr; returns kExitBadOptions.
int bad_options(const std::string& program, const std::string& text);

// "100K", "6M", "1500", "2MiB" (K = 1024, M = 1024*1024, optional B) -> bytes in
// [min_bytes, 64 MB]. Throws std::invalid_argument naming the text.
std::size_t parse_size(const std::string& text, std::size_t min_bytes);

// An option hidden from --help (the children's).
template <class T>
CLI::Option* add_hidden(CLI::App& app, const std::string& name, T& value) {
  return app.add_option(name, value)->group("");
}

// --pin: where the two sides of a pair run. `choices` is what this benchmark offers, among
// none (the scheduler decides), same (both on CPU 0) and split (publisher or host A on CPU 0,
// subscriber or host B on CPU 1).
CLI::Option* add_pin_option(CLI::App& app, std::string& pin, const std::vector<std::string>& choices,
                            const std::string& help);
struct Pinning {
  int pub = -1, sub = -1;  // CPU of the publisher's side (host A) and the subscriber's (host B); -1: any
};
Pinning pinning(const std::string& pin);
// Why --pin split cannot work here (this process may not use CPUs 0 and 1), or nothing.
std::optional<std::string> split_unavailable();

// The helpers that scripts drive with positional arguments (lcmx_bench_log, _monitor, _dds):
// `--help` or `-h` anywhere asks for the usage.
bool help_asked(int argc, char** argv);
// Prints `usage` on stdout and returns 0 when it was asked for, else on stderr and returns
// kExitBadOptions (a bad call).
int usage(const char* usage, bool asked);

// --wait: an lcmx subscriber node's ExecutorOptions::wait.
CLI::Option* add_wait_option(CLI::App& app, std::string& wait, const std::string& help);
// "block" | "spin" (spin_then_block) | "adaptive" | "busy" (busy_poll); anything else: block.
lcmx::WaitStrategy wait_strategy(const std::string& name);

}  // namespace lcmxbench
