// The WebSocket transport of `lcmx foxglove` (Boost.Beast; websocket.cpp is the only file that
// includes Beast or Asio, which compile slowly). It knows nothing of Foxglove beyond the
// subprotocol names it offers: the server (server.cpp) sees each client as a Connection and
// gives the transport a Peer that produces outgoing frames and consumes incoming ones.
//
// Threads: one I/O thread (the Listener's) runs every socket; Peer callbacks run on it, one at
// a time per connection. Connection::wake() and close() may be called from any thread.
// Ownership: the transport owns its sessions; a session owns its Peer (shared_ptr); the server
// keeps only weak_ptrs to Connections (no cycle). Errors: the Listener's constructor throws
// std::runtime_error (bad address, port in use, unreadable certificate or key); a connection's
// faults close that connection only.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "payload.hpp"

namespace lcmx::foxglove::detail {

// One WebSocket message to send: `head` then the parts of `body` (either may be empty), in one
// gathering write.
struct OutFrame {
  bool text = true;
  std::string head;
  std::shared_ptr<const Payload> body;
};

// The server's side of one client. All calls on the I/O thread.
class Peer {
 public:
  virtual ~Peer() = default;
  // The next frame to send, or nullopt when there is nothing (then wake() when there is).
  virtual std::optional<OutFrame> next_frame() = 0;
  virtual void on_text(std::string_view message) = 0;
  virtual void on_binary(std::span<const std::uint8_t> message) = 0;
  // Called once when the connection ended (either side, or an error).
  virtual void on_close() = 0;
};

// The transport's side of one client.
class Connection {
 public:
  virtual ~Connection() = default;
  // Any thread, never blocks: the Peer has something to send.
  virtual void wake() = 0;
  // Any thread: closes the connection (a close frame with `reason`).
  virtual void close(std::string reason) = 0;
  virtual const std::string& remote() const = 0;       // "ip:port"
  virtual const std::string& subprotocol() const = 0;  // the one agreed on
};

struct ListenOptions {
  std::string address = "127.0.0.1";
  std::uint16_t port = 0;  // 0: any free port (read it back with Listener::port())
  std::string tls_cert, tls_key;  // both or neither: PEM files for wss://
  std::vector<std::string> subprotocols;  // accepted, the client's first supported one wins
  std::string server_name = "lcmx";
  std::size_t max_incoming_bytes = std::size_t{64} << 20;  // one client message
};

// Called on the I/O thread for each new client, after the handshake.
using AcceptFn = std::function<std::shared_ptr<Peer>(std::shared_ptr<Connection>)>;

class Listener {
 public:
  Listener(const ListenOptions& options, AcceptFn accept);
  ~Listener();  // closes every connection and joins the I/O thread (no Peer call after)
  Listener(const Listener&) = delete;
  Listener& operator=(const Listener&) = delete;

  std::uint16_t port() const;
  // Runs `fn` on the I/O thread (any thread may call it).
  void post(std::function<void()> fn);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace lcmx::foxglove::detail
