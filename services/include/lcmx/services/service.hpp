// Services: request/response between nodes, on lcmx's own paths (docs/services.md).
//
//   auto server = node.create_service<Req, Resp>("plan", [](const Req& r) { return Resp{...}; });
//   auto client = node.create_client<Req, Resp>("plan");
//   if (auto r = client.call(req, 500ms)) use(r.value()); else log(r.message());
//
// A call finds its server by discovery and travels like a message: in-process, shared memory,
// UDP or the Message Bridge, whichever the pair's path is. Requests go on "<name>/rq", replies
// on "<name>/rp/<client id>" (envelopes lcmx_msgs.service_request_t / service_reply_t,
// lcmtypes/service.lcm), so stock LCM tools see and record them.
//
// Servers: a client probes the service and uses the servers that answered, so both the
// request and the reply path are known to work before its first call (wait_for_service).
// Each call is executed by exactly one server: the nearest (in-process, then shared memory,
// then UDP, then the bridge), then the lowest (participant, server id) - a stable choice. If
// that server goes away before answering, the call is sent to the next one (fail-over); if
// none is left it fails with server_gone. A server that answered but died before the reply
// arrived may thus have executed the call once more than the client sees; the client takes
// exactly one reply per call.
//
// Threads: a server's handler runs on its node's executor, under the node's threading rule.
// A client receives replies on a thread of its own (so call() may block inside a callback of
// any node); call_async()'s callback runs on that thread, or on it for a timeout or fail-over
// too: keep it short. All members are thread-safe.
// Errors: creating a service or client throws lcmx::Error (invalid_argument for a bad name);
// calls never throw for call errors - they return them in CallResult.
//
// lcmx::services: a layer above the runtime (core/), built on its publish/subscribe API and
// one hook (lcmx/core/detail/service_hook.hpp). This header also defines Node's service
// member templates (declared in lcmx/core/node.hpp). Include <lcmx/core.hpp>.
#pragma once

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <functional>
#include <future>
#include <memory>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "lcmx/core/error.hpp"
#include "lcmx/core/node.hpp"
#include "lcmx/core/stats.hpp"
#include "lcmx/core/subscriber.hpp"

namespace lcmx {

enum class CallErrc {
  timeout,         // no reply within the timeout (the call is forgotten: a late reply is dropped)
  no_server,       // no server of the service answered a probe within the timeout
  server_gone,     // the server went away before answering and no other server is left
  type_mismatch,   // the servers' request/response types are not the client's
  handler_failed,  // the server's handler threw (message: what it said)
  bad_request,     // the server could not decode the request
  shutdown,        // the client was destroyed or the runtime shut down
};
const char* to_string(CallErrc e);

// Thrown by CallResult::value() on a failed call.
class CallError : public std::runtime_error {
 public:
  CallError(CallErrc code, const std::string& what) : std::runtime_error(what), code_(code) {}
  CallErrc code() const noexcept { return code_; }

 private:
  CallErrc code_;
};

// Which server answered a call (or was chosen for it).
struct ServerInfo {
  std::uint64_t participant = 0;
  std::uint64_t id = 0;  // the server's id within its participant
  Path path = Path::intra;
  // What the server takes and answers, from its probe answer (lcm-gen names, fingerprints;
  // "" and 0 for raw bytes). `lcmx call` encodes JSON with them.
  std::string request_type, response_type;
  std::int64_t request_fingerprint = 0, response_fingerprint = 0;
};

// The outcome of a call: a response, or an error with a message. Never both.
template <class T>
class CallResult {
 public:
  static CallResult success(T value, ServerInfo server) {
    CallResult r;
    r.value_.emplace(std::move(value));
    r.server_ = server;
    return r;
  }
  static CallResult failure(CallErrc error, std::string message, ServerInfo server = {}) {
    CallResult r;
    r.error_ = error;
    r.message_ = std::move(message);
    r.server_ = server;
    return r;
  }
  bool ok() const noexcept { return value_.has_value(); }
  explicit operator bool() const noexcept { return ok(); }
  // The response; throws CallError if the call failed.
  const T& value() const& { check(); return *value_; }
  T& value() & { check(); return *value_; }
  T&& value() && { check(); return std::move(*value_); }
  // Only meaningful when !ok().
  CallErrc error() const noexcept { return error_; }
  const std::string& message() const noexcept { return message_; }
  // The server that answered (ok, handler_failed, bad_request, type_mismatch) or was asked.
  const ServerInfo& server() const noexcept { return server_; }

