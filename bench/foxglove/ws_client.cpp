#include "ws_client.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <random>
#include <stdexcept>

namespace lcmx::fgbench {
namespace {
struct Timeout {};
}  // namespace

WsClient::WsClient(const std::string& address, int port, const std::string& subprotocol) : buf_(1 << 20) {
  fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd_ < 0) throw std::runtime_error(std::string("socket: ") + std::strerror(errno));
  sockaddr_in sa{};
  sa.sin_family = AF_INET;
  sa.sin_port = htons(static_cast<std::uint16_t>(port));
  if (::inet_pton(AF_INET, address.c_str(), &sa.sin_addr) != 1) {
    ::close(fd_);
    throw std::runtime_error("bad IPv4 address " + address);
  }
  if (::connect(fd_, reinterpret_cast<sockaddr*>(&sa), sizeof sa) != 0) {
    const std::string e = std::strerror(errno);
    ::close(fd_);
    throw std::runtime_error("connect " + address + ":" + std::to_string(port) + ": " + e);
  }
  int one = 1;
  ::setsockopt(fd_, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
  const std::string req = "GET / HTTP/1.1\r\nHost: " + address + ":" + std::to_string(port) +
                          "\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                          "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
                          "Sec-WebSocket-Protocol: " + subprotocol + "\r\n\r\n";
  if (::send(fd_, req.data(), req.size(), MSG_NOSIGNAL) != static_cast<ssize_t>(req.size()))
    throw std::runtime_error("send of the upgrade request failed");
  // The response head (the server sends nothing else before we speak, but keep what follows).
  for (;;) {
    const std::string_view have(buf_.data() + begin_, end_ - begin_);
    const auto at = have.find("\r\n\r\n");
    if (at != std::string_view::npos) {
      if (have.substr(0, 12).find(" 101") == std::string_view::npos)
        throw std::runtime_error("upgrade refused: " + std::string(have.substr(0, have.find("\r\n"))));
      begin_ += at + 4;
      break;
    }
    if (!fill(10000)) throw std::runtime_error("no upgrade response in 10 s");
  }
}

WsClient::~WsClient() {
  if (fd_ >= 0) ::close(fd_);
}

bool WsClient::fill(int timeout_ms) {
  if (begin_ == end_) begin_ = end_ = 0;
  if (end_ == buf_.size()) {  // compact
    std::memmove(buf_.data(), buf_.data() + begin_, end_ - begin_);
    end_ -= begin_;
    begin_ = 0;
  }
  pollfd p{fd_, POLLIN, 0};
  const int r = ::poll(&p, 1, timeout_ms);
  if (r == 0) return false;
  if (r < 0 && errno != EINTR) throw std::runtime_error(std::string("poll: ") + std::strerror(errno));
  const ssize_t n = ::recv(fd_, buf_.data() + end_, buf_.size() - end_, 0);
  if (n == 0) throw std::runtime_error("connection closed");
  if (n < 0) {
    if (errno == EINTR || errno == EAGAIN) return true;
    throw std::runtime_error(std::string("recv: ") + std::strerror(errno));
  }
  end_ += static_cast<std::size_t>(n);
  return true;
}

void WsClient::need(std::size_t n, int timeout_ms) {
  while (end_ - begin_ < n)
    if (!fill(timeout_ms)) throw Timeout{};
}

void WsClient::send_frame(int opcode, std::string_view payload) {
  std::string f;
  f += static_cast<char>(0x80 | opcode);
  if (payload.size() < 126) {
    f += static_cast<char>(0x80 | payload.size());
  } else if (payload.size() < 65536) {
    f += static_cast<char>(0x80 | 126);
    f += static_cast<char>(payload.size() >> 8);
    f += static_cast<char>(payload.size() & 0xff);
  } else {
    f += static_cast<char>(0x80 | 127);
    for (int i = 7; i >= 0; --i) f += static_cast<char>((payload.size() >> (8 * i)) & 0xff);
  }
  static thread_local std::mt19937 rng{std::random_device{}()};
  const std::uint32_t key = rng();
  char k[4];
  std::memcpy(k, &key, 4);
  f.append(k, 4);
  for (std::size_t i = 0; i < payload.size(); ++i) f += static_cast<char>(payload[i] ^ k[i % 4]);
  std::size_t sent = 0;
  while (sent < f.size()) {
    const ssize_t n = ::send(fd_, f.data() + sent, f.size() - sent, MSG_NOSIGNAL);
    if (n < 0) {
      if (errno == EINTR) continue;
      throw std::runtime_error(std::string("send: ") + std::strerror(errno));
    }
    sent += static_cast<std::size_t>(n);
  }
}

void WsClient::send_text(std::string_view text) { send_frame(1, text); }

std::optional<WsClient::Message> WsClient::read(std::string& head, std::size_t keep, int timeout_ms) {
  head.clear();
  Message m;
  try {
    for (;;) {
      need(2, timeout_ms);
      const auto b0 = static_cast<std::uint8_t>(buf_[begin_]), b1 = static_cast<std::uint8_t>(buf_[begin_ + 1]);
      std::size_t hl = 2;
      std::uint64_t len = b1 & 0x7f;
      if (len == 126) hl += 2;
      else if (len == 127) hl += 8;
      if (b1 & 0x80) hl += 4;  // a masked server frame: not allowed, but read past it
      const int inside = std::max(timeout_ms, 10000);  // the rest of a frame that has begun
      need(hl, inside);
      const auto* p = reinterpret_cast<const std::uint8_t*>(buf_.data() + begin_);
      if (len == 126) len = (std::uint64_t{p[2]} << 8) | p[3];
      else if (len == 127) {
        len = 0;
        for (int i = 0; i < 8; ++i) len = (len << 8) | p[2 + i];
      }
      begin_ += hl;
      const int op = b0 & 0x0f;
      const bool fin = (b0 & 0x80) != 0;
      const bool control = op >= 8;
      const bool text = op == 1 || (op == 0 && m.opcode == 1);
      std::string ctl;
      // The payload: the kept part copied, the rest consumed as it comes.
      std::uint64_t left = len;
      while (left > 0) {
        if (begin_ == end_ && !fill(inside)) throw Timeout{};
        const std::size_t n = static_cast<std::size_t>(std::min<std::uint64_t>(left, end_ - begin_));
        if (control) ctl.append(buf_.data() + begin_, n);
        else if (text) head.append(buf_.data() + begin_, n);
        else if (head.size() < keep) head.append(buf_.data() + begin_, std::min(n, keep - head.size()));
        begin_ += n;
        left -= n;
      }
      if (op == 8) return std::nullopt;  // close
      if (op == 9) {
        send_frame(10, ctl);  // pong
        continue;
      }
      if (op == 10) continue;
      if (op != 0) m.opcode = op;
      m.size += len;
      if (fin) return m;
    }
  } catch (const Timeout&) {
    return std::nullopt;
  }
}

}  // namespace lcmx::fgbench
