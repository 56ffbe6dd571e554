// Services (lcmx/services/service.hpp, docs/services.md): servers and clients on ordinary lcmx
// channels. A server is a subscriber of "<name>/rq" plus one publisher per client on
// "<name>/rp/<client id>"; a client is a publisher of "<name>/rq", a subscriber of its reply
// channel on a node of its own, and one thread that runs that node (replies), timeouts,
// probes and fail-over.
//
// The envelopes (lcmtypes/service.lcm) go through lcmx::lcmtypes' bounded codec
// (lcmx/lcmtypes/envelope.hpp) as a header before a payload, so the payload is encoded in
// place and read where it lies (in shared memory) instead of being copied into the generated
// struct's byte vector.
//
// Trust (docs/services.md "Trust"): a server makes nothing for a request before it is checked
// (its reply channel is its client id's, the participant it names sent it and subscribes to
// that channel) and keeps a reply channel for at most kMaxClients clients; a client takes a
// reply only from the server its call went to, checked against the pair the reply came
// through (sender.hpp).
#include "lcmx/services/service.hpp"

#include <algorithm>
#include <condition_variable>
#include <cstring>
#include <map>
#include <mutex>
#include <random>
#include <set>
#include <thread>

#include <spdlog/spdlog.h>

#include "lcmx/core/detail/service_hook.hpp"
#include "lcmx/lcmtypes/envelope.hpp"
#include "sender.hpp"

namespace lcmx {

const char* to_string(CallErrc e) {
  switch (e) {
    case CallErrc::timeout: return "timeout";
    case CallErrc::no_server: return "no server";
    case CallErrc::server_gone: return "server gone";
    case CallErrc::type_mismatch: return "type mismatch";
    case CallErrc::handler_failed: return "handler failed";
    case CallErrc::bad_request: return "bad request";
    case CallErrc::shutdown: return "shutdown";
  }
  return "?";
}

namespace detail {
namespace {

using Clock = std::chrono::steady_clock;

// --- Envelopes (lcmtypes/service.lcm) ---------------------------------------------------------
// Encoded and decoded with lcmx::lcmtypes' bounded codec, header by header, so the payload is
// written in place (a loaned slot) and read where it lies (envelope.hpp).

using RequestHeader = lcmtypes::ServiceRequestHeader;
using ReplyHeader = lcmtypes::ServiceReplyHeader;

void patch_target(Bytes& message, std::uint64_t participant, std::uint64_t id) {
  lcmtypes::Writer w(std::span<std::byte>(message).subspan(lcmtypes::kServiceRequestTargetOffset, 16));
  w.i64(static_cast<std::int64_t>(participant));
  w.i64(static_cast<std::int64_t>(id));
}

bool compatible(std::int64_t a, std::int64_t b) { return a == 0 || b == 0 || a == b; }

std::string type_text(const std::string& name, std::int64_t fp) {
  if (fp == 0) return "raw bytes";
  return fmt::format("{} ({:#018x})", name.empty() ? std::string("?") : name,
                     static_cast<std::uint64_t>(fp));
}

int path_rank(Path p) {
  switch (p) {
    case Path::intra: return 0;
    case Path::shm: return 1;
    case Path::udp: return 2;
    case Path::bridge: return 3;
  }
  return 4;
}

std::string request_channel(const std::string& name) { return name + "/rq"; }
std::string reply_prefix(const std::string& name) { return name + "/rp/"; }
// Whether `channel` is "<name>/rp/<id as 16 lower-case hex digits>", id != 0 (no allocation:
// every request is checked).
bool is_reply_channel(std::string_view channel, std::string_view name, std::uint64_t id) {
  if (id == 0 || channel.size() != name.size() + 4 + 16 || channel.substr(0, name.size()) != name ||
      channel.substr(name.size(), 4) != "/rp/")
    return false;
  constexpr char kHex[] = "0123456789abcdef";
  for (std::size_t i = 0; i < 16; ++i)
    if (channel[name.size() + 4 + i] != kHex[(id >> (60 - 4 * i)) & 0xf]) return false;
  return true;
}

// "<name>/rq" and "<name>/rp/<16 hex>" must fit LCM's 63-byte channel names.
constexpr std::size_t kMaxServiceName = kMaxChannelLength - 4 - 16;
void check_name(const std::string& name, const char* what) {
  if (name.empty())
    throw Error(Errc::invalid_argument, std::string(what) + ": the service name is empty");
  if (name.size() > kMaxServiceName)
    throw Error(Errc::channel_too_long,
                fmt::format("{}: service name '{}' is {} bytes; at most {} (its reply channel "
                            "'<name>/rp/<16 hex digits>' must fit LCM's {}-byte channel names)",
                            what, name, name.size(), kMaxServiceName, kMaxChannelLength));
}

const TypeInfo& request_type_info() {
  return announced_type_info(lcmx_msgs::service_request_t::getTypeName(),
                             lcmx_msgs::service_request_t::getHash());
}
const TypeInfo& reply_type_info() {
  return announced_type_info(lcmx_msgs::service_reply_t::getTypeName(),
                             lcmx_msgs::service_reply_t::getHash());
}

std::uint64_t random_nonzero() {
  static std::mutex mu;
  static std::mt19937_64 rng{std::random_device{}() ^
                             static_cast<std::uint64_t>(Clock::now().time_since_epoch().count())};
  std::lock_guard lock(mu);
  std::uint64_t v = 0;
  while (v == 0) v = rng();
  return v;
}

}  // namespace

// --- Server ------------------------------------------------------------------------------------

class ServerCore {
 public:
  ServerCore(std::shared_ptr<NodeImpl> n, std::string nm, ServiceTypes t, ServerHandler h)
      : node(std::move(n)), name(std::move(nm)), types(std::move(t)), handler(std::move(h)),
        participant(hook::participant_id(*node)) {}