 private:
  void check() const {
    if (!value_) throw CallError(error_, message_);
  }
  std::optional<T> value_;
  CallErrc error_ = CallErrc::timeout;
  std::string message_;
  ServerInfo server_;
};

using Bytes = std::vector<std::byte>;

struct ClientStats {
  std::uint64_t calls = 0;         // call()/call_async() made
  std::uint64_t replies = 0;       // calls answered (ok or with a server's error)
  std::uint64_t timeouts = 0;
  std::uint64_t failovers = 0;     // calls re-sent to another server
  std::uint64_t late_replies = 0;  // replies to calls already finished (timed out, failed over)
  // Replies that completed a blocking call (call(), call_retained(), the future call_async())
  // on the thread that received them from UDP, not handed over through the client's thread.
  std::uint64_t direct_replies = 0;
  // Replies ignored because they did not come from the server their call went to: another
  // participant, or another publisher than that server's, sent them (a forgery or a mistake).
  std::uint64_t foreign_replies = 0;
  std::size_t pending = 0;         // calls waiting for a reply now
  std::size_t servers = 0;         // servers that answered a probe and are still matched
};

struct ServerStats {
  std::uint64_t requests = 0;  // requests this server executed
  std::uint64_t failed = 0;    // of which the handler threw or the request did not decode
  std::uint64_t probes = 0;    // probes answered
  // Requests (probes included) ignored before anything was made for them: their client was
  // not checked (its reply channel is not its client id's, the participant it names did not
  // send it or announces no subscriber of that channel) or the server has a reply channel
  // for kMaxClients clients already, all still subscribed (docs/services.md "Trust").
  std::uint64_t refused = 0;
  std::size_t clients = 0;     // clients it has a reply channel for now
};

// Where a raw service's handler writes its response: allocate(size) once, then fill the span
// (for a caller on this host, it lies in the shared memory the client reads: no copy). Valid
// during the handler only. allocate() throws Error(invalid_argument) if called twice.
class ResponseWriter {
 public:
  virtual ~ResponseWriter() = default;
  virtual std::span<std::byte> allocate(std::size_t size) = 0;
};

namespace detail {
class NodeImpl;

// What a service's request and response are: lcm-gen types, or raw bytes (fingerprint 0,
// empty name). A client and a server match when each fingerprint is equal or either is 0.
struct ServiceTypes {
  std::string request_name, response_name;
  std::int64_t request_fingerprint = 0, response_fingerprint = 0;
};

// The server's request handler over bytes: `request` is the payload (valid during the call).
// Throws what the user's handler throws; BadRequest if the request does not decode.
using ServerHandler = std::function<void(std::span<const std::byte> request, ResponseWriter& out)>;
struct BadRequest : std::runtime_error {
  using std::runtime_error::runtime_error;
};

class ServerCore;
class ClientCore;
std::shared_ptr<ServerCore> create_server(NodeImpl& node, std::string name, ServiceTypes types,
                                          ServerHandler handler);
void close_server(const std::shared_ptr<ServerCore>& server);
ServerStats server_stats(const ServerCore& server);
const std::string& server_name(const ServerCore& server);
// The server's id within its participant (ServerInfo::id at its clients).
std::uint64_t server_id(const ServerCore& server);
// Whether the client with this client id was answered by the server and still subscribes to
// its reply channel (for actions: a goal's client is alive). Any thread.
bool server_client_connected(const ServerCore& server, std::uint64_t client_id);

// Called on the client's thread, with no lock held, with the servers that went away (their
// reply publisher is no longer matched): for actions, whose goals live on one server.
using ServersGone = std::function<void(const std::vector<ServerInfo>& gone)>;
std::shared_ptr<ClientCore> create_client(NodeImpl& node, std::string name, ServiceTypes types,
                                          ServersGone on_servers_gone = {});
void close_client(const std::shared_ptr<ClientCore>& client);
// `encode` writes the request payload into a span of `size` bytes. `done` gets the response
// payload (a view valid during the call) or an error; it is called exactly once, on the
// client's thread (or on the caller's, for an error found at once). `reply` is the reply
// message `response` lies in (for RawMessage::retain(), during the call only), or nullptr
// when no reply came (an error the client found itself). With `pin`, only that server
// (participant, id) executes the call: it waits for that server's probe answer, and fails
// with server_gone, never over, if the server goes away. With `hands_over`, `done` only hands
// the result to another thread (a promise: short, never blocks, never calls lcmx): a reply
// that arrives over UDP may then run it on the thread that received it (the runtime's receive
// thread) instead of the client's, sparing the caller one thread hand-over. `on_sent` (may be
// empty) is told each server the call is sent to (again on a fail-over), on the thread that
// sends it, with the client's lock held: it must be short and take no lock but a leaf of its
// own (actions: a goal's status is taken only from the server its goal went to).
using ReplyHandler =
    std::function<void(std::span<const std::byte> response, CallErrc error, bool ok,
                       const std::string& message, const ServerInfo& server, const RawMessage* reply)>;
// An `encode` for client_call that copies `request` (which must outlive the client_call).
inline std::function<void(std::span<std::byte>)> copy_request(std::span<const std::byte> request) {
  return [request](std::span<std::byte> out) { std::copy(request.begin(), request.end(), out.begin()); };
}
void client_call(ClientCore& client, std::size_t size,
                 const std::function<void(std::span<std::byte>)>& encode,
                 std::chrono::milliseconds timeout, ReplyHandler done,
                 const ServerInfo* pin = nullptr, bool hands_over = false,
                 std::function<void(const ServerInfo&)> on_sent = {});
bool client_wait_for_service(ClientCore& client, std::chrono::milliseconds timeout);
ClientStats client_stats(const ClientCore& client);
std::vector<ServerInfo> client_servers(const ClientCore& client);
const std::string& client_name(const ClientCore& client);
std::uint64_t client_id(const ClientCore& client);  // the id in its reply channel's name

}  // namespace detail

// A server of a service. Destroying it stops serving (a running handler finishes first);
// clients see it go as they see a publisher go.
class Service {
 public:
  Service() = default;
  Service(Service&&) noexcept = default;
  Service& operator=(Service&& o) noexcept {
    reset();
    core_ = std::move(o.core_);
    return *this;
  }
  ~Service() { reset(); }
  ServerStats stats() const { return detail::server_stats(*core_); }
  const std::string& name() const { return detail::server_name(*core_); }
  explicit operator bool() const { return core_ != nullptr; }
  void reset() {
    if (core_) detail::close_server(core_);
    core_.reset();
  }

