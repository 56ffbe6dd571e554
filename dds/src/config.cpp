#include "lcmx/dds/config.hpp"

#include <sched.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <set>
#include <sstream>

#include "lcmx/bridge/detail/toml_check.hpp"
#include "lcmx/dds/idl.hpp"

namespace lcmx::dds {
namespace {

using bridge::detail::Checker;

// DDS topic names: letters, digits, '_', '/', '-', '.', 1..255 characters (what DDS and ROS 2
// accept, a subset of what Cyclone does).
bool valid_topic(std::string_view s) {
  if (s.empty() || s.size() > 255) return false;
  for (char c : s)
    if (!((c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' || c == '/' ||
          c == '-' || c == '.'))
      return false;
  return true;
}

bool valid_channel(std::string_view s) {
  if (s.empty() || s.size() > 63) return false;
  for (unsigned char c : s)
    if (c <= 0x20 || c >= 0x7f) return false;
  return true;
}

// An interface name (Linux: up to 15 characters, no '/' or blank) or an IPv4 address.
bool valid_interface(const std::string& s) {
  if (bridge::detail::valid_ipv4(s)) return true;
  if (s.empty() || s.size() > 15) return false;
  for (unsigned char c : s)
    if (c <= 0x20 || c >= 0x7f || c == '/' || c == '<' || c == '>' || c == '"' || c == '&' || c == '\'') return false;
  return true;
}

std::string xml_escape(const std::string& s) {
  std::string o;
  for (char c : s) {
    switch (c) {
      case '&': o += "&amp;"; break;
      case '<': o += "&lt;"; break;
      case '>': o += "&gt;"; break;
      case '"': o += "&quot;"; break;
      default: o += c;
    }
  }
  return o;
}

}  // namespace

const char* to_string(Direction d) {
  switch (d) {
    case Direction::to_dds: return "to_dds";
    case Direction::from_dds: return "from_dds";
    case Direction::both: return "both";
  }
  return "?";
}

const char* to_string(Mode m) { return m == Mode::typed ? "typed" : "opaque"; }

std::chrono::microseconds default_slice() noexcept {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (::sched_getaffinity(0, sizeof set, &set) != 0) return std::chrono::microseconds(0);
  return CPU_COUNT(&set) >= 2 ? std::chrono::microseconds(100) : std::chrono::microseconds(0);
}

std::string Config::cyclone_xml() const {
  if (interface.empty()) return {};
  std::string x = "<CycloneDDS><Domain id=\"any\"><General><Interfaces><NetworkInterface ";
  x += bridge::detail::valid_ipv4(interface) ? "address" : "name";
  x += "=\"" + xml_escape(interface) + "\"/></Interfaces>";
  x += std::string("<AllowMulticast>") + (allow_multicast ? "default" : "false") + "</AllowMulticast>";
  x += "</General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
       "<MaxAutoParticipantIndex>60</MaxAutoParticipantIndex>";
  if (!peers.empty()) {
    x += "<Peers>";
    for (const auto& p : peers) x += "<Peer address=\"" + xml_escape(p) + "\"/>";
    x += "</Peers>";
  }
  x += "</Discovery>";
  if (receive_buffer_kb > 0)
    x += "<Internal><SocketReceiveBufferSize max=\"" + std::to_string(receive_buffer_kb) + "KiB\"/></Internal>";
  x += "</Domain></CycloneDDS>";
  return x;
}

Config parse_config(std::string_view text, const std::filesystem::path& file) {
  Checker c(file);
  // The pre-scan against toml++ 3.3.0's non-ASCII bug, then the parse (as the bridge's).
  const toml::table root = bridge::detail::parse_toml(text, file);
  c.only(root, "", {"name", "domain", "partition", "interface", "allow_multicast", "peers", "receive_buffer_kb",
                    "types", "status_period_ms", "spin_us", "slice_us", "ros2", "map"});
  Config cfg;
  cfg.file = file;
  cfg.name = c.string(root, "", "name", true);
  if (!bridge::detail::valid_name(cfg.name, 32))
    c.fail("name", "must be 1 to 32 characters of [A-Za-z0-9_-] (got \"" + cfg.name + "\")", root.get("name"));
  cfg.domain = static_cast<std::uint32_t>(c.integer(root, "", "domain", false, 0, 0, kMaxDomain));
  cfg.partition = c.string(root, "", "partition", false);
  if (!cfg.partition.empty() && !valid_topic(cfg.partition))
    c.fail("partition", "must be 1 to 255 characters of [A-Za-z0-9_/.-]", root.get("partition"));
  cfg.interface = c.string(root, "", "interface", false);
  if (root.get("interface") && !valid_interface(cfg.interface))
    c.fail("interface", "must be an interface name (e.g. \"eth0\") or an IPv4 address (got \"" + cfg.interface + "\")",
           root.get("interface"));
  cfg.allow_multicast = c.boolean(root, "", "allow_multicast", true);
  cfg.peers = c.strings(root, "", "peers", false);
  for (std::size_t i = 0; i < cfg.peers.size(); ++i)
    if (!bridge::detail::valid_ipv4(cfg.peers[i]))
      c.fail("peers[" + std::to_string(i) + "]", "not an IPv4 address: \"" + cfg.peers[i] + "\"", root.get("peers"));
  if (cfg.interface.empty())  // these only shape the Cyclone config built from `interface`
    for (const char* key : {"allow_multicast", "peers", "receive_buffer_kb"})
      if (root.get(key))
        c.fail(key, "needs interface (without it Cyclone's defaults or CYCLONEDDS_URI apply)", root.get(key));
  cfg.receive_buffer_kb =
      static_cast<std::uint32_t>(c.integer(root, "", "receive_buffer_kb", false, 4096, 0, 1024 * 1024));
  if (!cfg.allow_multicast && cfg.peers.empty())
    c.fail("peers", "allow_multicast = false needs at least one peer (else nothing is discovered)",
           root.get("allow_multicast"));
  cfg.status_period = std::chrono::milliseconds(c.integer(root, "", "status_period_ms", false, 1000, 50, 600000));
  cfg.spin = std::chrono::microseconds(c.integer(root, "", "spin_us", false, 0, 0, 100000));
  if (root.get("slice_us")) {
    cfg.slice = std::chrono::microseconds(c.integer(root, "", "slice_us", false, 100, 0, 100000));
    if (cfg.slice->count() > 0 && cfg.slice->count() < 100)
      c.fail("slice_us", "must be 0 (the kernel's default) or 100..100000 (the kernel's range)", root.get("slice_us"));
  }
  const bool ros2_default = c.boolean(root, "", "ros2", false);

  for (const auto& p : c.strings(root, "", "types", false)) {
    if (p.empty()) c.fail("types", "empty path", root.get("types"));
    cfg.type_paths.push_back(c.path(p));
  }
  try {
    cfg.types = std::make_shared<const types::TypeRegistry>(types::TypeRegistry::load(cfg.type_paths));
  } catch (const types::Error& e) {
    c.fail("types", e.what(), root.get("types"));
  }

  const auto maps = c.tables(root, "", "map");
  if (maps.empty()) c.fail("map", "must list at least one mapping ([[map]] with channel and direction)");
  if (maps.size() > kMaxMappings)
    c.fail("map", "at most " + std::to_string(kMaxMappings) + " mappings (got " + std::to_string(maps.size()) + ")",
           root.get("map"));
  std::set<std::pair<std::string, int>> seen_channel;  // (channel, 0 = export / 1 = import)
  std::set<std::string> seen_topic;
  for (std::size_t i = 0; i < maps.size(); ++i) {
    const auto& t = *maps[i];
    const std::string p = "map[" + std::to_string(i) + "].";
    c.only(t, p, {"channel", "direction", "mode", "type", "ros2", "topic", "reliability", "history", "durability",
                  "partition"});
    MappingConfig m;
    m.channel = c.string(t, p, "channel", true);
    if (!valid_channel(m.channel))
      c.fail(p + "channel", "must be 1 to 63 printable ASCII characters without spaces (an LCM channel)",
             t.get("channel"));
    const std::string dir = c.string(t, p, "direction", true);
    if (dir == "to_dds") m.direction = Direction::to_dds;
    else if (dir == "from_dds") m.direction = Direction::from_dds;
    else if (dir == "both") m.direction = Direction::both;
    else c.fail(p + "direction", "must be \"to_dds\", \"from_dds\" or \"both\" (got \"" + dir + "\")", t.get("direction"));
    const std::string mode = c.string(t, p, "mode", false, "opaque");
    if (mode == "opaque") m.mode = Mode::opaque;
    else if (mode == "typed") m.mode = Mode::typed;
    else c.fail(p + "mode", "must be \"opaque\" or \"typed\" (got \"" + mode + "\")", t.get("mode"));
    m.type = c.string(t, p, "type", m.mode == Mode::typed);
    if (!m.type.empty()) {
      m.lcm_type = cfg.types->find(m.type);
      if (!m.lcm_type) {
        std::string known;
        for (const auto& ty : cfg.types->types()) known += (known.empty() ? "" : ", ") + ty->full_name();
        c.fail(p + "type", "unknown type \"" + m.type + "\" (" +
                               (known.empty() ? std::string("no types loaded: set types = [\"dir/or/file.lcm\"]")
                                              : "types loaded: " + known) + ")",
               t.get("type"));
      }
      if (m.mode == Mode::typed) {
        try {
          check_typed(*m.lcm_type);
        } catch (const types::Error& e) {
          c.fail(p + "type", std::string(e.what()) + " (use mode = \"opaque\")", t.get("type"));
        }
      }
    }
    m.ros2 = c.boolean(t, p, "ros2", ros2_default);
    m.topic = c.string(t, p, "topic", false, m.ros2 ? "rt/" + m.channel : m.channel);
    if (!valid_topic(m.topic))
      c.fail(p + "topic", "must be 1 to 255 characters of [A-Za-z0-9_/.-] (a DDS topic name; got \"" + m.topic + "\")",
             t.get("topic") ? t.get("topic") : t.get("channel"));
    if (!seen_topic.insert(m.topic).second)
      c.fail(p + "topic", "topic \"" + m.topic + "\" is already mapped (one mapping per topic; use direction = \"both\")",
             t.get("topic") ? t.get("topic") : t.get("channel"));
    if (m.exports() && !seen_channel.insert({m.channel, 0}).second)
      c.fail(p + "channel", "channel \"" + m.channel + "\" is already exported to DDS by another mapping", t.get("channel"));
    if (m.imports() && !seen_channel.insert({m.channel, 1}).second)
      c.fail(p + "channel", "channel \"" + m.channel + "\" is already imported from DDS by another mapping", t.get("channel"));
    const std::string rel = c.string(t, p, "reliability", false, "reliable");
    if (rel == "reliable") m.reliability = Reliability::reliable;
    else if (rel == "best_effort") m.reliability = Reliability::best_effort;
    else c.fail(p + "reliability", "must be \"reliable\" or \"best_effort\" (got \"" + rel + "\")", t.get("reliability"));
    m.history = static_cast<int>(c.integer(t, p, "history", false, 16, 1, 100000));
    const std::string dur = c.string(t, p, "durability", false, "volatile");
    if (dur == "volatile") m.durability = Durability::volatile_;
    else if (dur == "transient_local") m.durability = Durability::transient_local;
    else c.fail(p + "durability", "must be \"volatile\" or \"transient_local\" (got \"" + dur + "\")", t.get("durability"));
    m.partition = c.string(t, p, "partition", false, cfg.partition);
    if (!m.partition.empty() && !valid_topic(m.partition))
      c.fail(p + "partition", "must be 1 to 255 characters of [A-Za-z0-9_/.-]", t.get("partition"));
    cfg.mappings.push_back(std::move(m));
  }
  return cfg;
}

Config load_config(const std::filesystem::path& file) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(file, ec))
    throw ConfigError(file.string() + ": cannot read: " + (std::filesystem::exists(file, ec) ? "not a regular file"
                                                                                            : "no such file"));
  std::ifstream in(file, std::ios::binary);
  if (!in) throw ConfigError(file.string() + ": cannot read: " + std::strerror(errno));
  std::ostringstream ss;
  ss << in.rdbuf();
  return parse_config(ss.str(), file);
}

}  // namespace lcmx::dds