  // The request subscriber's callback: on the server node's executor, one at a time.
  void on_request(const RawMessage& m);
  ServerStats stats() const {
    std::lock_guard lock(mu);
    return {requests, failed, probes, refused, replies.size()};
  }
  // Whether the client `reply_channel` belongs to has been answered by this server and its
  // reply channel has a subscriber now (the client is alive; across hosts, its demand).
  bool client_connected(const std::string& reply_channel) const {
    std::lock_guard lock(mu);
    auto it = replies.find(reply_channel);
    return it != replies.end() && it->second.pub->subscriber_count() > 0;
  }

  // Receive thread, about once a second (RuntimeImpl::add_housekeeping): forgets clients whose
  // reply channel has had no subscriber for kClientGone, releasing their reply segments (a
  // client's reply subscriber lives as long as the client; across the bridges, the bridge's
  // subscription lives as long as the client's demand).
  void sweep();

  // Clients a server keeps a reply channel (a publisher: a /dev/shm segment and an endpoint
  // in its beacons) for at once. A new client beyond it takes the place of one whose reply
  // channel has no subscriber now; with none, its requests are refused (ServerStats::refused).
  static constexpr std::size_t kMaxClients = 256;

  const std::shared_ptr<NodeImpl> node;
  const std::string name;
  const ServiceTypes types;
  const ServerHandler handler;
  const std::uint64_t participant;
  std::shared_ptr<SubscriberCore> request_sub;
  std::uint64_t housekeeping = 0;  // the runtime's id of the sweep job

 private:
  struct ReplyChannel {
    std::shared_ptr<PublisherCore> pub;
    Clock::time_point last_subscribed;  // last seen with a subscriber (or made)
    std::uint64_t client_participant = 0;  // the participant the client's requests come from
  };
  static constexpr std::chrono::seconds kClientGone{10};
  // The publisher of the client's reply channel, made for a checked client only (see the
  // file comment); null (counted, logged at most every 5 s) for a request to refuse.
  // Shared: sweep() may forget the client meanwhile (the publisher lives while in use).
  std::shared_ptr<PublisherCore> reply_channel(const RequestHeader& h, const RawMessage& m);
  std::shared_ptr<PublisherCore> refuse(const RequestHeader& h, const char* why);
  // A reply without payload: a probe's answer or an error (responses go through Writer).
  void reply(PublisherCore& pub, const ReplyHeader& rh);