 private:
  friend class Node;
  explicit Service(std::shared_ptr<detail::ServerCore> c) : core_(std::move(c)) {}
  std::shared_ptr<detail::ServerCore> core_;
};

namespace detail {
// What Client<Req, Resp> and RawClient have in common.
class ClientHandle {
 public:
  ClientHandle() = default;
  ClientHandle(ClientHandle&&) noexcept = default;
  ClientHandle& operator=(ClientHandle&& o) noexcept {
    reset();
    core_ = std::move(o.core_);
    return *this;
  }
  ~ClientHandle() { reset(); }

  // Returns once a server answered a probe (request and reply paths both work), false after
  // `timeout` without one. Servers of other types do not count. Servers that start together
  // are all known when it returns (it waits up to 100 ms after the first answer for the other
  // subscribers of the request channel), so the stable choice among them is made.
  bool wait_for_service(std::chrono::milliseconds timeout) const {
    return client_wait_for_service(*core_, timeout);
  }
  // Servers that answered a probe and are still there, best first (the one calls go to).
  std::vector<ServerInfo> servers() const { return client_servers(*core_); }
  ClientStats stats() const { return client_stats(*core_); }
  const std::string& name() const { return client_name(*core_); }
  explicit operator bool() const { return core_ != nullptr; }
  // Pending calls end with CallErrc::shutdown.
  void reset() {
    if (core_) close_client(core_);
    core_.reset();
  }

 protected:
  explicit ClientHandle(std::shared_ptr<ClientCore> c) : core_(std::move(c)) {}
  std::shared_ptr<ClientCore> core_;
};
}  // namespace detail

// A client of a service with lcm-gen request type Req and response type Resp.
template <class Req, class Resp>
class Client : public detail::ClientHandle {
 public:
  using Result = CallResult<Resp>;
  Client() = default;

