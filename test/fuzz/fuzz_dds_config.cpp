// libFuzzer target: the DDS gateway's TOML configuration (dds/src/config.cpp,
// lcmx::dds::parse_config) on hostile text. Needs no Cyclone DDS (the parser does not).
//
// Checks: parse_config either returns a Config that satisfies what docs/dds.md promises (name,
// domain, status period, spin, receive buffer and every mapping's channel, topic, history in range; at most
// kMaxMappings mappings; one mapping per topic and per channel and direction; a typed mapping
// has its type) or throws ConfigError with a message naming the file; nothing else escapes
// (another exception type, a crash, a hang, unbounded memory). Type paths are named relative
// to a folder that does not exist, so only absolute paths reach the file system (read-only).
// A failed check prints what failed and aborts, which libFuzzer reports as a crash.

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <set>
#include <string>
#include <string_view>

#include "lcmx/dds/config.hpp"

namespace {

#define FUZZ_CHECK(cond)                                                                  \
  do {                                                                                    \
    if (!(cond)) {                                                                        \
      std::fprintf(stderr, "fuzz_dds_config: check failed: %s (%s:%d)\n", #cond,         \
                   __FILE__, __LINE__);                                                   \
      std::abort();                                                                       \
    }                                                                                     \
  } while (0)

constexpr const char* kFile = "/nonexistent-lcmx-fuzz/dds_gateway.toml";

void check(const lcmx::dds::Config& c) {
  FUZZ_CHECK(!c.name.empty() && c.name.size() <= 32);
  FUZZ_CHECK(c.domain <= static_cast<std::uint32_t>(lcmx::dds::kMaxDomain));
  FUZZ_CHECK(c.status_period.count() >= 50 && c.status_period.count() <= 600000);
  FUZZ_CHECK(c.spin.count() >= 0 && c.spin.count() <= 100000);
  FUZZ_CHECK(c.types != nullptr);
  FUZZ_CHECK(c.mappings.size() <= lcmx::dds::kMaxMappings);
  FUZZ_CHECK(c.peers.empty() || !c.interface.empty());
  FUZZ_CHECK(c.receive_buffer_kb <= 1024 * 1024);
  FUZZ_CHECK(!c.interface.empty() || c.receive_buffer_kb == 4096);  // with interface only
  std::set<std::string> topics;
  std::set<std::pair<std::string, bool>> channels;  // (channel, exports)
  for (const auto& m : c.mappings) {
    FUZZ_CHECK(!m.channel.empty() && m.channel.size() <= 63);
    FUZZ_CHECK(!m.topic.empty() && m.topic.size() <= 255);
    FUZZ_CHECK(topics.insert(m.topic).second);
    if (m.exports()) FUZZ_CHECK(channels.insert({m.channel, true}).second);
    if (m.imports()) FUZZ_CHECK(channels.insert({m.channel, false}).second);
    FUZZ_CHECK(m.history >= 1 && m.history <= 100000);
    if (m.mode == lcmx::dds::Mode::typed) FUZZ_CHECK(m.lcm_type != nullptr);
    if (!m.type.empty()) FUZZ_CHECK(m.lcm_type != nullptr);
  }
  (void)c.cyclone_xml();  // what the gateway hands to Cyclone
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  try {
    check(lcmx::dds::parse_config(text, kFile));
  } catch (const lcmx::dds::ConfigError& e) {
    FUZZ_CHECK(std::string_view(e.what()).starts_with(kFile));
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz_dds_config: unexpected exception: %s\n", e.what());
    std::abort();
  }
  return 0;
}