  mutable std::mutex mu;  // guards the members below (stats() reads them from any thread)
  std::map<std::string, ReplyChannel, std::less<>> replies;
  std::uint64_t requests = 0, failed = 0, probes = 0, refused = 0;
  std::uint64_t refused_logged = 0;  // `refused` when last logged
  Clock::time_point refused_log_at{};
  Bytes buffer;  // executor only: the reply being built
};

std::shared_ptr<PublisherCore> ServerCore::refuse(const RequestHeader& h, const char* why) {
  std::lock_guard lock(mu);
  ++refused;
  const auto now = Clock::now();
  if (now - refused_log_at >= std::chrono::seconds(5)) {
    spdlog::warn("lcmx: service '{}': a request from participant {:x} (client {:016x}) was refused: {} ({} "
                 "refused since the last report)",
                 name, static_cast<std::uint64_t>(h.client_participant), static_cast<std::uint64_t>(h.client_id), why,
                 refused - refused_logged);
    refused_logged = refused;
    refused_log_at = now;
  }
  return nullptr;
}

std::shared_ptr<PublisherCore> ServerCore::reply_channel(const RequestHeader& h, const RawMessage& m) {
  // The channel the client subscribes to is named after its id: never publish anywhere else.
  if (!is_reply_channel(h.reply_channel, name, static_cast<std::uint64_t>(h.client_id)))
    return refuse(h, "its reply channel is not its client id's");
  // Who sent it: over the bridges this host's bridge, which names no origin; else the
  // participant the request names (its client's), the same for every request of a client.
  const auto from = sender_of(m);
  const bool bridged = from && from->path == Path::bridge;
  if (!from || (!bridged && from->participant != static_cast<std::uint64_t>(h.client_participant)))
    return refuse(h, "it was not sent by the participant it names");
  std::shared_ptr<PublisherCore> known;
  bool other = false;
  {
    std::lock_guard lock(mu);
    if (auto it = replies.find(h.reply_channel); it != replies.end()) {
      other = !bridged && it->second.client_participant != 0 && it->second.client_participant != from->participant;
      known = it->second.pub;
    }
  }
  if (other) return refuse(h, "its client id is another participant's client's");
  if (known) return known;
  // A new client. Its reply channel must be subscribed by the participant the request names
  // (in its beacons, or in this process): random client ids make nothing. Requests through
  // the bridges are the exception: this host's bridge subscribes to a reply channel only
  // once a publisher of it exists here, so only the bound below applies to them.
  const std::string channel(h.reply_channel);
  if (!bridged && !hook::subscriber_announced(*node, from->participant, channel))
    return refuse(h, "its client announces no subscriber of its reply channel");
  std::shared_ptr<PublisherCore> evicted;  // destroyed with no lock held
  bool full = false;
  {
    std::lock_guard lock(mu);
    if (replies.size() >= kMaxClients) {
      auto victim = replies.end();
      for (auto it = replies.begin(); it != replies.end(); ++it)
        if (it->second.pub->subscriber_count() == 0 &&
            (victim == replies.end() || it->second.last_subscribed < victim->second.last_subscribed))
          victim = it;
      if (victim == replies.end()) {
        full = true;
      } else {
        evicted = std::move(victim->second.pub);
        replies.erase(victim);
      }
    }
  }
  if (full) return refuse(h, "the server has a reply channel for kMaxClients (256) subscribed clients already");
  evicted.reset();
  // Only this thread (the request subscriber's callback) adds clients; sweep() only forgets.
  auto pub = create_publisher(*node, channel, reply_type_info(), PublisherOptions{});
  std::lock_guard lock(mu);
  auto& r = replies[channel];
  r.pub = std::move(pub);
  r.last_subscribed = Clock::now();
  r.client_participant = bridged ? 0 : from->participant;
  return r.pub;
}

void ServerCore::sweep() {
  std::vector<std::shared_ptr<PublisherCore>> gone;  // destroyed with no lock held
  const auto now = Clock::now();
  std::lock_guard lock(mu);
  for (auto it = replies.begin(); it != replies.end();) {
    auto& rc = it->second;
    if (rc.pub->subscriber_count() > 0) rc.last_subscribed = now;
    if (now - rc.last_subscribed > kClientGone) {
      gone.push_back(std::move(rc.pub));
      it = replies.erase(it);
    } else {
      ++it;
    }
  }
}

void ServerCore::reply(PublisherCore& pub, const ReplyHeader& rh) {
  buffer.resize(lcmtypes::header_size(rh));
  lcmtypes::encode_header(rh, 0, buffer);
  pub.publish_bytes(buffer);
}

void ServerCore::on_request(const RawMessage& m) {
  RequestHeader h;
  std::span<const std::byte> payload;
  if (!lcmtypes::decode(m.data, h, payload)) {
    spdlog::warn("lcmx: service '{}': a malformed request ({} bytes) was ignored", name, m.data.size());
    return;
  }
  // Our server id: the request subscriber's endpoint id (set before it was registered, so
  // before any callback).
  const std::uint64_t id = request_sub->id;
  const bool any = h.server_participant == 0 && h.server_id == 0;
  if (!any && (static_cast<std::uint64_t>(h.server_participant) != participant ||
               static_cast<std::uint64_t>(h.server_id) != id))
    return;  // for another server of the service
  if (h.request_id == 0 && !any) return;  // probes are addressed to every server
  const auto pub = reply_channel(h, m);
  if (pub == nullptr) return;  // refused (counted and logged)
  ReplyHeader rh;
  std::string error;  // rh.error's text
  rh.client_id = h.client_id;
  rh.request_id = h.request_id;
  rh.server_participant = static_cast<std::int64_t>(participant);
  rh.server_id = static_cast<std::int64_t>(id);
  rh.reply_endpoint = static_cast<std::int64_t>(hook::endpoint_id(*pub));
  rh.request_fingerprint = types.request_fingerprint;
  rh.response_fingerprint = types.response_fingerprint;
  rh.request_type = types.request_name;
  rh.response_type = types.response_name;
  const bool types_ok = compatible(h.request_fingerprint, types.request_fingerprint) &&
                        compatible(h.response_fingerprint, types.response_fingerprint);
  if (!types_ok) {
    rh.status = lcmx_msgs::service_reply_t::TYPE_MISMATCH;
    rh.error = error = fmt::format("service '{}' takes {} and answers {}; the client sends {} and expects {}",
                           name, type_text(types.request_name, types.request_fingerprint),
                           type_text(types.response_name, types.response_fingerprint),
                           type_text("", h.request_fingerprint), type_text("", h.response_fingerprint));
  }
  if (h.request_id == 0) {  // a probe: the answer says who we are and what we take
    {
      std::lock_guard lock(mu);
      ++probes;
    }
    return reply(*pub, rh);
  }
  {
    std::lock_guard lock(mu);
    ++requests;
  }
  if (!types_ok) {
    {
      std::lock_guard lock(mu);
      ++failed;
    }
    return reply(*pub, rh);
  }

  // The handler writes the response straight after the header, in a slot loaned from the
  // reply publisher's shared memory: a client on this host reads it where it lies (no copy);
  // in-process and UDP clients get it from there as from any publish.
  struct Writer final : ResponseWriter {
    PublisherCore& pub;
    const ReplyHeader& rh;
    std::size_t header;
    std::optional<shm::WriteLoan> loan;
    std::size_t total = 0;
    Writer(PublisherCore& p, const ReplyHeader& r) : pub(p), rh(r), header(lcmtypes::header_size(r)) {}
    ~Writer() {
      if (loan) pub.drop_loan(std::move(*loan));
    }
    std::span<std::byte> allocate(std::size_t size) override {
      if (loan) throw Error(Errc::invalid_argument, "ResponseWriter::allocate called twice");
      if (size > static_cast<std::size_t>(INT32_MAX))
        throw Error(Errc::message_too_large, "a service response is limited to 2 GiB");
      total = header + size;
      try {
        loan.emplace(pub.loan(total));
      } catch (const Error& e) {  // not the handler's fault: say so (the status stays HANDLER_FAILED)
        throw std::runtime_error(std::string("the server could not reserve shared memory for its response "
                                      "(its handler did not fail): ") + e.what());
      }
      lcmtypes::encode_header(rh, size, {loan->data(), header});
      return {loan->data() + header, size};
    }
    void publish() {
      if (!loan) allocate(0);
      auto l = std::move(*loan);
      loan.reset();
      try {
        pub.publish_loan(std::move(l), total);
      } catch (const Error& e) {
        throw std::runtime_error(std::string("the server could not publish its response (its handler did not fail): ") +
                          e.what());
      }
    }
  };
  try {
    Writer writer(*pub, rh);
    handler(payload, writer);
    writer.publish();
    return;
  } catch (const BadRequest& e) {
    rh.status = lcmx_msgs::service_reply_t::BAD_REQUEST;
    error = e.what();
  } catch (const std::exception& e) {
    rh.status = lcmx_msgs::service_reply_t::HANDLER_FAILED;
    error = e.what();
  } catch (...) {
    rh.status = lcmx_msgs::service_reply_t::HANDLER_FAILED;
    error = "the handler threw a non-std::exception";
  }
  rh.error = error;
  {
    std::lock_guard lock(mu);
    ++failed;
  }
  spdlog::warn("lcmx: service '{}': {}", name, rh.error);
  reply(*pub, rh);
}

std::shared_ptr<ServerCore> create_server(NodeImpl& node, std::string name, ServiceTypes types,
                                          ServerHandler handler) {
  check_name(name, "create_service");
  if (!handler) throw Error(Errc::invalid_argument, "create_service '" + name + "': empty handler");
  auto server = std::make_shared<ServerCore>(hook::shared(node), name, std::move(types),
                                             std::move(handler));
  // The subscriber announces the envelope type, so discovery (and `lcmx services`) tell a
  // service's server from a plain subscriber. Its callback uses `server` by address: the
  // subscriber is removed (and its callback waited for) before the server goes.
  ServerCore* raw = server.get();
  server->request_sub = std::make_shared<RawSubscriberCore>(
      request_channel(name), SubscriberOptions{.queue_depth = 64},
      [raw](const RawMessage& m) { raw->on_request(m); }, request_type_info());
  add_subscriber(node, server->request_sub);
  // Without it a gone client's reply segment stayed until the next new client came.
  std::weak_ptr<ServerCore> weak = server;
  server->housekeeping = hook::add_housekeeping(node, [weak] {
    if (auto s = weak.lock()) s->sweep();
  });
  return server;
}

void close_server(const std::shared_ptr<ServerCore>& server) {
  hook::remove_housekeeping(*server->node, server->housekeeping);
  remove_subscriber(server->request_sub);
}

ServerStats server_stats(const ServerCore& server) { return server.stats(); }
const std::string& server_name(const ServerCore& server) { return server.name; }
std::uint64_t server_id(const ServerCore& server) { return server.request_sub->id; }
bool server_client_connected(const ServerCore& server, std::uint64_t client_id) {
  return server.client_connected(fmt::format("{}{:016x}", reply_prefix(server.name), client_id));
}

// --- Client ------------------------------------------------------------------------------------

class ClientCore : public std::enable_shared_from_this<ClientCore> {
 public:
  ClientCore(std::string nm, ServiceTypes t, ServersGone gone)
      : name(std::move(nm)), types(std::move(t)),
        client_id(random_nonzero()),
        reply_channel(fmt::format("{}{:016x}", reply_prefix(name), client_id)),
        on_servers_gone(std::move(gone)) {}