  // Blocks until the reply, an error or `timeout` (which also covers finding a server).
  Result call(const Req& request, std::chrono::milliseconds timeout) {
    return call_async(request, timeout).get();
  }
  // The result arrives in the future (never an exception in it).
  std::future<Result> call_async(const Req& request, std::chrono::milliseconds timeout) {
    auto promise = std::make_shared<std::promise<Result>>();
    auto future = promise->get_future();
    start(request, timeout, [promise](Result r) { promise->set_value(std::move(r)); }, true);
    return future;
  }
  // `done` runs once with the result, on the client's thread (see the file comment).
  void call_async(const Req& request, std::chrono::milliseconds timeout,
                  std::function<void(Result)> done) {
    start(request, timeout, std::move(done), false);
  }

 private:
  friend class Node;
  explicit Client(std::shared_ptr<detail::ClientCore> c) : ClientHandle(std::move(c)) {}
  // `hands_over`: see detail::client_call.
  void start(const Req& request, std::chrono::milliseconds timeout, std::function<void(Result)> done,
             bool hands_over) {
    const auto size = static_cast<std::size_t>(request.getEncodedSize());
    detail::client_call(
        *core_, size,
        [&request](std::span<std::byte> out) {
          request.encode(out.data(), 0, static_cast<int>(out.size()));
        },
        timeout,
        [done = std::move(done)](std::span<const std::byte> bytes, CallErrc error, bool ok,
                                 const std::string& message, const ServerInfo& server, const RawMessage*) {
          if (!ok) return done(Result::failure(error, message, server));
          Resp response;
          if (bytes.size() > static_cast<std::size_t>(INT32_MAX) ||
              response.decode(bytes.data(), 0, static_cast<int>(bytes.size())) < 0)
            return done(Result::failure(CallErrc::type_mismatch,
                                        std::string("the response did not decode as ") +
                                            Resp::getTypeName(),
                                        server));
          done(Result::success(std::move(response), server));
        },
        nullptr, hands_over);
  }
};

// A client over raw bytes: requests and responses are any payload (lcm-gen encodings or not).
class RawClient : public detail::ClientHandle {
 public:
  using Result = CallResult<Bytes>;
  RawClient() = default;

  Result call(std::span<const std::byte> request, std::chrono::milliseconds timeout) {
    return call_async(request, timeout).get();
  }
  std::future<Result> call_async(std::span<const std::byte> request,
                                 std::chrono::milliseconds timeout) {
    auto promise = std::make_shared<std::promise<Result>>();
    auto future = promise->get_future();
    start(request, timeout, [promise](Result r) { promise->set_value(std::move(r)); }, true);
    return future;
  }
  // `done` runs once with the result, on the client's thread (see the file comment).
  void call_async(std::span<const std::byte> request, std::chrono::milliseconds timeout,
                  std::function<void(Result)> done) {
    start(request, timeout, std::move(done), false);
  }

  // Zero-copy forms of call(): the response stays where it arrived - the reply's pinned
  // shared-memory slot, or the in-process or UDP message's buffer - instead of being copied
  // into a byte vector (RawMessage::retain()). It stays valid while the RetainedBytes (or a
  // copy of its owner) lives, on any thread. A shared-memory response held this way keeps its
  // slot pinned (the server's reply publisher skips it); at most shm::Reader::kMaxDetached
  // responses per server are held at once, and beyond that the response is copied
  // (RetainedBytes::zero_copy says which). For large responses: it saves a copy of every byte
  // (docs/services.md).
  using RetainedResult = CallResult<RetainedBytes>;
  RetainedResult call_retained(std::span<const std::byte> request, std::chrono::milliseconds timeout) {
    auto promise = std::make_shared<std::promise<RetainedResult>>();
    auto future = promise->get_future();
    start_retained(request, timeout, [promise](RetainedResult r) { promise->set_value(std::move(r)); }, true);
    return future.get();
  }
  // `done` runs once with the result, on the client's thread (see the file comment).
  void call_retained_async(std::span<const std::byte> request, std::chrono::milliseconds timeout,
                           std::function<void(RetainedResult)> done) {
    start_retained(request, timeout, std::move(done), false);
  }

 private:
  friend class Node;
  explicit RawClient(std::shared_ptr<detail::ClientCore> c) : ClientHandle(std::move(c)) {}
  // `hands_over`: see detail::client_call.
  void start(std::span<const std::byte> request, std::chrono::milliseconds timeout,
             std::function<void(Result)> done, bool hands_over) {
    detail::client_call(
        *core_, request.size(),
        detail::copy_request(request), timeout,
        [done = std::move(done)](std::span<const std::byte> bytes, CallErrc error, bool ok,
                                 const std::string& message, const ServerInfo& server, const RawMessage*) {
          if (!ok) return done(Result::failure(error, message, server));
          done(Result::success(Bytes(bytes.begin(), bytes.end()), server));
        },
        nullptr, hands_over);
  }

