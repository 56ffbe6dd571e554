// The only translation unit with Boost.Beast / Asio / OpenSSL (see websocket.hpp).
#include "websocket.hpp"

#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/ssl.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/ssl.hpp>
#include <boost/beast/websocket.hpp>
#include <boost/beast/websocket/ssl.hpp>

#include <netinet/in.h>
#include <netinet/tcp.h>
#include <sys/socket.h>

#include <array>
#include <atomic>
#include <future>
#include <mutex>
#include <sstream>
#include <stdexcept>
#include <thread>

namespace lcmx::foxglove::detail {
namespace {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
using tcp = asio::ip::tcp;

// The first subprotocol the client offers that we accept, "" if none.
std::string choose_subprotocol(std::string_view offered, const std::vector<std::string>& ours) {
  std::size_t at = 0;
  while (at <= offered.size()) {
    auto comma = offered.find(',', at);
    if (comma == std::string_view::npos) comma = offered.size();
    auto item = offered.substr(at, comma - at);
    while (!item.empty() && (item.front() == ' ' || item.front() == '\t')) item.remove_prefix(1);
    while (!item.empty() && (item.back() == ' ' || item.back() == '\t')) item.remove_suffix(1);
    for (const auto& s : ours)
      if (item == s) return s;
    at = comma + 1;
  }
  return {};
}

class SessionBase {
 public:
  virtual ~SessionBase() = default;
  virtual void shutdown() = 0;  // I/O thread
};

// One client. Stream: websocket::stream<beast::tcp_stream> or its TLS form.
template <class WsStream>
class Session final : public SessionBase, public Connection, public std::enable_shared_from_this<Session<WsStream>> {
 public:
  template <class... Args>
  Session(asio::io_context& ioc, const ListenOptions& o, const AcceptFn& accept, std::string remote, Args&&... args)
      : ioc_(ioc), opts_(o), accept_(accept), remote_(std::move(remote)), ws_(std::forward<Args>(args)...) {}

  void start() {
    if constexpr (kTls) {
      beast::get_lowest_layer(ws_).expires_after(std::chrono::seconds(30));
      ws_.next_layer().async_handshake(asio::ssl::stream_base::server,
                                       [self = this->shared_from_this()](beast::error_code ec) {
                                         if (ec) return;  // a failed TLS handshake ends the connection
                                         self->read_request();
                                       });
    } else {
      read_request();
    }
  }

  // Connection
  void wake() override {
    if (wake_pending_.exchange(true)) return;
    asio::post(ioc_, [w = this->weak_from_this()] {
      if (auto self = w.lock()) {
        self->wake_pending_ = false;
        self->write_next();
      }
    });
  }
  void close(std::string reason) override {
    asio::post(ioc_, [w = this->weak_from_this(), reason = std::move(reason)] {
      auto self = w.lock();
      if (!self || !self->open_ || self->closing_) return;
      self->closing_ = true;
      self->ws_.async_close(websocket::close_reason(websocket::close_code::policy_error, reason),
                            [self](beast::error_code) { self->ended(); });
    });
  }
  const std::string& remote() const override { return remote_; }
  const std::string& subprotocol() const override { return subprotocol_; }

  void shutdown() override {
    beast::error_code ec;
    beast::get_lowest_layer(ws_).socket().shutdown(tcp::socket::shutdown_both, ec);
    beast::get_lowest_layer(ws_).socket().close(ec);
  }

 private:
  static constexpr bool kTls = !std::is_same_v<WsStream, websocket::stream<beast::tcp_stream>>;

  auto& http_stream() { return ws_.next_layer(); }

  void read_request() {
    beast::get_lowest_layer(ws_).expires_after(std::chrono::seconds(30));
    http::async_read(http_stream(), buffer_, request_,
                     [self = this->shared_from_this()](beast::error_code ec, std::size_t) {
                       if (ec) return;
                       self->on_request();
                     });
  }

  void reply_http(http::status status, std::string body) {
    auto res = std::make_shared<http::response<http::string_body>>(status, request_.version());
    res->set(http::field::server, opts_.server_name);
    res->set(http::field::content_type, "text/plain; charset=utf-8");
    res->keep_alive(false);
    res->body() = std::move(body);
    res->prepare_payload();
    http::async_write(http_stream(), *res, [self = this->shared_from_this(), res](beast::error_code, std::size_t) {
      self->shutdown();
    });
  }

