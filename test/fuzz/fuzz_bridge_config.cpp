// libFuzzer target: the Message Bridge's TOML configuration (bridge/src/config.cpp,
// lcmx::bridge::parse_config) on hostile text.
//
// Checks: parse_config either returns a Config that satisfies what docs/bridge.md promises
// (names, ports, timeouts and sizes in range, unique names and ports, at least one channel) or
// throws ConfigError with a message naming the file; nothing else escapes (another exception
// type, a crash, a hang, unbounded memory). Key files are named relative to a folder that does
// not exist, so only absolute paths reach the file system (read-only).
// A failed check prints what failed and aborts, which libFuzzer reports as a crash.

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <set>
#include <string>
#include <string_view>

#include "lcmx/bridge/config.hpp"

namespace {

#define FUZZ_CHECK(cond)                                                                  \
  do {                                                                                    \
    if (!(cond)) {                                                                        \
      std::fprintf(stderr, "fuzz_bridge_config: check failed: %s (%s:%d)\n", #cond,      \
                   __FILE__, __LINE__);                                                   \
      std::abort();                                                                       \
    }                                                                                     \
  } while (0)

constexpr const char* kFile = "/nonexistent-lcmx-fuzz/bridge.toml";

void check(const lcmx::bridge::Config& c) {
  FUZZ_CHECK(!c.name.empty() && c.name.size() <= 32);
  FUZZ_CHECK(!c.listen.empty());
  FUZZ_CHECK(c.control_port >= 1);
  FUZZ_CHECK(c.heartbeat.count() >= 10 && c.heartbeat.count() <= 60000);
  FUZZ_CHECK(c.link_timeout >= 2 * c.heartbeat);
  FUZZ_CHECK(c.failback_hold.count() >= 0);
  FUZZ_CHECK(c.status_period.count() >= 50);
  FUZZ_CHECK(!c.channels.empty());
  std::set<int> ports{c.control_port};
  std::set<std::string> names;
  for (const auto& ch : c.channels) {
    FUZZ_CHECK(ch.port >= 1);
    FUZZ_CHECK(ports.insert(ch.port).second);
    FUZZ_CHECK(names.insert(ch.name).second);
    FUZZ_CHECK(ch.priority >= 0 && ch.priority <= 7);
    FUZZ_CHECK(ch.hwm >= 1 && ch.hwm <= 1000000);
    FUZZ_CHECK(!ch.topics.empty());
  }
  std::set<std::string> peers;
  for (const auto& p : c.peers) {
    FUZZ_CHECK(p.name != c.name);
    FUZZ_CHECK(peers.insert(p.name).second);
    FUZZ_CHECK(!p.endpoints.empty());
    FUZZ_CHECK(p.public_key.empty() || p.public_key.size() == 40);
  }
  // The lookups the bridge makes on every topic.
  (void)c.channel_of("CAMERA");
  (void)c.carried("MAP_1");
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  try {
    check(lcmx::bridge::parse_config(text, kFile));
  } catch (const lcmx::bridge::ConfigError& e) {
    FUZZ_CHECK(std::string_view(e.what()).starts_with(kFile));
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz_bridge_config: unexpected exception: %s\n", e.what());
    std::abort();
  }
  return 0;
}
