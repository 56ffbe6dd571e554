// A minimal blocking WebSocket client (RFC 6455) for the Foxglove benchmark: just enough to
// connect with a subprotocol, send text messages and read messages, keeping only the first bytes
// of each (a Foxglove data frame's header is its first 13), so the clients of the benchmark cost
// the machine little and the server is what is measured. Not for production: no TLS, no
// extensions, IPv4 literal addresses only.
// Not thread-safe: one thread per client. Errors throw std::runtime_error.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace lcmx::fgbench {

class WsClient {
 public:
  // Connects to address:port and completes the upgrade offering `subprotocol`.
  WsClient(const std::string& address, int port, const std::string& subprotocol);
  ~WsClient();
  WsClient(const WsClient&) = delete;
  WsClient& operator=(const WsClient&) = delete;

  void send_text(std::string_view text);

  struct Message {
    int opcode = 0;         // 1 text, 2 binary
    std::size_t size = 0;   // the whole payload
  };
  // The next message (continuations joined; pings answered): the whole of a text message, the
  // first `keep` bytes of a binary one, in `head`. nullopt on close, or when `timeout_ms` passes
  // before a message begins (a begun one is read to its end, waiting up to 10 s).
  std::optional<Message> read(std::string& head, std::size_t keep, int timeout_ms);

 private:
  bool fill(int timeout_ms);  // more bytes into buf_; false on timeout
  void need(std::size_t n, int timeout_ms);
  void send_frame(int opcode, std::string_view payload);

  int fd_ = -1;
  std::vector<char> buf_;
  std::size_t begin_ = 0, end_ = 0;
};

}  // namespace lcmx::fgbench