  // Makes the client's node (beside `user_node`, in its runtime), endpoints and thread.
  void start(NodeImpl& user_node);
  void close();
  void call(std::size_t size, const std::function<void(std::span<std::byte>)>& encode,
            std::chrono::milliseconds timeout, ReplyHandler done, const ServerInfo* pin, bool hands_over,
            std::function<void(const ServerInfo&)> on_sent);
  bool wait_for_service(std::chrono::milliseconds timeout);
  ClientStats stats() const;
  std::vector<ServerInfo> servers_now() const;

  const std::string name;
  const ServiceTypes types;
  const std::uint64_t client_id;
  const std::string reply_channel;
  const ServersGone on_servers_gone;  // may be empty

 private:
  struct Known {
    ServerInfo info;
    // The publisher of our reply channel we hear this server through (see on_reply), and the
    // server's own publisher of it (the same, unless the bridges carry the channel).
    std::uint64_t reply_participant = 0, reply_endpoint = 0;
    std::uint64_t server_reply_endpoint = 0;
    bool types_ok = true;
    std::string mismatch;  // !types_ok: the server's words
  };
  struct Pending {
    Bytes message;                 // the encoded request (target patched on fail-over)
    Clock::time_point deadline;
    std::chrono::milliseconds timeout;
    ReplyHandler done;
    ServerInfo target;
    bool sent = false;  // false: waiting for a server
    // `done` only hands the result over (a blocking call's promise): its reply may complete it
    // where the reply is received (try_inline_reply).
    bool hands_over = false;
    // Only this server (participant, id) may execute the call: no fail-over.
    std::optional<std::pair<std::uint64_t, std::uint64_t>> pin;
    // Told each server the call is sent to (detail::client_call); may be empty.
    std::function<void(const ServerInfo&)> on_sent;
    // The servers the call was sent to (more than one after a fail-over): its reply is taken
    // from one of them only, through the publisher it was heard through (see on_reply).
    struct SentTo {
      std::uint64_t participant = 0, id = 0;
      std::uint64_t reply_endpoint = 0;  // the server's publisher of our reply channel
      bool remote = false;               // reached over UDP or the bridges
    };
    std::vector<SentTo> sent_to;
  };
  struct Finished {  // a call ended by the client itself (not a reply): `done` runs unlocked
    ReplyHandler done;
    CallErrc error;
    std::string message;
    ServerInfo server;
  };

  // The envelope fields every request of this client has (request id 0, no target: a probe).
  // Views `reply_channel` (a member).
  RequestHeader request_header() const {
    RequestHeader h;
    h.client_id = static_cast<std::int64_t>(client_id);
    h.client_participant = static_cast<std::int64_t>(participant);
    h.request_fingerprint = types.request_fingerprint;
    h.response_fingerprint = types.response_fingerprint;
    h.reply_channel = reply_channel;
    return h;
  }
  // Whether a reply that came from `from` may answer call `p`: the server it names is one the
  // call went to, and that server's publisher sent it (sender.hpp). Under mu.
  static bool from_target(const Pending& p, const ReplyHeader& h, const std::optional<Sender>& from);
  void loop();
  void on_reply(const RawMessage& m);  // client thread, in the reply subscriber's callback
  // The runtime's receive thread (SubscriberCore::udp_inline): completes a hands_over call on
  // its reply from UDP at once; false (the client thread takes it) for anything else.
  bool try_inline_reply(const RawMessage& m);
  // Ends call `it` with its reply: under `lock` (released here, before `done` runs).
  void complete_locked(std::unique_lock<std::mutex>& lock, std::map<std::uint64_t, Pending>::iterator it,
                       const ReplyHeader& h, std::span<const std::byte> payload, const RawMessage& m);
  // Under mu: drop servers whose reply publisher is no longer matched, fail calls over.
  void refresh_servers_locked(std::vector<Finished>& finished, std::vector<ServerInfo>& gone_servers);
  const Known* best_locked() const;
  // The server a call goes to now: its pinned server if known, else the best; null if none.
  const Known* target_locked(const Pending& p) const;
  void send_locked(Pending& p, const Known& server);
  // Removes a call from `pending` (or all of them), keeping `in_flight` in step.
  std::map<std::uint64_t, Pending>::iterator forget_locked(std::map<std::uint64_t, Pending>::iterator it);
  void forget_all_locked();
  void dispatch_waiting_locked();
  void expire_locked(Clock::time_point now, std::vector<Finished>& finished);
  std::string mismatch_text_locked() const;
  void probe_locked(Clock::time_point now);
  static void finish(std::vector<Finished>& finished);

