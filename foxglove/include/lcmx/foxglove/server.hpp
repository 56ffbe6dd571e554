// lcmx::foxglove — a Foxglove WebSocket protocol v1 server over lcmx (docs/foxglove.md):
// every lcmx channel on every path is advertised with a JSON Schema from the run-time `.lcm`
// types, subscribed in lcmx only while a client subscribes to it, and sent to each client
// through a bounded queue of its own. Also: client publishing (JSON -> typed LCM), lcmx services
// as Foxglove services, and the connection graph from discovery. `lcmx foxglove` runs one.
//
//   lcmx::foxglove::ServerOptions o;
//   o.registry = std::make_shared<lcmx::types::TypeRegistry>(lcmx::types::TypeRegistry::load({"lcmtypes"}));
//   lcmx::foxglove::Server server(std::move(o));   // listening on 127.0.0.1:8765
//
// Threads: the server runs its own (an I/O thread for the sockets, a discovery thread, the
// lcmx node's executor); every member of Server is thread-safe.
// Errors: the constructor throws foxglove::Error (cannot listen, bad TLS files, a bad regular
// expression) or lcmx::Error (cannot join lcmx). Faults of one client (bad JSON, unknown ids)
// are answered with a `status` error to that client, never thrown.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "lcmx/core/options.hpp"
#include "lcmx/types/schema.hpp"

namespace lcmx::foxglove {

// The reserved channel `lcmx play` publishes its clock on (lcmx_msgs.play_clock_t,
// lcmtypes/play.lcm). While a clock is there the server offers the `time` capability and
// follows it (docs/foxglove.md "Time"); the channel itself is not advertised.
inline constexpr const char* kPlayClockChannel = "LCMX_PLAY_CLOCK";

class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(what) {}
};

struct RateLimit {
  std::string pattern;  // ECMAScript regex, whole LCM channel name; "" = every channel
  double max_hz = 0;    // at most this many messages per second forwarded (> 0)
};

struct ServerOptions {
  std::string address = "127.0.0.1";  // listen address; another one opens it to that network
  std::uint16_t port = 8765;           // 0: any free port (Server::port())
  std::string tls_cert, tls_key;       // PEM files: wss:// instead of ws://
  std::string name = "lcmx";           // serverInfo.name

  // The type path; null or empty: every channel is advertised as lcmx.unknown.
  std::shared_ptr<const types::TypeRegistry> registry;

  // LCM channels advertised: those matching any `channels` regex (all when empty) and no
  // `exclude` regex. ECMAScript, whole name (as `lcmx record -c/-x`).
  std::vector<std::string> channels, exclude;
  std::vector<RateLimit> rate_limits;  // the first whose pattern matches applies

  // clientPublish: off unless `client_publish` (any topic) or `publish_allow` (regexes of the
  // LCM channels a client may publish on) is given.
  bool client_publish = false;
  std::vector<std::string> publish_allow;
  bool services = true;  // advertise lcmx services and forward calls
  std::chrono::milliseconds service_timeout{5000};

  // Each client's queue of messages (docs/foxglove.md "Queue policy").
  std::size_t client_queue_bytes = std::size_t{64} << 20;
  std::size_t client_queue_messages = 4096;
  std::chrono::milliseconds status_period{2000};  // throttle of the "too slow" warning

  RuntimeOptions runtime = RuntimeOptions::from_env();  // how the server joins lcmx
  int executor_threads = 2;  // decode threads (one channel's messages stay in order)
  std::chrono::milliseconds discovery_period{250};  // how often the channel list is refreshed
};

struct ClientStats {
  std::string remote;              // "ip:port"
  std::size_t queued_bytes = 0;    // in its queue now (bounded by client_queue_bytes)
  std::size_t queued_messages = 0;
  std::uint64_t dropped = 0;       // from its queue since it connected
};

struct ServerStats {
  std::size_t clients = 0;
  std::size_t channels = 0;        // advertised now
  std::size_t lcm_subscriptions = 0;  // LCM channels subscribed in lcmx now (lazy)
  std::uint64_t messages_in = 0;   // received from lcmx
  std::uint64_t messages_out = 0;  // queued to clients (every client counts)
  std::uint64_t dropped = 0;       // dropped from client queues (slow clients)
  std::size_t max_client_queue_bytes = 0;  // the fullest client queue now (bounded by client_queue_bytes)
  std::vector<ClientStats> per_client;
  std::uint64_t rate_skipped = 0;  // not forwarded by a rate limit
  std::uint64_t decode_errors = 0;
  bool time = false;               // following an `lcmx play` clock (the `time` capability)
};

namespace detail {
struct ServerImpl;  // server.cpp
}

class Server {
 public:
  explicit Server(ServerOptions options);
  ~Server();  // closes every client, leaves lcmx
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  std::uint16_t port() const;
  ServerStats stats() const;

 private:
  std::shared_ptr<detail::ServerImpl> impl_;
};

}  // namespace lcmx::foxglove
