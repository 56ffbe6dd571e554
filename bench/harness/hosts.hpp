// Emulated hosts for the benchmarks between hosts (bench/harness): network namespaces joined by
// one veth link named "eth" through a Linux bridge (lcmx::test::Emulation, test/support), so
// every packet stays inside namespaces the run created, and they are removed on every exit path
// (the Emulation's destructor; a SIGKILLed run's are removed by the next one). Host 0 is "A"
// (publishers, clients), host 1 "B" (subscribers, servers). Needs root; built with the tests
// (LCMX_BUILD_TESTS), which define LCMX_BENCH_WITH_NETNS.
#pragma once

#include <CLI/CLI.hpp>

#include <optional>
#include <string>

#include "lcmx/test/netns.hpp"

namespace lcmxbench {

struct LinkOptions {
  std::string rate;                      // tc tbf rate of the link at each sender ("" = not shaped)
  std::string tcp_congestion = "cubic";  // the hosts' TCP congestion control ("" = this machine's)
};

// --link-rate (with this benchmark's default in `link.rate` and its help) and, when `tcp` is
// set, --tcp-congestion.
void add_link_options(CLI::App& app, LinkOptions& link, const std::string& rate_help, bool tcp);
// Why the link options cannot work ("--link-rate 'x': ..."), or nothing.
std::optional<std::string> bad_link_options(const LinkOptions& link);
// The link rate in bits per second; 0 when not shaped.
double link_bits_per_second(const LinkOptions& link);

// Why hosts cannot be emulated here (not root, no `ip`, ...), or nothing.
std::optional<std::string> hosts_unavailable();
// `hosts` hosts on one "eth" link. Throws lcmx::test::SetupError (the failing command).
lcmx::test::Emulation emulate_hosts(const LinkOptions& link, int hosts = 2);
// "A <ns> (<address>) -> B <ns> (<address>)" for the progress lines.
std::string hosts_line(const lcmx::test::Emulation& emu);
// The TCP congestion control a host runs (read inside its namespace).
std::string tcp_congestion_of(lcmx::test::Emulation& emu, int host);

// Writes the config of `lcmx bridge` on host `host` (0: A, 1: B) of a two-host emulation, named
// `<prefix>A` or `<prefix>B`, listening on its "eth" address, with the other host's bridge as
// its one peer on that link, control port 7700; `body` adds the rest (top-level keys, then
// [[channel]] tables; docs/bridge.md "Configuration"). Returns the file's path,
// `<dir>/<prefix><A|B>.toml`. Throws std::runtime_error when it cannot be written.
std::string write_bridge_config(const lcmx::test::Emulation& emu, int host, const std::string& dir,
                                const std::string& prefix, const std::string& body);

}  // namespace lcmxbench
