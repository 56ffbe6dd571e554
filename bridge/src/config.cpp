#include "lcmx/bridge/config.hpp"

#include <arpa/inet.h>
#include <fnmatch.h>
#include <zmq.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <toml++/toml.h>
#include <variant>

#include "lcmx/bridge/detail/toml_check.hpp"
#include "lcmx/bridge/detail/wire.hpp"
#include "lcmx/udpm/detail/key_file.hpp"

namespace lcmx::bridge {
namespace {

constexpr std::int64_t kMaxMs = 600000;

bool valid_z85_key(const std::string& k) {
  if (k.size() != 40) return false;
  std::uint8_t raw[32];
  return ::zmq_z85_decode(raw, k.c_str()) != nullptr;
}

using detail::Checker;
using detail::valid_ipv4;
using detail::valid_name;

// A CURVE key file named by config key `key_name`; its errors name that key.
std::string key_of(const Checker& c, const std::string& key_name, const std::filesystem::path& p,
                   KeyFile kind = KeyFile::public_key) {
  try {
    return read_key_file(p, kind);
  } catch (const ConfigError& e) {
    c.fail(key_name, e.what());
  }
}

bool glob_match(const std::vector<std::string>& globs, std::string_view topic) {
  const std::string t(topic);
  for (const auto& g : globs)
    if (::fnmatch(g.c_str(), t.c_str(), 0) == 0) return true;
  return false;
}

}  // namespace

std::optional<std::size_t> Config::channel_of(std::string_view topic) const {
  for (std::size_t i = 0; i < channels.size(); ++i)
    if (glob_match(channels[i].topics, topic)) return i;
  return std::nullopt;
}

bool Config::carried(std::string_view topic) const { return glob_match(carry, topic); }

Config parse_config(std::string_view text, const std::filesystem::path& file) {
  Checker c(file);
  // The pre-scan against toml++ 3.3.0's non-ASCII bug, then the parse (detail/toml_check.hpp).
  const toml::table root = detail::parse_toml(text, file);
  c.only(root, "", {"name", "listen", "control_port", "carry", "heartbeat_ms", "link_timeout_ms",
                    "failback_hold_ms", "status_period_ms", "max_catalogue", "channel", "peer", "security"});
  Config cfg;
  cfg.file = file;
  cfg.name = c.string(root, "", "name", true);
  if (!valid_name(cfg.name, 32))
    c.fail("name", "must be 1 to 32 characters of [A-Za-z0-9_-] (got \"" + cfg.name + "\")", root.get("name"));

  cfg.listen = c.strings(root, "", "listen", true);
  if (cfg.listen.empty()) c.fail("listen", "must list at least one IPv4 address", root.get("listen"));
  {
    std::set<std::string> seen;
    for (std::size_t i = 0; i < cfg.listen.size(); ++i) {
      const std::string k = "listen[" + std::to_string(i) + "]";
      if (!valid_ipv4(cfg.listen[i])) c.fail(k, "not an IPv4 address: \"" + cfg.listen[i] + "\"", root.get("listen"));
      if (!seen.insert(cfg.listen[i]).second) c.fail(k, "duplicate address " + cfg.listen[i], root.get("listen"));
    }
  }
  cfg.control_port = static_cast<std::uint16_t>(c.integer(root, "", "control_port", true, 0, 1, 65535));
  cfg.carry = c.strings(root, "", "carry", false);
  for (std::size_t i = 0; i < cfg.carry.size(); ++i)
    if (cfg.carry[i].empty()) c.fail("carry[" + std::to_string(i) + "]", "empty pattern", root.get("carry"));
  cfg.heartbeat = std::chrono::milliseconds(c.integer(root, "", "heartbeat_ms", false, 100, 10, 60000));
  cfg.link_timeout = std::chrono::milliseconds(c.integer(root, "", "link_timeout_ms", false, 500, 20, kMaxMs));
  if (cfg.link_timeout < 2 * cfg.heartbeat)
    c.fail("link_timeout_ms", "must be at least twice heartbeat_ms (" + std::to_string(2 * cfg.heartbeat.count()) +
                                  "), or one lost heartbeat takes the link down",
           root.get("link_timeout_ms") ? root.get("link_timeout_ms") : root.get("heartbeat_ms"));
  cfg.failback_hold = std::chrono::milliseconds(c.integer(root, "", "failback_hold_ms", false, 1000, 0, kMaxMs));
  cfg.status_period = std::chrono::milliseconds(c.integer(root, "", "status_period_ms", false, 1000, 50, kMaxMs));
  cfg.max_catalogue = static_cast<std::size_t>(c.integer(root, "", "max_catalogue", false,
                                                         static_cast<std::int64_t>(kDefaultMaxCatalogue), 0,
                                                         static_cast<std::int64_t>(wire::kMaxCatalogue)));

  // Channels.
  const auto chans = c.tables(root, "", "channel");
  std::set<std::string> chan_names;
  std::set<std::int64_t> ports{cfg.control_port};
  for (std::size_t i = 0; i < chans.size(); ++i) {
    const auto& t = *chans[i];
    const std::string p = "channel[" + std::to_string(i) + "].";
    c.only(t, p, {"name", "port", "priority", "hwm", "drop", "topics", "max_keep"});
    ChannelConfig ch;
    ch.name = c.string(t, p, "name", true);
    if (!valid_name(ch.name, 32)) c.fail(p + "name", "must be 1 to 32 characters of [A-Za-z0-9_-]", t.get("name"));
    if (!chan_names.insert(ch.name).second) c.fail(p + "name", "duplicate channel name \"" + ch.name + "\"", t.get("name"));
    ch.port = static_cast<std::uint16_t>(c.integer(t, p, "port", true, 0, 1, 65535));
    if (!ports.insert(ch.port).second)
      c.fail(p + "port", "port " + std::to_string(ch.port) + " is already used (control_port or another channel)",
             t.get("port"));
    ch.priority = static_cast<int>(c.integer(t, p, "priority", false, 0, 0, 7));
    ch.hwm = static_cast<std::size_t>(c.integer(t, p, "hwm", false, 16, 1, 1000000));
    ch.max_keep = static_cast<std::uint32_t>(
        c.integer(t, p, "max_keep", false, kDefaultMaxKeep, 0, wire::Control::kMaxKeep));
    const std::string drop = c.string(t, p, "drop", false, "oldest");
    if (drop == "oldest") ch.drop = DropPolicy::oldest;
    else if (drop == "newest") ch.drop = DropPolicy::newest;
    else c.fail(p + "drop", "must be \"oldest\" or \"newest\" (got \"" + drop + "\")", t.get("drop"));
    ch.topics = c.strings(t, p, "topics", false, {"*"});
    if (ch.topics.empty()) c.fail(p + "topics", "must list at least one pattern", t.get("topics"));
    for (std::size_t k = 0; k < ch.topics.size(); ++k)
      if (ch.topics[k].empty()) c.fail(p + "topics[" + std::to_string(k) + "]", "empty pattern", t.get("topics"));
    cfg.channels.push_back(std::move(ch));
  }
  if (chans.size() > kMaxChannels)
    c.fail("channel", "at most " + std::to_string(kMaxChannels) + " channels (got " + std::to_string(chans.size()) + ")",
           root.get("channel"));
  if (cfg.channels.empty()) {
    if (cfg.control_port == 65535) c.fail("control_port", "no room for the default channel on control_port+1");
    ChannelConfig ch;
    ch.name = "default";
    ch.port = static_cast<std::uint16_t>(cfg.control_port + 1);
    cfg.channels.push_back(std::move(ch));
  }

  // Security first: peers' key files are required only with CURVE.
  if (const toml::node* n = root.get("security")) {
    const toml::table* t = n->as_table();
    if (!t) c.fail("security", "must be a table ([security])", n);
    c.only(*t, "security.", {"curve", "secret_key_file", "public_key_file"});
    cfg.security.curve = c.boolean(*t, "security.", "curve", false);
    const auto sk = c.string(*t, "security.", "secret_key_file", cfg.security.curve);
    const auto pk = c.string(*t, "security.", "public_key_file", cfg.security.curve);
    if (cfg.security.curve) {
      if (!curve_available()) c.fail("security.curve", "this libzmq was built without CURVE support", t->get("curve"));
      cfg.security.secret_key_file = c.path(sk);
      cfg.security.public_key_file = c.path(pk);
      cfg.security.secret_key = key_of(c, "security.secret_key_file", cfg.security.secret_key_file, KeyFile::secret);
      cfg.security.public_key = key_of(c, "security.public_key_file", cfg.security.public_key_file);
      char derived[41] = {};
      if (::zmq_curve_public(derived, cfg.security.secret_key.c_str()) != 0 || cfg.security.public_key != derived)
        c.fail("security.public_key_file", "does not hold the public key of security.secret_key_file");
    }
  }

  const auto peers = c.tables(root, "", "peer");
  if (peers.size() > kMaxPeers)
    c.fail("peer", "at most " + std::to_string(kMaxPeers) + " peers (got " + std::to_string(peers.size()) + ")",
           root.get("peer"));
  std::set<std::string> peer_names;
  // Every address names one host: without CURVE a peer is told apart from the others (and from
  // any other machine) by the address its connections come from (docs/bridge.md "Trust"), so
  // two peers (or a peer and this bridge) may not share one.
  std::map<std::string, std::string> owner_of;  // address -> "peer NAME" or "listen"
  for (const auto& a : cfg.listen) owner_of.emplace(a, "this bridge's listen");
  for (std::size_t i = 0; i < peers.size(); ++i) {
    const auto& t = *peers[i];
    const std::string p = "peer[" + std::to_string(i) + "].";
    c.only(t, p, {"name", "endpoints", "public_key_file"});
    PeerConfig peer;
    peer.name = c.string(t, p, "name", true);
    if (!valid_name(peer.name, 32)) c.fail(p + "name", "must be 1 to 32 characters of [A-Za-z0-9_-]", t.get("name"));
    if (peer.name == cfg.name) c.fail(p + "name", "is this bridge's own name", t.get("name"));
    if (!peer_names.insert(peer.name).second) c.fail(p + "name", "duplicate peer \"" + peer.name + "\"", t.get("name"));
    const auto eps = c.tables(t, p, "endpoints");
    if (eps.empty()) c.fail(p + "endpoints", "must list at least one { link = ..., address = ... }", t.get("endpoints"));
    if (eps.size() > kMaxEndpoints)
      c.fail(p + "endpoints", "at most " + std::to_string(kMaxEndpoints) + " endpoints (got " + std::to_string(eps.size()) + ")",
             t.get("endpoints"));
    std::set<std::string> links;
    for (std::size_t k = 0; k < eps.size(); ++k) {
      const std::string q = p + "endpoints[" + std::to_string(k) + "].";
      c.only(*eps[k], q, {"link", "address"});
      EndpointConfig e;
      e.link = c.string(*eps[k], q, "link", true);
      if (!valid_name(e.link, 16)) c.fail(q + "link", "must be 1 to 16 characters of [A-Za-z0-9_-]", eps[k]->get("link"));
      if (!links.insert(e.link).second) c.fail(q + "link", "duplicate link \"" + e.link + "\"", eps[k]->get("link"));
      e.address = c.string(*eps[k], q, "address", true);
      if (!valid_ipv4(e.address))
        c.fail(q + "address", "not an IPv4 address: \"" + e.address + "\"", eps[k]->get("address"));
      if (auto [it, fresh] = owner_of.emplace(e.address, "peer " + peer.name); !fresh)
        c.fail(q + "address", "duplicate address " + e.address + " (already " + it->second +
                                  "): each address must name one host",
               eps[k]->get("address"));
      peer.endpoints.push_back(std::move(e));
    }
    const auto pk = c.string(t, p, "public_key_file", cfg.security.curve);
    if (cfg.security.curve) {
      peer.public_key_file = c.path(pk);
      peer.public_key = key_of(c, p + "public_key_file", peer.public_key_file);
    }
    cfg.peers.push_back(std::move(peer));
  }
  return cfg;
}

Config load_config(const std::filesystem::path& file) {
  std::error_code ec;
  if (std::filesystem::is_directory(file, ec))
    throw ConfigError(file.string() + ": is a directory, not a config file (TOML)");
  std::ifstream in(file, std::ios::binary);
  if (!in) throw ConfigError(file.string() + ": cannot read: " + std::strerror(errno));
  std::ostringstream ss;
  ss << in.rdbuf();
  return parse_config(ss.str(), file);
}

bool curve_available() { return ::zmq_has("curve") == 1; }

KeyPair generate_key_pair() {
  if (!curve_available()) throw ConfigError("this libzmq was built without CURVE support");
  char pub[41] = {}, sec[41] = {};
  if (::zmq_curve_keypair(pub, sec) != 0)
    throw ConfigError(std::string("zmq_curve_keypair failed: ") + ::zmq_strerror(::zmq_errno()));
  return {pub, sec};
}

void write_key_pair(const std::filesystem::path& prefix, const KeyPair& keys, bool overwrite) {
  // Written to a new file (O_EXCL) beside the target and renamed over it: a rename replaces the
  // directory entry, never what a symbolic link there points to. A target that exists is
  // refused unless `overwrite`, and refused even then when it is not a regular file (a link
  // planted at chipA.key would otherwise be followed, or silently replaced).
  const std::filesystem::path secret(prefix.string() + ".key"), pub(prefix.string() + ".pub");
  // Both targets are checked before either is written.
  for (const auto& p : {secret, pub})
    if (const auto problem = udpm::detail::check_key_file_target(p.string(), overwrite))
      throw ConfigError(p.string() + ": " + problem->why);
  auto write = [&](const std::filesystem::path& p, const std::string& key, mode_t mode, const char* what) {
    const std::string text = "# lcmx bridge CURVE " + std::string(what) + " key (Z85)\n" + key + "\n";
    if (const auto problem = udpm::detail::write_key_file_bytes(p.string(), text, mode, overwrite))
      throw ConfigError(p.string() + ": " + problem->why);
  };
  write(secret, keys.secret_key, 0600, "secret");
  write(pub, keys.public_key, 0644, "public");
}

std::string read_key_file(const std::filesystem::path& file, KeyFile kind) {
  // Owner and mode: a secret key anyone else can read is no secret; a public key anyone else
  // can write is a key they chose.
  const bool secret = kind == KeyFile::secret;
  auto read = udpm::detail::read_key_file_bytes(
      file.string(), secret ? udpm::detail::KeyFileAccess::owner_only : udpm::detail::KeyFileAccess::public_key,
      {secret ? "a secret key" : "a public key", "`lcmx bridge keygen`"}, kMaxKeyFileBytes);
  if (const auto* p = std::get_if<udpm::detail::KeyFileProblem>(&read)) throw ConfigError(file.string() + ": " + p->why);
  const std::string& text = std::get<std::string>(read);
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line)) {
    while (!line.empty() && (line.back() == '\r' || line.back() == ' ' || line.back() == '\t')) line.pop_back();
    const auto b = line.find_first_not_of(" \t");
    if (b == std::string::npos || line[b] == '#') continue;
    line.erase(0, b);
    if (!valid_z85_key(line))
      throw ConfigError(file.string() + ": not a CURVE key (expected 40 Z85 characters, as `lcmx bridge keygen` writes)");
    return line;
  }
  throw ConfigError(file.string() + ": no key in the file");
}

}  // namespace lcmx::bridge
