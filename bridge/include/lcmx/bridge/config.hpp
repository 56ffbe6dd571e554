// The Message Bridge's configuration file (TOML; format and defaults in docs/bridge.md, a
// commented example in bridge/examples/bridge.toml).
//
// load_config() validates everything at once (types, ranges, names, duplicate names and
// ports, unknown keys, key files) and throws ConfigError naming the file and the bad key,
// e.g. "bridge.toml: channel[1].hwm: must be an integer from 1 to 1000000 (line 23)".
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace lcmx::bridge {

// Limits load_config() enforces (docs/bridge.md "Configuration"). Channels: each has its own
// thread and ZeroMQ I/O thread, picked by a 64-bit affinity mask (the control sockets use bit
// `channels`). Peers: a message is queued for every wanting peer in one pass.
inline constexpr std::size_t kMaxChannels = 32;
inline constexpr std::size_t kMaxPeers = 64;
inline constexpr std::size_t kMaxEndpoints = 8;       // links per peer
inline constexpr std::size_t kMaxKeyFileBytes = 4096;  // a key file is one 40-character line
// What a peer may ask of this host, at most (docs/bridge.md "Trust"): the keep last N of a
// republisher (ChannelConfig::max_keep) and the topics of a peer's catalogue announced here
// (Config::max_catalogue). The wire format's own limits: wire::Control::kMaxKeep, wire::kMaxCatalogue.
inline constexpr std::uint32_t kDefaultMaxKeep = 16;
inline constexpr std::size_t kDefaultMaxCatalogue = 256;

class ConfigError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// What a full (peer, channel) queue does with a new message.
enum class DropPolicy {
  oldest,  // drop the oldest queued message (keep the newest: state, images)
  newest,  // drop the new message (keep what is queued: streams that must not skip back)
};

struct ChannelConfig {
  std::string name;
  std::uint16_t port = 0;
  int priority = 0;          // 0..7, higher = more urgent (thread niceness, IP TOS)
  std::size_t hwm = 16;      // messages queued per peer before dropping
  DropPolicy drop = DropPolicy::oldest;
  std::vector<std::string> topics{"*"};  // fnmatch globs; first matching channel wins
  // The largest keep last N this host's republisher of a topic on this channel takes from a
  // peer (its `keep`), 0..1000: a ring of max_keep + 1 slots of the topic's size at most.
  std::uint32_t max_keep = kDefaultMaxKeep;
};

struct EndpointConfig {
  std::string link;     // e.g. "pcie", "eth"
  std::string address;  // the peer's IPv4 address on that link
};

struct PeerConfig {
  std::string name;
  std::vector<EndpointConfig> endpoints;  // preference order
  std::filesystem::path public_key_file;  // absolute (resolved against the config's folder)
  std::string public_key;                 // Z85, 40 chars; empty unless security.curve
};

struct SecurityConfig {
  bool curve = false;
  std::filesystem::path secret_key_file, public_key_file;
  std::string secret_key, public_key;  // Z85, 40 chars each; empty unless curve
};

struct Config {
  std::filesystem::path file;  // where it was read from ("" for parse_config of a string)
  std::string name;
  std::vector<std::string> listen;  // IPv4 addresses
  std::uint16_t control_port = 0;
  std::vector<std::string> carry;   // globs
  std::chrono::milliseconds heartbeat{100};
  std::chrono::milliseconds link_timeout{500};
  std::chrono::milliseconds failback_hold{1000};
  std::chrono::milliseconds status_period{1000};
  // How many topics of each peer's catalogue this bridge announces on its host to pattern
  // subscribers (an idle republisher each), 0..1024; the rest is left out (logged once).
  std::size_t max_catalogue = kDefaultMaxCatalogue;
  std::vector<ChannelConfig> channels;  // never empty after loading
  std::vector<PeerConfig> peers;
  SecurityConfig security;

  // Index of the first channel whose globs match `topic`; nullopt if none does.
  std::optional<std::size_t> channel_of(std::string_view topic) const;
  // Whether `topic` matches one of the carry globs.
  bool carried(std::string_view topic) const;
};

// Reads and validates a config file. Relative key-file paths are relative to the file's folder.
// Throws ConfigError.
Config load_config(const std::filesystem::path& file);
// Same, from text; `file` names it in messages and anchors relative paths.
Config parse_config(std::string_view text, const std::filesystem::path& file);

// A CURVE key pair in Z85 text (40 characters each). Throws ConfigError if libzmq lacks CURVE.
struct KeyPair {
  std::string public_key, secret_key;
};
KeyPair generate_key_pair();
// Writes PREFIX.key (secret, mode 0600) and PREFIX.pub. Refuses to overwrite existing files
// unless `overwrite`, and refuses a path that is a symbolic link (or anything but a regular
// file) even then: each file is written to a new temporary file in the same folder and renamed
// over the old one, so nothing is ever written through a link. Throws ConfigError naming the file.
void write_key_pair(const std::filesystem::path& prefix, const KeyPair& keys, bool overwrite = false);
// Which key a key file holds: a secret key must be owned by this process's user and readable
// by nobody else (no group or other permission bits, like ssh's private keys); a public key
// must be owned by this user or root and writable by nobody else (whoever can write it can
// make this bridge trust another key).
enum class KeyFile { secret, public_key };
// Reads a key file: the first line that is neither empty nor a '#' comment, which must be a
// 40-character Z85 key. The file must be a regular file of at most kMaxKeyFileBytes, with the
// owner and mode `kind` asks for (checked on the opened file). Throws ConfigError naming the
// file (and what to run: chmod 600 / chown).
std::string read_key_file(const std::filesystem::path& file, KeyFile kind = KeyFile::public_key);
// Whether this libzmq supports CURVE.
bool curve_available();

}  // namespace lcmx::bridge
