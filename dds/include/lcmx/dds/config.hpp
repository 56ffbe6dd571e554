// The DDS gateway's configuration file (TOML; reference and defaults in docs/dds.md, a
// commented example in dds/examples/dds_gateway.toml).
//
// load_config() validates everything at once (types, ranges, names, duplicate mappings, unknown
// keys, the .lcm type path and the typed mappings' types) with the Message Bridge's checker
// (lcmx/bridge/detail/toml_check.hpp) and throws ConfigError naming the file and the key, e.g.
// "gw.toml: map[1].history: must be an integer from 1 to 100000 (line 12)".
#pragma once

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "lcmx/bridge/config.hpp"
#include "lcmx/types/schema.hpp"

namespace lcmx::dds {

using bridge::ConfigError;  // the same error type as the bridge's config

inline constexpr std::size_t kMaxMappings = 256;
inline constexpr std::int64_t kMaxDomain = 230;  // Cyclone's default port mapping ends there

enum class Direction { to_dds, from_dds, both };
enum class Mode {
  opaque,  // one envelope type (lcmx::dds::Envelope): the LCM bytes
  typed,   // the .lcm type as IDL (lcmx idl): DDS programs see its fields
};
enum class Reliability { reliable, best_effort };
enum class Durability { volatile_, transient_local };

const char* to_string(Direction d);
const char* to_string(Mode m);

struct MappingConfig {
  std::string channel;          // LCM channel (<= 63 bytes)
  Direction direction = Direction::to_dds;
  Mode mode = Mode::opaque;
  std::string type;             // "pkg.type_t": required for typed; optional for opaque
  bool ros2 = false;            // topic "rt/<channel>", type "pkg::msg::dds_::T_"
  std::string topic;            // DDS topic name (default: channel, or rt/<channel> with ros2)
  Reliability reliability = Reliability::reliable;
  int history = 16;             // KEEP_LAST depth
  Durability durability = Durability::volatile_;
  std::string partition;        // per mapping; default: the gateway's
  const types::StructType* lcm_type = nullptr;  // resolved `type` (in Config::types), or null

  bool exports() const { return direction != Direction::from_dds; }
  bool imports() const { return direction != Direction::to_dds; }
};

struct Config {
  std::filesystem::path file;
  std::string name;                 // [A-Za-z0-9_-]{1,32}
  std::uint32_t domain = 0;         // DDS domain id, 0..230
  std::string partition;            // default partition of every mapping ("" = DDS's default)
  // Cyclone's network: when `interface` is set the gateway builds Cyclone's config from these
  // (and ignores CYCLONEDDS_URI); otherwise Cyclone's own default or CYCLONEDDS_URI applies.
  std::string interface;            // an interface name ("eth0") or IPv4 address ("127.0.0.1")
  bool allow_multicast = true;      // with `interface` only
  std::vector<std::string> peers;   // unicast discovery peers (IPv4), with `interface` only
  // With `interface` only: the socket receive buffer Cyclone asks for, in KiB (it takes what
  // net.core.rmem_max allows); 0 = Cyclone's own default (1 MiB). Large samples imported from
  // DDS overrun 1 MiB and wait for a retransmission (~50 ms for 2 MB on loopback).
  std::uint32_t receive_buffer_kb = 4096;
  std::chrono::milliseconds status_period{1000};
  // How long after the last lcmx message the gateway's executor keeps polling for the next
  // one before it sleeps (WaitStrategy::adaptive: yields between polls, stops when a yield
  // lets another thread run). Saves the wake-up per export only while messages come less
  // than `spin` apart; otherwise it costs: a CPU busy polling right after a dds_write makes
  // the scheduler wake the DDS reader on another CPU (docs/dds.md "Benchmark", unpinned: 1 KB
  // median 1.37x at 0, 1.42x at 50 us, 7 runs each). 0 (default): block at once.
  std::chrono::microseconds spin{0};
  // The scheduler slice the gateway's executor thread asks for (ExecutorOptions::slice;
  // Linux 6.12 and later): short, so that a message's datagrams all leave before the DDS
  // reader they wake preempts the gateway (docs/dds.md "Benchmark"). 0: the kernel's default.
  // Unset (no `slice_us`): default_slice() when the gateway starts.
  std::optional<std::chrono::microseconds> slice;
  std::vector<std::filesystem::path> type_paths;  // .lcm files/directories (absolute)
  std::shared_ptr<const types::TypeRegistry> types;  // loaded type_paths (never null)
  std::vector<MappingConfig> mappings;

  // Cyclone's XML config for `interface` / `allow_multicast` / `peers`; "" without interface.
  std::string cyclone_xml() const;
};

// The slice a gateway without `slice_us` asks for: 100 us when the calling thread may run on two
// CPUs or more (sched_getaffinity), else 0 (the kernel's default). The short slice is there so
// that a reader the gateway wakes runs after it on the same CPU instead of waking another; on
// a single CPU there is no other, and the short slice would only let the gateway preempt the
// publisher that woke it (docs/dds.md "Benchmark": 100 KB 1.27-1.32x with it, 1.14-1.19x
// without, everything pinned to one CPU). Never throws (0 if the affinity cannot be read).
std::chrono::microseconds default_slice() noexcept;

// Reads and validates a config file. Throws ConfigError.
Config load_config(const std::filesystem::path& file);
// Same, from text; `file` names it in messages and anchors relative paths.
Config parse_config(std::string_view text, const std::filesystem::path& file);

}  // namespace lcmx::dds