  void on_request() {
    if (!websocket::is_upgrade(request_)) {
      reply_http(http::status::upgrade_required,
                 "lcmx foxglove: a Foxglove WebSocket server. Open it in Foxglove or Lichtblick "
                 "(\"Foxglove WebSocket\" connection) at ws://HOST:PORT.\n");
      return;
    }
    const auto offered = request_[http::field::sec_websocket_protocol];
    subprotocol_ = choose_subprotocol(std::string_view(offered.data(), offered.size()), opts_.subprotocols);
    if (subprotocol_.empty()) {
      std::string list;
      for (const auto& s : opts_.subprotocols) list += (list.empty() ? "" : ", ") + s;
      reply_http(http::status::bad_request,
                 "lcmx foxglove: no supported WebSocket subprotocol offered (supported: " + list + ")\n");
      return;
    }
    beast::get_lowest_layer(ws_).expires_never();
    ws_.set_option(websocket::stream_base::timeout::suggested(beast::role_type::server));
    ws_.set_option(websocket::stream_base::decorator([this](websocket::response_type& res) {
      res.set(http::field::server, opts_.server_name);
      res.set(http::field::sec_websocket_protocol, subprotocol_);
    }));
    ws_.read_message_max(opts_.max_incoming_bytes);
    ws_.auto_fragment(false);
    ws_.async_accept(request_, [self = this->shared_from_this()](beast::error_code ec) {
      if (ec) return;
      self->open_ = true;
      self->peer_ = self->accept_(self);
      if (!self->peer_) {
        self->close("refused");
        return;
      }
      self->read_next();
      self->write_next();
    });
  }

  void read_next() {
    ws_.async_read(in_, [self = this->shared_from_this()](beast::error_code ec, std::size_t) {
      if (ec) {
        self->ended();
        return;
      }
      const auto data = self->in_.cdata();
      const auto* p = static_cast<const std::uint8_t*>(data.data());
      if (self->ws_.got_text()) self->peer_->on_text(std::string_view(reinterpret_cast<const char*>(p), data.size()));
      else self->peer_->on_binary(std::span<const std::uint8_t>(p, data.size()));
      self->in_.consume(self->in_.size());
      if (self->open_) self->read_next();
    });
  }

  // Writes the Peer's next frame, if any. `chained`: called as the previous write completed.
  // Frames that follow each other are corked (TCP_CORK) until the Peer has none left: the kernel
  // then sends full segments, and a client is woken once per batch, not once per small message
  // (the per-message wake-ups and segments were most of the server's CPU at 10 000 messages/s).
  void write_next(bool chained = false) {
    if (writing_ || !open_ || closing_ || !peer_) return;
    auto f = peer_->next_frame();
    if (!f) {
      cork(false);
      return;
    }
    if (chained) cork(true);
    writing_ = true;
    out_ = std::move(*f);
    ws_.text(out_.text);
    bufs_.clear();
    if (!out_.head.empty()) bufs_.push_back(asio::buffer(out_.head));
    if (out_.body)
      for (const auto& p : out_.body->parts) bufs_.push_back(asio::buffer(p->data(), p->size()));
    ws_.async_write(bufs_, [self = this->shared_from_this()](beast::error_code ec, std::size_t) {
      self->writing_ = false;
      self->out_ = {};
      if (ec) {
        self->ended();
        return;
      }
      self->write_next(true);
    });
  }

  void cork(bool on) {
    if (on == corked_) return;
    corked_ = on;
    const int v = on ? 1 : 0;
    ::setsockopt(beast::get_lowest_layer(ws_).socket().native_handle(), IPPROTO_TCP, TCP_CORK, &v, sizeof v);
  }

  void ended() {
    if (!open_) return;
    open_ = false;
    if (peer_) peer_->on_close();
    shutdown();
  }

  asio::io_context& ioc_;
  const ListenOptions& opts_;
  const AcceptFn& accept_;
  std::string remote_, subprotocol_;
  WsStream ws_;
  beast::flat_buffer buffer_;
  http::request<http::string_body> request_;
  beast::flat_buffer in_;
  OutFrame out_;
  std::vector<asio::const_buffer> bufs_;  // out_'s pieces, while it is written
  std::shared_ptr<Peer> peer_;
  bool open_ = false, closing_ = false, writing_ = false, corked_ = false;
  std::atomic<bool> wake_pending_{false};
};

using PlainWs = websocket::stream<beast::tcp_stream>;
using TlsWs = websocket::stream<beast::ssl_stream<beast::tcp_stream>>;

}  // namespace

struct Listener::Impl {
  ListenOptions opts;
  AcceptFn accept;
  asio::io_context ioc{1};
  tcp::acceptor acceptor{ioc};
  std::optional<asio::ssl::context> tls;
  std::vector<std::weak_ptr<SessionBase>> sessions;  // I/O thread only
  std::thread thread;
  std::uint16_t port = 0;