  std::shared_ptr<NodeImpl> node;  // manual executor, run by `thread`
  std::uint64_t participant = 0;   // node's (set by start)
  std::shared_ptr<PublisherCore> request_pub;
  std::shared_ptr<SubscriberCore> reply_sub;
  std::uint64_t tap = 0;
  std::thread thread;

  mutable std::mutex mu;           // guards everything below
  std::condition_variable cv;      // servers changed (wait_for_service)
  bool closed = false;        // no more calls (closed, or the runtime shut down)
  bool close_called = false;  // close() ran
  std::atomic<bool> matches_changed{true};
  std::map<std::pair<std::uint64_t, std::uint64_t>, Known> servers;  // (participant, id)
  std::map<std::uint64_t, Pending> pending;
  // Calls sent and not yet answered, expired or failed. At most kMaxInFlight: the rest wait in
  // `pending` (unsent, in call order) and go as earlier ones end. A burst of calls from many
  // threads would otherwise overrun the request ring (PublisherOptions::shm_slots, 8) before
  // the server's executor reads it, losing requests that then time out; probes need room too.
  std::size_t in_flight = 0;
  static constexpr std::size_t kMaxInFlight = 6;
  std::uint64_t next_request = 1;
  int waiters = 0;  // threads in wait_for_service()
  Clock::time_point next_probe{};
  Clock::time_point wake_at{};
  Clock::time_point first_server_at{};  // when the first usable server answered (wait_for_service)
  static constexpr std::chrono::milliseconds kServerGrace{100};  // when the client thread wakes at the latest (its run_once deadline)
  std::chrono::milliseconds probe_interval{2};
  std::size_t last_server_count = 0;  // request subscribers matched when we last probed
  Bytes probe_message;
  ClientStats counters;
};

void ClientCore::start(NodeImpl& user_node) {
  node = hook::create_manual_node(user_node, hook::node_name(user_node) + "/client:" + name);
  participant = hook::participant_id(*node);
  request_pub = create_publisher(*node, request_channel(name), request_type_info(), PublisherOptions{});
  // A new server's subscriber wakes our thread to probe it (matched before this line: the
  // thread's first pass sees the count).
  hook::interrupt_on_match(*request_pub);
  std::weak_ptr<ClientCore> weak = weak_from_this();
  reply_sub = std::make_shared<RawSubscriberCore>(
      reply_channel, SubscriberOptions{.queue_depth = 64},
      [this](const RawMessage& m) { on_reply(m); }, reply_type_info());
  // A weak reference: the receive thread may offer a reply while the client is being closed.
  reply_sub->udp_inline = [weak](const RawMessage& m) {
    const auto self = weak.lock();
    return self && self->try_inline_reply(m);
  };
  add_subscriber(*node, reply_sub);
  // Our reply channel's publishers come and go (a server leaves): re-check at once.
  tap = hook::add_event_tap(*node, [weak, channel = reply_channel](const Event& e) {
    if (e.channel != channel && e.kind != Event::Kind::participant_left) return;
    if (auto self = weak.lock()) {
      self->matches_changed.store(true);
      hook::interrupt(*self->node);
    }
  });
  const RequestHeader h = request_header();
  probe_message.resize(lcmtypes::header_size(h));
  lcmtypes::encode_header(h, 0, probe_message);
  thread = std::thread([this] { loop(); });
}

void ClientCore::close() {
  {
    std::lock_guard lock(mu);
    if (close_called) return;
    close_called = true;
    closed = true;
  }
  cv.notify_all();
  hook::interrupt(*node);
  if (thread.joinable()) {
    if (thread.get_id() == std::this_thread::get_id()) thread.detach();  // from a done callback
    else thread.join();
  }
  hook::remove_event_tap(*node, tap);
  std::vector<Finished> finished;
  {
    std::lock_guard lock(mu);
    for (auto& [id, p] : pending)
      finished.push_back({std::move(p.done), CallErrc::shutdown,
                          "service '" + name + "': the client was closed", p.target});
    forget_all_locked();
  }
  finish(finished);
  remove_subscriber(reply_sub);
  request_pub.reset();
  hook::stop(*node);
}

void ClientCore::finish(std::vector<Finished>& finished) {
  for (auto& f : finished) {
    try {
      f.done({}, f.error, false, f.message, f.server, nullptr);
    } catch (const std::exception& e) {
      spdlog::error("lcmx: a service call's completion threw: {}", e.what());
    }
  }
  finished.clear();
}

void ClientCore::loop() {
  std::vector<Finished> finished;
  std::vector<ServerInfo> gone_servers;
  for (;;) {
    std::chrono::nanoseconds wait{std::chrono::seconds(1)};
    {
      std::unique_lock lock(mu);
      if (closed) return;
      const auto now = Clock::now();
      if (matches_changed.exchange(false)) {
        refresh_servers_locked(finished, gone_servers);
        // A server's reply publisher may have just matched: its answer to the next probe now
        // arrives, so probe at once rather than at the back-off's next turn.
        next_probe = now;
        probe_interval = std::chrono::milliseconds(2);
      }
      expire_locked(now, finished);
      // Probe while someone waits for a server, or a request subscriber appeared that has not
      // answered yet (a new server: it may be nearer, or the one to fail over to).
      const auto subscribers = request_pub->subscriber_count();
      if (subscribers != last_server_count) {
        last_server_count = subscribers;
        probe_interval = std::chrono::milliseconds(2);
        next_probe = now;
      }
      bool waiting = waiters > 0;  // for a server (not for a free place in flight)
      for (const auto& [id, p] : pending) waiting = waiting || (!p.sent && target_locked(p) == nullptr);
      const bool unanswered = subscribers > servers.size();
      if ((waiting || unanswered) && subscribers > 0) {
        if (now >= next_probe) probe_locked(now);
        wait = std::min<std::chrono::nanoseconds>(wait, next_probe - now);
      }
      for (const auto& [id, p] : pending)
        wait = std::min<std::chrono::nanoseconds>(wait, p.deadline - now);
      wait = std::max<std::chrono::nanoseconds>(wait, std::chrono::nanoseconds(0));
      wake_at = now + wait;
      if (hook::stopped(*node)) {  // the runtime shut down: nothing will answer any more
        closed = true;
        for (auto& [id, p] : pending)
          finished.push_back({std::move(p.done), CallErrc::shutdown,
                              "service '" + name + "': the runtime shut down", p.target});
        forget_all_locked();
      }
    }
    finish(finished);
    if (!gone_servers.empty() && on_servers_gone) {
      try {
        on_servers_gone(gone_servers);
      } catch (const std::exception& e) {
        spdlog::error("lcmx: service '{}': a servers-gone listener threw: {}", name, e.what());
      }
    }
    gone_servers.clear();
    if (hook::stopped(*node)) return;
    hook::run_once(*node, wait);
  }
}

void ClientCore::probe_locked(Clock::time_point now) {
  request_pub->publish_bytes(probe_message);
  next_probe = now + probe_interval;
  // 2, 4, ... 512 ms, then every second while a server is still silent.
  probe_interval = std::min<std::chrono::milliseconds>(probe_interval * 2, std::chrono::seconds(1));
}

void ClientCore::refresh_servers_locked(std::vector<Finished>& finished,
                                        std::vector<ServerInfo>& gone_servers) {
  std::map<std::pair<std::uint64_t, std::uint64_t>, Path> matched;  // (participant, endpoint)
  const std::pair<std::uint64_t, std::uint64_t>* bridge = nullptr;   // a bridge republisher
  for (const auto& p : subscriber_stats(*reply_sub).publishers)
    matched[{p.publisher_participant, p.publisher_endpoint}] = p.path;
  for (const auto& [key, path] : matched)
    if (path == Path::bridge && bridge == nullptr) bridge = &key;
  std::set<std::pair<std::uint64_t, std::uint64_t>> gone;
  for (auto it = servers.begin(); it != servers.end();) {
    Known& k = it->second;
    // Heard through the publisher we watch; or, the pair's path changed (a topic that turns
    // large goes from UDP to the bridges, and back when they stop), through the server's own
    // publisher or this host's bridge. Gone only when neither is matched.
    auto m = matched.find({k.reply_participant, k.reply_endpoint});
    if (m == matched.end()) m = matched.find({k.info.participant, k.server_reply_endpoint});
    const bool remote = k.info.path != Path::intra && k.info.path != Path::shm;
    if (m == matched.end() && bridge != nullptr && remote) m = matched.find(*bridge);
    if (m == matched.end() && remote && hook::endpoint_announced(*node, k.info.participant, k.info.id)) {
      ++it;  // between two paths (its reply channel turned large; the bridges take over)
      continue;
    }
    if (m == matched.end()) {
      gone.insert(it->first);
      gone_servers.push_back(k.info);
      it = servers.erase(it);
    } else {
      k.reply_participant = m->first.first;
      k.reply_endpoint = m->first.second;
      k.info.path = m->second;
      ++it;
    }
  }
  if (gone.empty()) return;
  cv.notify_all();
  const Known* next = best_locked();
  for (auto it = pending.begin(); it != pending.end();) {
    auto& p = it->second;
    if (!p.sent || !gone.contains({p.target.participant, p.target.id})) {
      ++it;
      continue;
    }
    if (next != nullptr && !p.pin) {
      ++counters.failovers;
      spdlog::info("lcmx: service '{}': server {:x}/{} went away; call {} goes to {:x}/{}", name,
                   p.target.participant, p.target.id, it->first, next->info.participant, next->info.id);
      send_locked(p, *next);
      ++it;
    } else {
      finished.push_back({std::move(p.done), CallErrc::server_gone,
                          fmt::format("service '{}': the server went away before answering "
                                      "and no other server is known",
                                      name),
                          p.target});
      it = forget_locked(it);
    }
  }
  dispatch_waiting_locked();
}

const ClientCore::Known* ClientCore::best_locked() const {
  const Known* best = nullptr;
  for (const auto& [key, k] : servers) {
    if (!k.types_ok) continue;
    if (best == nullptr || path_rank(k.info.path) < path_rank(best->info.path)) best = &k;
    // Equal rank: the map's order (participant, id) already makes the first one stable.
  }
  return best;
}

const ClientCore::Known* ClientCore::target_locked(const Pending& p) const {
  if (!p.pin) return best_locked();
  auto it = servers.find(*p.pin);
  return it != servers.end() && it->second.types_ok ? &it->second : nullptr;
}

std::map<std::uint64_t, ClientCore::Pending>::iterator ClientCore::forget_locked(
    std::map<std::uint64_t, Pending>::iterator it) {
  if (it->second.sent) --in_flight;
  return pending.erase(it);
}

void ClientCore::forget_all_locked() {
  pending.clear();
  in_flight = 0;
}

void ClientCore::send_locked(Pending& p, const Known& server) {
  p.target = server.info;
  if (!p.sent) ++in_flight;  // a fail-over re-sends a call already in flight
  p.sent = true;
  p.sent_to.push_back({server.info.participant, server.info.id, server.server_reply_endpoint,
                       server.info.path == Path::udp || server.info.path == Path::bridge});
  if (p.on_sent) p.on_sent(server.info);
  patch_target(p.message, server.info.participant, server.info.id);
  request_pub->publish_bytes(p.message);
}

bool ClientCore::from_target(const Pending& p, const ReplyHeader& h, const std::optional<Sender>& from) {
  if (!from) return false;
  for (const auto& t : p.sent_to)
    if (t.participant == static_cast<std::uint64_t>(h.server_participant) &&
        t.id == static_cast<std::uint64_t>(h.server_id) && sent_by(*from, t.participant, t.reply_endpoint, t.remote))
      return true;
  return false;
}

// Sends waiting calls, oldest first, while fewer than kMaxInFlight are in flight.
void ClientCore::dispatch_waiting_locked() {
  for (auto& [id, p] : pending) {
    if (in_flight >= kMaxInFlight) return;
    if (!p.sent)
      if (const Known* target = target_locked(p)) send_locked(p, *target);
  }
}

std::string ClientCore::mismatch_text_locked() const {
  for (const auto& [key, k] : servers)
    if (!k.types_ok) return k.mismatch;
  return {};
}

void ClientCore::expire_locked(Clock::time_point now, std::vector<Finished>& finished) {
  for (auto it = pending.begin(); it != pending.end();) {
    auto& p = it->second;
    if (p.deadline > now) {
      ++it;
      continue;
    }
    if (p.sent) {
      ++counters.timeouts;
      finished.push_back({std::move(p.done), CallErrc::timeout,
                          fmt::format("service '{}': no reply within {} ms", name, p.timeout.count()),
                          p.target});
    } else if (target_locked(p) != nullptr) {  // never sent: it waited behind calls in flight
      ++counters.timeouts;
      finished.push_back({std::move(p.done), CallErrc::timeout,
                          fmt::format("service '{}': no reply within {} ms (the call waited behind {} "
                                      "calls of this client in flight and was never sent)",
                                      name, p.timeout.count(), in_flight),
                          {}});
    } else if (auto text = mismatch_text_locked(); !text.empty()) {
      finished.push_back({std::move(p.done), CallErrc::type_mismatch, text, {}});
    } else {
      finished.push_back({std::move(p.done), CallErrc::no_server,
                          fmt::format("service '{}': no server answered within {} ms", name,
                                      p.timeout.count()),
                          {}});
    }
    it = forget_locked(it);
  }
  dispatch_waiting_locked();
}

void ClientCore::on_reply(const RawMessage& m) {
  ReplyHeader h;
  std::span<const std::byte> payload;
  if (!lcmtypes::decode(m.data, h, payload) || static_cast<std::uint64_t>(h.client_id) != client_id) return;
  const auto sender = sender_of(m);
  ServerInfo from;
  from.participant = static_cast<std::uint64_t>(h.server_participant);
  from.id = static_cast<std::uint64_t>(h.server_id);
  std::unique_lock lock(mu);
  if (h.request_id == 0) {  // a probe's answer: a server we can use (or one of other types)
    // Only from the server it names: its own reply publisher (or this host's bridge).
    if (!sender || !sent_by(*sender, from.participant, static_cast<std::uint64_t>(h.reply_endpoint), true)) {
      ++counters.foreign_replies;
      return;
    }
    Known k;
    k.info = from;
    k.info.request_type = std::string(h.request_type);
    k.info.response_type = std::string(h.response_type);
    k.info.request_fingerprint = h.request_fingerprint;
    k.info.response_fingerprint = h.response_fingerprint;
    k.reply_endpoint = static_cast<std::uint64_t>(h.reply_endpoint);
    k.server_reply_endpoint = k.reply_endpoint;
    // The publisher we hear the server through: its own reply publisher, or (a server on
    // another host behind the Message Bridges) this host's bridge republishing the channel.
    // When that publisher is no longer matched, the server is gone for us.
    k.reply_participant = k.info.participant;
    bool matched = false;
    const auto pairs = subscriber_stats(*reply_sub).publishers;
    for (const auto& p : pairs)
      if (p.publisher_participant == k.info.participant && p.publisher_endpoint == k.reply_endpoint) {
        k.info.path = p.path;
        matched = true;
      }
    for (const auto& p : pairs)
      if (!matched && p.path == Path::bridge) {
        k.reply_participant = p.publisher_participant;
        k.reply_endpoint = p.publisher_endpoint;
        k.info.path = Path::bridge;
        matched = true;
      }
    if (!matched) return;  // already gone again
    k.types_ok = h.status != lcmx_msgs::service_reply_t::TYPE_MISMATCH;
    if (!k.types_ok)
      k.mismatch = fmt::format(
          "service '{}': its server takes {} and answers {}; this client sends {} and expects {}",
          name, type_text(std::string(h.request_type), h.request_fingerprint),
          type_text(std::string(h.response_type), h.response_fingerprint),
          type_text(types.request_name, types.request_fingerprint),
          type_text(types.response_name, types.response_fingerprint));
    const bool is_new = !servers.contains({from.participant, from.id});
    if (k.types_ok && best_locked() == nullptr) first_server_at = Clock::now();
    servers[{from.participant, from.id}] = k;
    if (is_new && !k.types_ok) spdlog::warn("lcmx: {}", k.mismatch);
    dispatch_waiting_locked();
    lock.unlock();
    cv.notify_all();
    return;
  }
  auto it = pending.find(static_cast<std::uint64_t>(h.request_id));
  if (it == pending.end()) {
    ++counters.late_replies;
    return;
  }
  if (!from_target(it->second, h, sender)) {  // not from a server the call went to
    ++counters.foreign_replies;
    return;
  }
  complete_locked(lock, it, h, payload, m);
}

bool ClientCore::try_inline_reply(const RawMessage& m) {
  ReplyHeader h;
  std::span<const std::byte> payload;
  if (!lcmtypes::decode(m.data, h, payload) || static_cast<std::uint64_t>(h.client_id) != client_id ||
      h.request_id == 0)
    return false;  // not ours, or a probe's answer: the client thread's
  const auto sender = sender_of(m);
  std::unique_lock lock(mu);
  auto it = pending.find(static_cast<std::uint64_t>(h.request_id));
  // Calls waiting to be sent go when this one ends: the client thread publishes them. A
  // reply not from the call's server is the client thread's to count.
  if (it == pending.end() || !it->second.hands_over || pending.size() > in_flight ||
      !from_target(it->second, h, sender))
    return false;
  ++counters.direct_replies;
  complete_locked(lock, it, h, payload, m);
  return true;
}

void ClientCore::complete_locked(std::unique_lock<std::mutex>& lock, std::map<std::uint64_t, Pending>::iterator it,
                                 const ReplyHeader& h, std::span<const std::byte> payload, const RawMessage& m) {
  ServerInfo from;
  from.participant = static_cast<std::uint64_t>(h.server_participant);
  from.id = static_cast<std::uint64_t>(h.server_id);
  auto done = std::move(it->second.done);
  ServerInfo server = from;
  if (auto s = servers.find({from.participant, from.id}); s != servers.end()) server = s->second.info;
  forget_locked(it);
  ++counters.replies;
  dispatch_waiting_locked();
  lock.unlock();
  CallErrc error = CallErrc::handler_failed;
  switch (h.status) {
    case lcmx_msgs::service_reply_t::OK: break;
    case lcmx_msgs::service_reply_t::TYPE_MISMATCH: error = CallErrc::type_mismatch; break;
    case lcmx_msgs::service_reply_t::BAD_REQUEST: error = CallErrc::bad_request; break;
    default: error = CallErrc::handler_failed; break;
  }
  const bool ok = h.status == lcmx_msgs::service_reply_t::OK;
  try {
    done(payload, error, ok, ok ? std::string() : "service '" + name + "': " + std::string(h.error), server, &m);
  } catch (const std::exception& e) {
    spdlog::error("lcmx: service '{}': a call's completion threw: {}", name, e.what());
  }
}

void ClientCore::call(std::size_t size, const std::function<void(std::span<std::byte>)>& encode,
                      std::chrono::milliseconds timeout, ReplyHandler done, const ServerInfo* pin,
                      bool hands_over, std::function<void(const ServerInfo&)> on_sent) {
  if (size > static_cast<std::size_t>(INT32_MAX))
    return done({}, CallErrc::bad_request, false, "a service request is limited to 2 GiB", {}, nullptr);
  RequestHeader h = request_header();
  Pending p;
  p.timeout = timeout;
  p.deadline = Clock::now() + timeout;
  p.done = std::move(done);
  p.hands_over = hands_over;
  p.on_sent = std::move(on_sent);
  if (pin != nullptr) p.pin.emplace(pin->participant, pin->id);
  std::unique_lock lock(mu);
  if (closed) {
    lock.unlock();
    return p.done({}, CallErrc::shutdown, false, "service '" + name + "': the client was closed", {}, nullptr);
  }
  h.request_id = static_cast<std::int64_t>(next_request++);
  const auto hs = lcmtypes::header_size(h);
  p.message.resize(hs + size);
  lcmtypes::encode_header(h, size, p.message);
  encode({p.message.data() + hs, size});
  ++counters.calls;
  auto& slot = pending[static_cast<std::uint64_t>(h.request_id)] = std::move(p);
  bool wake = true;  // no server yet: probe now
  if (const Known* target = target_locked(slot)) {
    if (in_flight < kMaxInFlight) send_locked(slot, *target);  // else it goes when one ends
    wake = slot.deadline < wake_at;  // the client thread must time it out earlier than planned
  }
  lock.unlock();
  if (wake) hook::interrupt(*node);
}

bool ClientCore::wait_for_service(std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  std::unique_lock lock(mu);
  ++waiters;
  lock.unlock();
  hook::interrupt(*node);
  lock.lock();
  // Ready once a server answered and either every request subscriber has answered or
  // kServerGrace passed since the first answer: servers that start together are all known
  // (and the stable choice among them made) before the first call. A subscriber that never
  // answers (a recorder of the channel) delays it by kServerGrace only.
  bool ok = false;
  for (;;) {
    if (closed) break;
    const auto now = Clock::now();
    auto wake = deadline;
    if (best_locked() != nullptr) {
      if (servers.size() >= request_pub->subscriber_count() || now >= first_server_at + kServerGrace) {
        ok = true;
        break;
      }
      wake = std::min(deadline, first_server_at + kServerGrace);
    }
    if (now >= deadline) break;
    cv.wait_until(lock, wake);
  }
  --waiters;
  return ok;
}

ClientStats ClientCore::stats() const {
  std::lock_guard lock(mu);
  ClientStats s = counters;
  s.pending = pending.size();
  for (const auto& [key, k] : servers) s.servers += k.types_ok ? 1 : 0;
  return s;
}

std::vector<ServerInfo> ClientCore::servers_now() const {
  std::lock_guard lock(mu);
  std::vector<ServerInfo> out;
  for (const auto& [key, k] : servers)
    if (k.types_ok) out.push_back(k.info);
  std::stable_sort(out.begin(), out.end(), [](const ServerInfo& a, const ServerInfo& b) {
    return path_rank(a.path) < path_rank(b.path);
  });
  return out;
}

std::shared_ptr<ClientCore> create_client(NodeImpl& node, std::string name, ServiceTypes types,
                                          ServersGone on_servers_gone) {
  check_name(name, "create_client");
  auto client = std::make_shared<ClientCore>(std::move(name), std::move(types), std::move(on_servers_gone));
  client->start(node);
  return client;
}

void close_client(const std::shared_ptr<ClientCore>& client) { client->close(); }

void client_call(ClientCore& client, std::size_t size,
                 const std::function<void(std::span<std::byte>)>& encode,
                 std::chrono::milliseconds timeout, ReplyHandler done, const ServerInfo* pin,
                 bool hands_over, std::function<void(const ServerInfo&)> on_sent) {
  client.call(size, encode, timeout, std::move(done), pin, hands_over, std::move(on_sent));
}
bool client_wait_for_service(ClientCore& client, std::chrono::milliseconds timeout) {
  return client.wait_for_service(timeout);
}
ClientStats client_stats(const ClientCore& client) { return client.stats(); }
std::vector<ServerInfo> client_servers(const ClientCore& client) { return client.servers_now(); }
const std::string& client_name(const ClientCore& client) { return client.name; }
std::uint64_t client_id(const ClientCore& client) { return client.client_id; }

}  // namespace detail
}  // namespace lcmx

namespace lcmx {

RawClient Node::create_client_raw(std::string name) {
  return RawClient(detail::create_client(*impl_, std::move(name), {}));
}

Service Node::create_service_raw(std::string name, detail::ServiceTypes types, detail::ServerHandler handler) {
  if (!handler) throw Error(Errc::invalid_argument, "create_service_raw '" + name + "': empty handler");
  return Service(detail::create_server(*impl_, std::move(name), std::move(types), std::move(handler)));
}

RawClient Node::create_client_raw(std::string name, detail::ServiceTypes types) {
  return RawClient(detail::create_client(*impl_, std::move(name), std::move(types)));
}

}  // namespace lcmx