  void start_retained(std::span<const std::byte> request, std::chrono::milliseconds timeout,
                      std::function<void(RetainedResult)> done, bool hands_over) {
    detail::client_call(
        *core_, request.size(),
        detail::copy_request(request), timeout,
        [done = std::move(done)](std::span<const std::byte> bytes, CallErrc error, bool ok,
                                 const std::string& message, const ServerInfo& server,
                                 const RawMessage* reply) {
          if (!ok || reply == nullptr) return done(RetainedResult::failure(error, message, server));
          RetainedBytes whole = reply->retain();
          // The payload lies after the reply envelope's header, at the same offset in the
          // retained message as in the reply.
          const auto offset = static_cast<std::size_t>(bytes.data() - reply->data.data());
          RetainedBytes r{whole.data.subspan(offset, bytes.size()), std::move(whole.owner), whole.zero_copy};
          done(RetainedResult::success(std::move(r), server));
        },
        nullptr, hands_over);
  }
};

}  // namespace lcmx

// --- Node's service members (declared in lcmx/core/node.hpp) ----------------------------------

namespace lcmx {

template <class Req, class Resp, class F>
Service Node::create_service(std::string name, F&& handler) {
  if constexpr (std::is_constructible_v<bool, const std::remove_reference_t<F>&>)
    if (!static_cast<bool>(handler))
      throw Error(Errc::invalid_argument, "create_service '" + name + "': empty handler");
  detail::ServiceTypes types{Req::getTypeName(), Resp::getTypeName(), Req::getHash(), Resp::getHash()};
  detail::ServerHandler h = [f = std::forward<F>(handler)](std::span<const std::byte> in,
                                                           ResponseWriter& out) mutable {
    Req request;
    if (in.size() > static_cast<std::size_t>(INT32_MAX) ||
        request.decode(in.data(), 0, static_cast<int>(in.size())) < 0)
      throw detail::BadRequest(std::string("the request did not decode as ") + Req::getTypeName());
    Resp response;
    if constexpr (std::is_invocable_v<F&, const Req&, Resp&>) {
      f(request, response);
    } else {
      static_assert(std::is_invocable_r_v<Resp, F&, const Req&>,
                    "create_service<Req, Resp>: handler must be Resp(const Req&) or "
                    "void(const Req&, Resp&)");
      response = f(request);
    }
    const auto size = static_cast<std::size_t>(response.getEncodedSize());
    auto bytes = out.allocate(size);
    response.encode(bytes.data(), 0, static_cast<int>(size));
  };
  return Service(detail::create_server(*impl_, std::move(name), std::move(types), std::move(h)));
}

template <class F>
Service Node::create_service_raw(std::string name, F&& handler) {
  if constexpr (std::is_constructible_v<bool, const std::remove_reference_t<F>&>)
    if (!static_cast<bool>(handler))  // an empty std::function or a null function pointer
      throw Error(Errc::invalid_argument, "create_service_raw '" + name + "': empty handler");
  detail::ServerHandler h;
  if constexpr (std::is_invocable_v<F&, std::span<const std::byte>, ResponseWriter&>) {
    h = std::forward<F>(handler);
  } else {
    static_assert(std::is_invocable_r_v<Bytes, F&, std::span<const std::byte>>,
                  "create_service_raw: handler must be Bytes(std::span<const std::byte>) or "
                  "void(std::span<const std::byte>, ResponseWriter&)");
    h = [f = std::forward<F>(handler)](std::span<const std::byte> in, ResponseWriter& out) mutable {
      const Bytes response = f(in);
      auto bytes = out.allocate(response.size());
      std::copy(response.begin(), response.end(), bytes.begin());
    };
  }
  return Service(detail::create_server(*impl_, std::move(name), {}, std::move(h)));
}

template <class Req, class Resp>
Client<Req, Resp> Node::create_client(std::string name) {
  return Client<Req, Resp>(detail::create_client(
      *impl_, std::move(name), {Req::getTypeName(), Resp::getTypeName(), Req::getHash(), Resp::getHash()}));
}

}  // namespace lcmx