  void do_accept() {
    acceptor.async_accept([this](beast::error_code ec, tcp::socket sock) {
      if (ec) {
        if (ec == asio::error::operation_aborted || !acceptor.is_open()) return;
        do_accept();
        return;
      }
      beast::error_code e2;
      const auto ep = sock.remote_endpoint(e2);
      std::ostringstream r;
      r << ep.address().to_string() << ":" << ep.port();
      sock.set_option(tcp::no_delay(true), e2);
      std::erase_if(sessions, [](const auto& w) { return w.expired(); });
      if (tls) {
        auto s = std::make_shared<Session<TlsWs>>(ioc, opts, accept, r.str(), std::move(sock), *tls);
        sessions.push_back(s);
        s->start();
      } else {
        auto s = std::make_shared<Session<PlainWs>>(ioc, opts, accept, r.str(), std::move(sock));
        sessions.push_back(s);
        s->start();
      }
      do_accept();
    });
  }
};

Listener::Listener(const ListenOptions& options, AcceptFn accept) : impl_(std::make_unique<Impl>()) {
  auto& i = *impl_;
  i.opts = options;
  i.accept = std::move(accept);
  if (options.tls_cert.empty() != options.tls_key.empty())
    throw std::runtime_error("--tls-cert and --tls-key go together");
  if (!options.tls_cert.empty()) {
    i.tls.emplace(asio::ssl::context::tls_server);
    i.tls->set_options(asio::ssl::context::default_workarounds | asio::ssl::context::no_sslv2 |
                       asio::ssl::context::no_sslv3 | asio::ssl::context::no_tlsv1 |
                       asio::ssl::context::no_tlsv1_1);
    beast::error_code ec;
    i.tls->use_certificate_chain_file(options.tls_cert, ec);
    if (ec) throw std::runtime_error("TLS certificate " + options.tls_cert + ": " + ec.message());
    i.tls->use_private_key_file(options.tls_key, asio::ssl::context::pem, ec);
    if (ec) throw std::runtime_error("TLS key " + options.tls_key + ": " + ec.message());
  }
  beast::error_code ec;
  const auto addr = asio::ip::make_address(options.address, ec);
  if (ec) throw std::runtime_error("bad address '" + options.address + "': " + ec.message());
  const tcp::endpoint ep(addr, options.port);
  i.acceptor.open(ep.protocol(), ec);
  if (!ec) i.acceptor.set_option(asio::socket_base::reuse_address(true), ec);
  if (!ec) i.acceptor.bind(ep, ec);
  if (!ec) i.acceptor.listen(asio::socket_base::max_listen_connections, ec);
  if (ec)
    throw std::runtime_error("cannot listen on " + options.address + ":" + std::to_string(options.port) + ": " +
                             ec.message());
  i.port = i.acceptor.local_endpoint().port();
  i.do_accept();
  i.thread = std::thread([&i] {
    for (;;) {
      try {
        i.ioc.run();
        return;
      } catch (const std::exception&) {
        // A handler threw (a Peer's fault): that connection's state is its own; go on.
      }
    }
  });
}

Listener::~Listener() {
  auto& i = *impl_;
  std::promise<void> done;
  asio::post(i.ioc, [&i, &done] {
    beast::error_code ec;
    i.acceptor.close(ec);
    for (auto& w : i.sessions)
      if (auto s = w.lock()) s->shutdown();
    done.set_value();
  });
  // Sockets closed on the I/O thread (no session reads or writes after), then stop.
  done.get_future().wait_for(std::chrono::seconds(5));
  i.ioc.stop();
  if (i.thread.joinable()) i.thread.join();
}

std::uint16_t Listener::port() const { return impl_->port; }

void Listener::post(std::function<void()> fn) { asio::post(impl_->ioc, std::move(fn)); }

}  // namespace lcmx::foxglove::detail
