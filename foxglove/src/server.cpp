// The Foxglove server's protocol logic (docs/foxglove.md). Pieces:
//  - Impl: the channel catalogue (from discovery beacons and the channels the runtime sees),
//    the lazy lcmx subscriptions (Route, one per LCM channel while any client subscribes to a
//    Foxglove channel of it), services, the connection graph, and the discovery thread;
//  - Client: one WebSocket client (a transport Peer): its control messages, its bounded data
//    queue (ClientQueue), its subscriptions and client-published channels.
//  - the play clock: while discovery shows an `lcmx play` clock (kPlayClockChannel), the
//    server subscribes to it, offers `time` (a new serverInfo to every client) and sends
//    `time` frames; messages without `utime` are then stamped with the log's time.
// Threads: the I/O thread runs every Client's on_text/on_binary/next_frame and the Impl calls
// they make; the node's executor threads run Route callbacks (decode, JSON, push to clients)
// and the clock's; the discovery thread runs tick(); service replies arrive on the lcmx client
// threads.
// Locks, in order: Impl::mu -> Route::mu -> Client::mu (leaf); Impl::seen_mu, Impl::probe_mu
// and Impl::clock_mu are leaves. No lcmx subscriber is destroyed while Impl::mu is held (its destruction waits for
// a running callback, which takes Route::mu and Client::mu).
#include "lcmx/foxglove/server.hpp"

#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include <atomic>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <map>
#include <mutex>
#include <optional>
#include <random>
#include <regex>
#include <set>
#include <thread>

#include "client_queue.hpp"
#include "lcmx/core.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "lcmx/types/types.hpp"
#include "lcmx_msgs/play_clock_t.hpp"
#include "lcmx_msgs/service_reply_t.hpp"
#include "lcmx_msgs/service_request_t.hpp"
#include "mapping.hpp"
#include "websocket.hpp"

namespace lcmx::foxglove {
namespace {

using detail::ViewKind;
using nlohmann::json;
using Clock = std::chrono::steady_clock;

constexpr const char* kSlowStatusId = "lcmx.slow_client";

std::uint64_t now_ns() {
  return static_cast<std::uint64_t>(
      std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch()).count());
}

void put_u32(std::string& s, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) s += static_cast<char>((v >> (8 * i)) & 0xff);
}
void put_u64(std::string& s, std::uint64_t v) {
  for (int i = 0; i < 8; ++i) s += static_cast<char>((v >> (8 * i)) & 0xff);
}
std::uint32_t get_u32(const std::uint8_t* p) {
  return std::uint32_t{p[0]} | (std::uint32_t{p[1]} << 8) | (std::uint32_t{p[2]} << 16) | (std::uint32_t{p[3]} << 24);
}

std::string hex64(std::uint64_t v) {
  char b[24];
  std::snprintf(b, sizeof b, "%016llx", static_cast<unsigned long long>(v));
  return b;
}

std::string status_json(int level, const std::string& message, const std::string& id = {}) {
  json j{{"op", "status"}, {"level", level}, {"message", message}};
  if (!id.empty()) j["id"] = id;
  return j.dump();
}

std::vector<std::regex> compile(const std::vector<std::string>& patterns, const char* what) {
  std::vector<std::regex> out;
  for (const auto& p : patterns) {
    try {
      out.emplace_back(p, std::regex::ECMAScript | std::regex::optimize);
    } catch (const std::regex_error& e) {
      throw Error(std::string(what) + " '" + p + "': bad regular expression (" + e.what() + ")");
    }
  }
  return out;
}
// A name from the network (channel, service) or an error text holding one, for the log: bytes a
// terminal could act on (controls, DEL, anything not ASCII) as \xNN, a backslash doubled (README
// "Names from the network"; apps' safe_text.hpp does the same for the verbs' own output).
std::string printable(std::string_view s) {
  std::string out;
  out.reserve(s.size());
  for (const char ch : s) {
    const auto c = static_cast<unsigned char>(ch);
    if (c == '\\') {
      out += "\\\\";
    } else if (c >= 0x20 && c < 0x7f) {
      out += ch;
    } else {
      char b[8];
      std::snprintf(b, sizeof b, "\\x%02x", c);
      out += b;
    }
  }
  return out;
}

// lcmx's own channels, never advertised.
bool reserved_channel(const std::string& ch) {
  return ch == "LCMX_BEACON" || ch == "LCMX_HISTORY" || ch == kPlayClockChannel;
}

bool any_match(const std::vector<std::regex>& rs, const std::string& s) {
  for (const auto& r : rs)
    if (std::regex_match(s, r)) return true;
  return false;
}

}  // namespace

namespace detail {

struct ChannelKey {
  std::string lcm;
  std::uint64_t fingerprint = 0;
  ViewKind view = ViewKind::none;
  auto operator<=>(const ChannelKey&) const = default;
};

struct FoxChannel {
  std::uint32_t id = 0;
  ChannelKey key;
  const types::StructType* type = nullptr;  // null: unknown type (lcmx.unknown)
  json advertised;                          // the channel object of `advertise`
};

class Client;

// A Foxglove channel with the clients subscribed to it, as a Route callback sees it.
struct Target {
  std::uint32_t channel = 0;
  std::uint64_t fingerprint = 0;
  const types::StructType* type = nullptr;
  ViewKind view = ViewKind::none;
  std::vector<std::pair<std::shared_ptr<Client>, std::uint32_t>> subs;  // client, subscription id
};

// One LCM channel subscribed in lcmx for the clients.
struct Route {
  std::string lcm;
  RawSubscriber sub;  // Impl::mu
  std::mutex mu;
  std::shared_ptr<const std::vector<Target>> targets;  // mu; replaced, never changed in place
  // The callback's own (one callback of a subscriber at a time):
  double min_interval_s = 0;
  Clock::time_point last_forward{};

  std::shared_ptr<const std::vector<Target>> snapshot() {
    std::lock_guard l(mu);
    return targets;
  }
};

struct ServiceEntry {
  std::uint32_t id = 0;
  std::string name;
  RawClient client;
  const types::StructType* request = nullptr;
  const types::StructType* response = nullptr;
  bool advertised = false;
};

struct Graph {
  std::map<std::string, std::set<std::string>> published, subscribed, services;
  bool operator==(const Graph&) const = default;
};

}  // namespace detail

using detail::ChannelKey;
using detail::ServerImpl;
using detail::Client;
using detail::FoxChannel;
using detail::Graph;
using detail::Route;
using detail::ServiceEntry;
using detail::Target;

struct detail::ServerImpl : std::enable_shared_from_this<detail::ServerImpl> {
  ServerOptions o;
  std::shared_ptr<const types::TypeRegistry> reg;
  std::vector<std::regex> allow, deny, publish_allow;
  std::vector<std::pair<std::regex, double>> rates;
  std::string session_id;

  std::optional<Runtime> rt;
  std::optional<Node> node;
  ChannelSubscription watcher;  // sees every channel name; subscribes to none
  std::vector<std::unique_ptr<discovery::Discovery>> observers;
  std::unique_ptr<detail::Listener> listener;

  mutable std::mutex mu;
  std::map<ChannelKey, std::uint32_t> ids;           // stable for the session
  std::map<std::uint32_t, FoxChannel> channels;      // advertised now
  std::map<std::string, std::shared_ptr<Route>> routes;
  std::set<std::shared_ptr<Client>> clients;
  std::map<std::string, ServiceEntry> services;
  std::uint32_t next_channel_id = 1, next_service_id = 1, next_client = 1;
  Graph graph;

  std::mutex seen_mu;
  std::set<std::string> seen;  // channel names the runtime saw (any path, stock senders too)

  std::mutex probe_mu;
  std::map<std::string, std::uint64_t> probed;  // stock / raw channels: fingerprint of a message
  std::map<std::string, RawSubscriber> probes;  // discovery thread only

  std::thread disc_thread;
  std::mutex stop_mu;
  std::condition_variable stop_cv;
  bool stopping = false;

  std::atomic<std::uint64_t> messages_in{0}, messages_out{0}, dropped{0}, rate_skipped{0}, decode_errors{0};

  // The play clock. clock_sub: the discovery thread's (made and destroyed outside mu: its
  // callback takes mu). time_active (mu): `time` is in the capabilities clients were sent.
  std::optional<Subscriber<lcmx_msgs::play_clock_t>> clock_sub;
  bool time_active = false;
  std::mutex clock_mu;
  struct ClockState {
    std::int64_t log_ns = 0;
    Clock::time_point at{};  // when log_ns was received
    double speed = 0;
    bool paused = false;
  } clock;                                // clock_mu
  std::atomic<bool> clock_valid{false};  // clock holds a value (fast path of stamp())

  explicit ServerImpl(ServerOptions opts);
  void start();
  void stop();

  bool channel_allowed(const std::string& ch) const {
    return (allow.empty() || any_match(allow, ch)) && !any_match(deny, ch);
  }
  double min_interval(const std::string& ch) const {
    for (const auto& [r, hz] : rates)
      if (std::regex_match(ch, r)) return hz > 0 ? 1.0 / hz : 0;
    return 0;
  }

  // Discovery thread.
  void run_discovery();
  void tick();
  void follow_clock(bool present);
  // Executor threads: a clock message.
  void on_clock(const lcmx_msgs::play_clock_t& m);
  // The log's time now (ns) while a clock is followed.
  std::optional<std::uint64_t> log_time_ns();
  // mu held: what a client is sent when it connects or the capabilities change.
  std::string server_info_locked(const std::string& subprotocol) const;
  void send_catalogue_locked(Client& c) const;
  // Executor threads.
  void on_message(Route& r, const RawMessage& m);

  // I/O thread (from Client).
  std::shared_ptr<detail::Peer> on_open(std::shared_ptr<detail::Connection> c);
  void subscribe(const std::shared_ptr<Client>& c, std::uint32_t sub, std::uint32_t channel);
  void unsubscribe(const std::shared_ptr<Client>& c, std::uint32_t sub);
  void client_closed(const std::shared_ptr<Client>& c);
  void rebuild_route_locked(const std::string& lcm, std::vector<RawSubscriber>& to_drop);
  void service_call(const std::shared_ptr<Client>& c, std::uint32_t service, std::uint32_t call,
                    std::string_view encoding, std::span<const std::uint8_t> payload);
  json graph_update(const Graph& from, const Graph& to, bool full) const;
};

namespace detail {

// One WebSocket client.
class Client final : public detail::Peer, public std::enable_shared_from_this<Client> {
 public:
  Client(ServerImpl& s, std::weak_ptr<detail::Connection> c, std::uint32_t id, std::string subprotocol)
      : subprotocol(std::move(subprotocol)),
        srv_(s),
        conn_(std::move(c)),
        id_(id),
        queue_(s.o.client_queue_bytes, s.o.client_queue_messages) {}

  const std::string subprotocol;

  // Any thread: the server's time is now `ns` (a `time` frame; only the latest is kept).
  void set_time(std::uint64_t ns) {
    {
      std::lock_guard l(mu_);
      if (closed_) return;
      time_ = ns;
    }
    wake();
  }

  // Any thread: a message for subscription `sub`.
  void push(std::uint32_t sub, std::uint64_t ts, const std::shared_ptr<const detail::Payload>& payload) {
    {
      std::lock_guard l(mu_);
      if (closed_ || !subs_live_.count(sub)) return;
      const auto n = queue_.push({sub, ts, payload, 0});
      srv_.messages_out.fetch_add(1, std::memory_order_relaxed);
      if (n > 0) {
        srv_.dropped.fetch_add(n, std::memory_order_relaxed);
        drops_since_status_ += n;
        const auto now = Clock::now();
        if (now - last_status_ >= srv_.o.status_period) {
          last_status_ = now;
          warned_ = true;
          control_.push_back(text(status_json(
              1,
              "lcmx foxglove: this client does not keep up: " + std::to_string(drops_since_status_) +
                  " messages dropped (oldest first, from the channels holding the most bytes; queue bound " +
                  std::to_string(queue_.max_bytes() >> 20) + " MiB / " + std::to_string(queue_.max_messages()) +
                  " messages; lowering a channel's rate or subscribing to fewer helps)",
              kSlowStatusId)));
          drops_since_status_ = 0;
        }
      }
    }
    wake();
  }
  // Any thread: a control frame (never dropped).
  void send(detail::OutFrame f) {
    {
      std::lock_guard l(mu_);
      if (closed_) return;
      control_.push_back(std::move(f));
    }
    wake();
  }
  void send_text(std::string s) { send(text(std::move(s))); }

  static detail::OutFrame text(std::string s) {
    detail::OutFrame f;
    f.text = true;
    f.head = std::move(s);
    return f;
  }

  // Subscriptions (Impl::mu held; subs_live_ is what push() checks, under mu_).
  void add_sub(std::uint32_t sub, std::uint32_t channel) {
    subs_[sub] = channel;
    std::lock_guard l(mu_);
    subs_live_.insert(sub);
  }
  std::optional<std::uint32_t> remove_sub(std::uint32_t sub) {
    auto it = subs_.find(sub);
    if (it == subs_.end()) return std::nullopt;
    const auto ch = it->second;
    subs_.erase(it);
    std::lock_guard l(mu_);
    subs_live_.erase(sub);
    queue_.erase(sub);
    return ch;
  }
  const std::map<std::uint32_t, std::uint32_t>& subs() const { return subs_; }
  bool graph_subscribed = false;  // Impl::mu
  std::uint32_t id() const { return id_; }

  // Peer
  std::optional<detail::OutFrame> next_frame() override {
    std::lock_guard l(mu_);
    if (!control_.empty()) {
      auto f = std::move(control_.front());
      control_.pop_front();
      return f;
    }
    if (time_) {
      detail::OutFrame f;
      f.text = false;
      f.head += static_cast<char>(2);
      put_u64(f.head, *time_);
      time_.reset();
      return f;
    }
    if (auto m = queue_.pop()) {
      detail::OutFrame f;
      f.text = false;
      f.head.reserve(13);
      f.head += static_cast<char>(1);
      put_u32(f.head, m->subscription);
      put_u64(f.head, m->timestamp_ns);
      f.body = std::move(m->payload);
      return f;
    }
    if (warned_) {
      warned_ = false;
      return text(json{{"op", "removeStatus"}, {"statusIds", {kSlowStatusId}}}.dump());
    }
    return std::nullopt;
  }
  void on_text(std::string_view message) override;
  void on_binary(std::span<const std::uint8_t> message) override;
  void on_close() override {
    {
      std::lock_guard l(mu_);
      closed_ = true;
      control_.clear();
    }
    srv_.client_closed(shared_from_this());
  }

  std::uint64_t queued_bytes() const {
    std::lock_guard l(mu_);
    return queue_.bytes();
  }
  ClientStats stats() const {
    ClientStats st;
    if (auto c = conn_.lock()) st.remote = c->remote();
    std::lock_guard l(mu_);
    st.queued_bytes = queue_.bytes();
    st.queued_messages = queue_.size();
    st.dropped = queue_.dropped();
    return st;
  }

  // Client-published channels (I/O thread).
  struct Publication {
    std::string topic;
    const types::StructType* type = nullptr;
    RawPublisher pub;
  };
  std::map<std::uint32_t, Publication> pubs;

 private:
  void wake() {
    if (auto c = conn_.lock()) c->wake();
  }
  void error(const std::string& m) { send_text(status_json(2, m)); }
  void handle(const json& j);

  ServerImpl& srv_;
  std::weak_ptr<detail::Connection> conn_;
  std::uint32_t id_;
  std::map<std::uint32_t, std::uint32_t> subs_;  // Impl::mu: subscription -> channel

  mutable std::mutex mu_;
  std::set<std::uint32_t> subs_live_;
  std::deque<detail::OutFrame> control_;
  std::optional<std::uint64_t> time_;  // a `time` frame to send
  detail::ClientQueue queue_;
  bool closed_ = false, warned_ = false;
  std::uint64_t drops_since_status_ = 0;
  Clock::time_point last_status_{};
};

void Client::on_text(std::string_view message) {
  json j;
  try {
    j = json::parse(message);
  } catch (const json::exception& e) {
    error(std::string("lcmx foxglove: a message that is not JSON: ") + e.what());
    return;
  }
  try {
    handle(j);
  } catch (const std::exception& e) {
    error(std::string("lcmx foxglove: ") + e.what());
  }
}

void Client::handle(const json& j) {
  const std::string op = j.value("op", "");
  auto self = shared_from_this();
  if (op == "subscribe") {
    for (const auto& s : j.at("subscriptions"))
      srv_.subscribe(self, s.at("id").get<std::uint32_t>(), s.at("channelId").get<std::uint32_t>());
  } else if (op == "unsubscribe") {
    for (const auto& id : j.at("subscriptionIds")) srv_.unsubscribe(self, id.get<std::uint32_t>());
  } else if (op == "advertise") {
    const bool enabled = srv_.o.client_publish || !srv_.publish_allow.empty();
    for (const auto& c : j.at("channels")) {
      const auto id = c.at("id").get<std::uint32_t>();
      const auto topic = c.at("topic").get<std::string>();
      const auto encoding = c.value("encoding", "");
      const auto schema_name = c.value("schemaName", "");
      if (!enabled) {
        error("lcmx foxglove: client publishing is off (start with --client-publish or --publish-allow REGEX)");
        continue;
      }
      if (!srv_.o.client_publish && !any_match(srv_.publish_allow, topic)) {
        error("lcmx foxglove: publishing on '" + topic + "' is not allowed (--publish-allow)");
        continue;
      }
      if (encoding != "json") {
        error("lcmx foxglove: '" + topic + "': encoding '" + encoding + "' not supported (json only)");
        continue;
      }
      const types::StructType* t = srv_.reg ? srv_.reg->find(std::string_view(schema_name)) : nullptr;
      if (t == nullptr) {
        error("lcmx foxglove: '" + topic + "': schema '" + schema_name +
              "' is no LCM type of the type path (give the package-qualified name, e.g. lcmx_examples.pose_t)");
        continue;
      }
      try {
        Publication p{topic, t,
                      srv_.node->advertise_raw(topic, t->full_name(), static_cast<std::int64_t>(t->fingerprint))};
        pubs.erase(id);
        pubs.emplace(id, std::move(p));
      } catch (const std::exception& e) {
        error("lcmx foxglove: cannot publish on '" + topic + "': " + e.what());
      }
    }
  } else if (op == "unadvertise") {
    for (const auto& id : j.at("channelIds")) pubs.erase(id.get<std::uint32_t>());
  } else if (op == "subscribeConnectionGraph" || op == "unsubscribeConnectionGraph") {
    const bool on = op == "subscribeConnectionGraph";
    std::lock_guard l(srv_.mu);
    graph_subscribed = on;
    if (on) send_text(srv_.graph_update(Graph{}, srv_.graph, true).dump());
  } else if (op == "getParameters" || op == "setParameters" || op == "subscribeParameterUpdates" ||
             op == "unsubscribeParameterUpdates" || op == "fetchAsset") {
    error("lcmx foxglove: '" + op + "' is not supported by this server");
  } else {
    error("lcmx foxglove: unknown op '" + op + "'");
  }
}

void Client::on_binary(std::span<const std::uint8_t> m) {
  if (m.empty()) return;
  if (m[0] == 1) {  // client message data: channel id, payload
    if (m.size() < 5) return error("lcmx foxglove: client message shorter than its header");
    const auto id = get_u32(&m[1]);
    auto it = pubs.find(id);
    if (it == pubs.end()) return error("lcmx foxglove: client message on unknown channel " + std::to_string(id));
    try {
      const auto v = detail::from_foxglove_json(
          *it->second.type, std::string_view(reinterpret_cast<const char*>(m.data() + 5), m.size() - 5));
      const auto bytes = types::encode(*it->second.type, v);
      it->second.pub.publish(std::span<const std::byte>(reinterpret_cast<const std::byte*>(bytes.data()), bytes.size()));
    } catch (const std::exception& e) {
      error("lcmx foxglove: publish on '" + it->second.topic + "': " + e.what());
    }
  } else if (m[0] == 2) {  // service call request
    if (m.size() < 13) return error("lcmx foxglove: service call shorter than its header");
    const auto service = get_u32(&m[1]), call = get_u32(&m[5]), enc_len = get_u32(&m[9]);
    if (m.size() < 13 + std::size_t{enc_len}) return error("lcmx foxglove: service call: bad encoding length");
    srv_.service_call(shared_from_this(), service, call,
                      std::string_view(reinterpret_cast<const char*>(m.data() + 13), enc_len), m.subspan(13 + enc_len));
  } else {
    error("lcmx foxglove: unknown binary opcode " + std::to_string(m[0]));
  }
}

}  // namespace detail

namespace {
json service_json(const ServiceEntry& e) {
  auto def = [](const types::StructType* t) {
    return json{{"encoding", "json"}, {"schemaName", t->full_name()}, {"schemaEncoding", "jsonschema"},
                {"schema", detail::json_schema(*t)}};
  };
  return {{"id", e.id},
          {"name", e.name},
          {"type", e.request->full_name() + " -> " + e.response->full_name()},
          {"request", def(e.request)},
          {"response", def(e.response)},
          {"requestSchema", detail::json_schema(*e.request)},
          {"responseSchema", detail::json_schema(*e.response)}};
}
}  // namespace

// ---- Impl ----

ServerImpl::ServerImpl(ServerOptions opts) : o(std::move(opts)) {
  reg = o.registry ? o.registry : std::make_shared<const types::TypeRegistry>();
  allow = compile(o.channels, "--channel");
  deny = compile(o.exclude, "--exclude");
  publish_allow = compile(o.publish_allow, "--publish-allow");
  for (const auto& r : o.rate_limits) {
    if (!(r.max_hz > 0)) throw Error("rate limit must be > 0 Hz");
    rates.emplace_back(compile({r.pattern.empty() ? std::string(".*") : r.pattern}, "--max-rate").front(), r.max_hz);
  }
  std::random_device rd;
  session_id = hex64((std::uint64_t{rd()} << 32) | rd());
}

void ServerImpl::start() {
  rt.emplace(Runtime::create(o.runtime));
  NodeOptions no;
  no.executor.threads = std::max(1, o.executor_threads);
  node.emplace(rt->create_node("lcmx_foxglove", no));
  std::weak_ptr<ServerImpl> weak = shared_from_this();
  // Every channel name the runtime sees (lcmx publishers in beacons, stock senders' datagrams),
  // refused: nothing is subscribed here. The filter runs under the runtime's lock: a set insert only.
  watcher = node->subscribe_channels(
      [this](const std::string& ch) {
        std::lock_guard l(seen_mu);
        if (seen.size() < 100000) seen.insert(ch);
        return false;
      },
      [](const RawMessage&) {});
  for (const bool vehicle : {false, true}) {
    const auto& u = vehicle ? o.runtime.vehicle_url : o.runtime.discovery_url;
    if (u.empty()) continue;
    discovery::Options d;
    d.group = udpm::parse_url(u);
    d.observer = true;
    // The vehicle group's observer is of the vehicle scope: no registry of its own (a host-scope
    // one would open a registry for the vehicle group and take this host's speaker for a twin),
    // as the tools' (apps/lcmx/tools_common.hpp).
    d.scope = vehicle ? lcmx_msgs::beacon_t::SCOPE_VEHICLE : lcmx_msgs::beacon_t::SCOPE_HOST;
    observers.push_back(std::make_unique<discovery::Discovery>(d, nullptr, nullptr));
  }
  for (auto& d : observers) d->query();
  detail::ListenOptions lo;
  lo.address = o.address;
  lo.port = o.port;
  lo.tls_cert = o.tls_cert;
  lo.tls_key = o.tls_key;
  lo.subprotocols = {"foxglove.sdk.v1", "foxglove.websocket.v1"};
  lo.server_name = "lcmx-foxglove";
  try {
    listener = std::make_unique<detail::Listener>(lo, [weak](std::shared_ptr<detail::Connection> c) {
      auto self = weak.lock();
      return self ? self->on_open(std::move(c)) : nullptr;
    });
  } catch (const std::runtime_error& e) {
    throw Error(e.what());
  }
  tick();
  disc_thread = std::thread([this] { run_discovery(); });
}

void ServerImpl::stop() {
  {
    std::lock_guard l(stop_mu);
    stopping = true;
  }
  stop_cv.notify_all();
  if (disc_thread.joinable()) disc_thread.join();
  // lcmx first (its callbacks push to clients), then the sockets, then lcmx itself.
  std::vector<RawSubscriber> subs;
  std::map<std::string, ServiceEntry> svc;
  std::set<std::shared_ptr<Client>> cl;
  {
    std::lock_guard l(mu);
    for (auto& [_, r] : routes) subs.push_back(std::move(r->sub));
    routes.clear();
    svc.swap(services);
    cl.swap(clients);
  }
  subs.clear();
  svc.clear();
  probes.clear();
  clock_sub.reset();
  watcher.reset();
  listener.reset();  // no Client call on the I/O thread after this
  for (auto& c : cl) c->pubs.clear();
  cl.clear();
  observers.clear();
  node.reset();
  rt.reset();
}

void ServerImpl::run_discovery() {
  std::unique_lock l(stop_mu);
  while (!stopping) {
    stop_cv.wait_for(l, o.discovery_period, [this] { return stopping; });
    if (stopping) break;
    l.unlock();
    try {
      tick();
    } catch (const std::exception& e) {
      spdlog::warn("lcmx foxglove: discovery: {}", printable(e.what()));
    }
    l.lock();
  }
}

json ServerImpl::graph_update(const Graph& from, const Graph& to, bool full) const {
  json pub = json::array(), sub = json::array(), svc = json::array(), rmt = json::array(), rms = json::array();
  auto add = [&](json& out, const std::map<std::string, std::set<std::string>>& a,
                 const std::map<std::string, std::set<std::string>>& b, const char* ids) {
    for (const auto& [name, set] : b) {
      auto it = a.find(name);
      if (full || it == a.end() || it->second != set) out.push_back({{"name", name}, {ids, set}});
    }
  };
  add(pub, from.published, to.published, "publisherIds");
  add(sub, from.subscribed, to.subscribed, "subscriberIds");
  add(svc, from.services, to.services, "providerIds");
  std::set<std::string> old_topics, new_topics;
  for (const auto* m : {&from.published, &from.subscribed})
    for (const auto& [n, _] : *m) old_topics.insert(n);
  for (const auto* m : {&to.published, &to.subscribed})
    for (const auto& [n, _] : *m) new_topics.insert(n);
  for (const auto& n : old_topics)
    if (!new_topics.count(n)) rmt.push_back(n);
  for (const auto& [n, _] : from.services)
    if (!to.services.count(n)) rms.push_back(n);
  return {{"op", "connectionGraphUpdate"}, {"publishedTopics", pub}, {"subscribedTopics", sub},
          {"advertisedServices", svc}, {"removedTopics", rmt}, {"removedServices", rms}};
}

void ServerImpl::tick() {
  const std::int64_t self_id = static_cast<std::int64_t>(rt->participant_id());
  std::vector<discovery::Participant> ps;
  {
    std::set<std::int64_t> dup;
    for (auto& d : observers)
      for (auto& p : d->participants())
        if (p.beacon.participant_id != self_id && dup.insert(p.beacon.participant_id).second) ps.push_back(std::move(p));
  }
  const auto rq_fp = lcmx_msgs::service_request_t::getHash();
  const auto rp_fp = lcmx_msgs::service_reply_t::getHash();

  // Channels with lcmx publishers (by fingerprint), services, the graph.
  std::map<std::string, std::set<std::uint64_t>> pubs;
  std::set<std::string> service_names;
  Graph g;
  for (const auto& p : ps) {
    const auto& b = p.beacon;
    const std::string who = b.process_name + "[" + std::to_string(b.pid) + "]@" + hex64(static_cast<std::uint64_t>(b.host_id)).substr(8);
    for (const auto& e : b.endpoints) {
      if (e.topic == "LCMX_BEACON") continue;
      const std::string id = who + "/" + e.node;
      if (e.fingerprint == rq_fp) {
        const std::string suffix = "/rq";
        if (e.kind == lcmx_msgs::endpoint_t::KIND_SUBSCRIBER && e.topic.size() > suffix.size() &&
            e.topic.compare(e.topic.size() - suffix.size(), suffix.size(), suffix) == 0) {
          const auto name = e.topic.substr(0, e.topic.size() - suffix.size());
          service_names.insert(name);
          g.services[name].insert(id);
        }
        continue;
      }
      if (e.fingerprint == rp_fp) continue;
      if (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER) {
        pubs[e.topic].insert(static_cast<std::uint64_t>(e.fingerprint));
        g.published[e.topic].insert(id);
      } else {
        g.subscribed[e.topic].insert(id);
      }
    }
  }

  // Channels without a typed lcmx publisher (stock LCM senders, raw publishers): one message
  // tells their fingerprint (a probe subscription, dropped once it has it).
  std::set<std::string> candidates;
  {
    std::lock_guard l(seen_mu);
    candidates = seen;
  }
  for (const auto& [ch, fps] : pubs)
    if (fps.count(0)) candidates.insert(ch);
  std::map<std::string, std::uint64_t> probed_now;
  {
    std::lock_guard l(probe_mu);
    probed_now = probed;
  }
  std::vector<RawSubscriber> done_probes;
  for (const auto& ch : candidates) {
    if (reserved_channel(ch) || !channel_allowed(ch)) continue;
    auto it = pubs.find(ch);
    const bool typed = it != pubs.end() && std::any_of(it->second.begin(), it->second.end(), [](auto f) { return f != 0; });
    if (typed) continue;
    if (auto p = probed_now.find(ch); p != probed_now.end()) {
      auto& set = pubs[ch];
      set.erase(0);
      set.insert(p->second);
      if (auto pr = probes.find(ch); pr != probes.end()) {
        done_probes.push_back(std::move(pr->second));
        probes.erase(pr);
      }
      continue;
    }
    if (probes.count(ch) || probes.size() >= 64) continue;
    // A service's reply channel or request channel of a stock peer is no channel to show.
    if (ch.size() > 3 && (ch.compare(ch.size() - 3, 3, "/rq") == 0 || ch.find("/rp/") != std::string::npos)) continue;
    try {
      probes.emplace(ch, node->subscribe_raw(ch, [this, ch](const RawMessage& m) {
        const auto fp = types::message_fingerprint(m.data.data(), m.data.size());
        std::lock_guard l(probe_mu);
        probed.emplace(ch, fp.value_or(0));
      }));
    } catch (const std::exception& e) {
      spdlog::warn("lcmx foxglove: cannot probe channel '{}': {}", printable(ch), printable(e.what()));
    }
  }
  for (auto& [ch, fps] : pubs) fps.erase(0);
  done_probes.clear();

  // The wanted Foxglove channels.
  std::map<ChannelKey, const types::StructType*> want;
  for (const auto& [ch, fps] : pubs) {
    if (reserved_channel(ch) || !channel_allowed(ch)) continue;
    for (auto fp : fps) {
      const types::StructType* t = reg->find(fp);
      want[{ch, fp, ViewKind::none}] = t;
      if (t != nullptr)
        if (const auto v = detail::view_of(*t); v.kind != ViewKind::none) want[{ch, fp, v.kind}] = t;
    }
  }

  // Services: a client each (it probes the servers for their types); advertised once typed.
  std::vector<RawClient> gone_clients;
  std::vector<std::pair<std::shared_ptr<Client>, std::string>> out;  // sent after the lock
  std::vector<RawSubscriber> to_drop;
  {
    std::lock_guard l(mu);
    json adv = json::array(), unadv = json::array(), sadv = json::array(), sunadv = json::array();
    for (auto it = channels.begin(); it != channels.end();) {
      if (!want.count(it->second.key)) {
        unadv.push_back(it->first);
        const std::string lcm = it->second.key.lcm;
        const auto id = it->first;
        for (const auto& c : clients) {
          std::vector<std::uint32_t> drop;
          for (const auto& [s, ch] : c->subs())
            if (ch == id) drop.push_back(s);
          for (auto s : drop) c->remove_sub(s);
        }
        it = channels.erase(it);
        rebuild_route_locked(lcm, to_drop);
      } else {
        ++it;
      }
    }
    for (const auto& [key, t] : want) {
      auto [idit, fresh] = ids.emplace(key, next_channel_id);
      if (fresh) ++next_channel_id;
      if (channels.count(idit->second)) continue;
      FoxChannel fc;
      fc.id = idit->second;
      fc.key = key;
      fc.type = t;
      std::string topic = key.lcm, schema_name, schema;
      if (t == nullptr) {
        schema_name = detail::kUnknownSchemaName;
        schema = detail::unknown_schema();
      } else if (key.view == ViewKind::none) {
        schema_name = t->full_name();
        schema = detail::json_schema(*t);
      } else {
        const auto v = detail::view_of(*t);
        topic += v.topic_suffix;
        schema_name = v.schema_name;
        schema = detail::view_schema(key.view);
      }
      fc.advertised = {{"id", fc.id},         {"topic", topic},   {"encoding", "json"},
                       {"schemaName", schema_name}, {"schema", schema}, {"schemaEncoding", "jsonschema"}};
      adv.push_back(fc.advertised);
      channels.emplace(fc.id, std::move(fc));
    }

    if (o.services) {
      for (auto it = services.begin(); it != services.end();) {
        if (!service_names.count(it->first)) {
          if (it->second.advertised) sunadv.push_back(it->second.id);
          gone_clients.push_back(std::move(it->second.client));
          it = services.erase(it);
        } else {
          ++it;
        }
      }
      for (const auto& name : service_names) {
        auto it = services.find(name);
        if (it == services.end()) {
          try {
            ServiceEntry e;
            e.id = next_service_id++;
            e.name = name;
            e.client = node->create_client_raw(name);
            it = services.emplace(name, std::move(e)).first;
          } catch (const std::exception& ex) {
            spdlog::warn("lcmx foxglove: service '{}': {}", printable(name), printable(ex.what()));
            continue;
          }
        }
        auto& e = it->second;
        if (e.advertised) continue;
        const auto servers = e.client.servers();
        if (servers.empty()) continue;
        e.request = reg->find(static_cast<std::uint64_t>(servers.front().request_fingerprint));
        e.response = reg->find(static_cast<std::uint64_t>(servers.front().response_fingerprint));
        if (e.request == nullptr || e.response == nullptr) continue;  // raw or not in the type path
        e.advertised = true;
        sadv.push_back(service_json(e));
      }
    }

    const bool graph_changed = !(g == graph);
    json gu;
    if (graph_changed) gu = graph_update(graph, g, false);
    graph = std::move(g);
    for (const auto& c : clients) {
      if (!unadv.empty()) out.emplace_back(c, json{{"op", "unadvertise"}, {"channelIds", unadv}}.dump());
      if (!adv.empty()) out.emplace_back(c, json{{"op", "advertise"}, {"channels", adv}}.dump());
      if (!sunadv.empty()) out.emplace_back(c, json{{"op", "unadvertiseServices"}, {"serviceIds", sunadv}}.dump());
      if (!sadv.empty()) out.emplace_back(c, json{{"op", "advertiseServices"}, {"services", sadv}}.dump());
      if (graph_changed && c->graph_subscribed) out.emplace_back(c, gu.dump());
    }
  }
  for (auto& [c, s] : out) c->send_text(std::move(s));
  to_drop.clear();
  gone_clients.clear();
  follow_clock(pubs.count(kPlayClockChannel) > 0);
}

// Discovery thread: subscribes to the play clock while a publisher of it is there; when it
// goes, `time` is withdrawn (a new serverInfo to every client).
void ServerImpl::follow_clock(bool present) {
  if (present == clock_sub.has_value()) return;
  if (present) {
    std::weak_ptr<ServerImpl> weak = shared_from_this();
    try {
      clock_sub.emplace(node->subscribe<lcmx_msgs::play_clock_t>(
          kPlayClockChannel, [weak](const lcmx_msgs::play_clock_t& m) {
            if (auto self = weak.lock()) self->on_clock(m);
          }));
    } catch (const std::exception& e) {
      spdlog::warn("lcmx foxglove: cannot follow the play clock: {}", e.what());
    }
    return;
  }
  clock_sub.reset();  // outside mu: its callback takes mu
  clock_valid = false;
  std::lock_guard l(mu);
  if (!time_active) return;
  time_active = false;
  for (const auto& c : clients) {
    c->send_text(server_info_locked(c->subprotocol));
    send_catalogue_locked(*c);
  }
  spdlog::info("lcmx foxglove: the play clock is gone: time is the receive time again");
}

void ServerImpl::on_clock(const lcmx_msgs::play_clock_t& m) {
  if (m.log_utime <= 0) return;
  {
    std::lock_guard l(clock_mu);
    clock = {m.log_utime * 1000, Clock::now(), m.speed, m.paused != 0};
  }
  clock_valid = true;
  std::lock_guard l(mu);
  if (!time_active) {
    // Clients learn the capability from a new serverInfo (same session: they keep their
    // subscriptions); the channels follow it, since a serverInfo resets a client's types.
    time_active = true;
    for (const auto& c : clients) {
      c->send_text(server_info_locked(c->subprotocol));
      send_catalogue_locked(*c);
    }
    spdlog::info("lcmx foxglove: following the play clock (time capability)");
  }
  const auto ns = static_cast<std::uint64_t>(m.log_utime) * 1000;
  for (const auto& c : clients) c->set_time(ns);
}

std::optional<std::uint64_t> ServerImpl::log_time_ns() {
  if (!clock_valid.load(std::memory_order_acquire)) return std::nullopt;
  std::lock_guard l(clock_mu);
  std::int64_t t = clock.log_ns;
  if (!clock.paused && clock.speed > 0)
    t += static_cast<std::int64_t>(std::chrono::duration<double, std::nano>(Clock::now() - clock.at).count() *
                                   clock.speed);
  return static_cast<std::uint64_t>(t);
}

std::string ServerImpl::server_info_locked(const std::string& subprotocol) const {
  json caps = json::array({"connectionGraph"});
  if (o.client_publish || !publish_allow.empty()) caps.push_back("clientPublish");
  if (o.services) caps.push_back("services");
  if (time_active) caps.push_back("time");
  return json{{"op", "serverInfo"},
              {"name", o.name},
              {"capabilities", caps},
              {"supportedEncodings", json::array({"json"})},
              {"metadata", {{"lcmx", "lcmx foxglove"}, {"subprotocol", subprotocol}}},
              {"sessionId", session_id}}
      .dump();
}


void ServerImpl::send_catalogue_locked(Client& c) const {
  json adv = json::array();
  for (const auto& [_, ch] : channels) adv.push_back(ch.advertised);
  if (!adv.empty()) c.send_text(json{{"op", "advertise"}, {"channels", adv}}.dump());
  json sadv = json::array();
  for (const auto& [name, e] : services)
    if (e.advertised) sadv.push_back(service_json(e));
  if (!sadv.empty()) c.send_text(json{{"op", "advertiseServices"}, {"services", sadv}}.dump());
}

std::shared_ptr<detail::Peer> ServerImpl::on_open(std::shared_ptr<detail::Connection> conn) {
  std::lock_guard l(mu);
  auto c = std::make_shared<Client>(*this, conn, next_client++, conn->subprotocol());
  c->send_text(server_info_locked(c->subprotocol));
  send_catalogue_locked(*c);
  if (time_active)
    if (const auto t = log_time_ns()) c->set_time(*t);
  clients.insert(c);
  spdlog::info("lcmx foxglove: client {} connected from {} ({})", c->id(), conn->remote(), conn->subprotocol());
  return c;
}

// Rebuilds the Route of `lcm` from the clients' subscriptions; a Route without any is removed
// (its subscriber moved to `to_drop`, destroyed by the caller after the lock).
void ServerImpl::rebuild_route_locked(const std::string& lcm, std::vector<RawSubscriber>& to_drop) {
  auto targets = std::make_shared<std::vector<Target>>();
  std::map<std::uint32_t, std::size_t> at;
  for (const auto& c : clients) {
    for (const auto& [sub, chid] : c->subs()) {
      auto ch = channels.find(chid);
      if (ch == channels.end() || ch->second.key.lcm != lcm) continue;
      auto [it, fresh] = at.emplace(chid, targets->size());
      if (fresh)
        targets->push_back({chid, ch->second.key.fingerprint, ch->second.type, ch->second.key.view, {}});
      (*targets)[it->second].subs.emplace_back(c, sub);
    }
  }
  auto rit = routes.find(lcm);
  if (targets->empty()) {
    if (rit != routes.end()) {
      {
        std::lock_guard rl(rit->second->mu);
        rit->second->targets = targets;
      }
      to_drop.push_back(std::move(rit->second->sub));
      routes.erase(rit);
    }
    return;
  }
  if (rit == routes.end()) {
    auto r = std::make_shared<Route>();
    r->lcm = lcm;
    r->min_interval_s = min_interval(lcm);
    r->targets = targets;
    std::weak_ptr<Route> wr = r;
    r->sub = node->subscribe_raw(lcm, [this, wr](const RawMessage& m) {
      if (auto rr = wr.lock()) on_message(*rr, m);
    });
    routes.emplace(lcm, std::move(r));
    return;
  }
  std::lock_guard rl(rit->second->mu);
  rit->second->targets = targets;
}

void ServerImpl::subscribe(const std::shared_ptr<Client>& c, std::uint32_t sub, std::uint32_t channel) {
  std::vector<RawSubscriber> to_drop;
  std::string err;
  {
    std::lock_guard l(mu);
    auto ch = channels.find(channel);
    if (ch == channels.end()) {
      err = "lcmx foxglove: subscribe: no channel " + std::to_string(channel);
    } else if (c->subs().count(sub)) {
      err = "lcmx foxglove: subscribe: subscription id " + std::to_string(sub) + " is in use";
    } else {
      c->add_sub(sub, channel);
      try {
        rebuild_route_locked(ch->second.key.lcm, to_drop);
      } catch (const std::exception& e) {
        c->remove_sub(sub);
        err = "lcmx foxglove: cannot subscribe to '" + ch->second.key.lcm + "': " + e.what();
      }
    }
  }
  if (!err.empty()) c->send_text(status_json(2, err));
}

void ServerImpl::unsubscribe(const std::shared_ptr<Client>& c, std::uint32_t sub) {
  std::vector<RawSubscriber> to_drop;
  {
    std::lock_guard l(mu);
    const auto ch = c->remove_sub(sub);
    if (!ch) return;
    if (auto it = channels.find(*ch); it != channels.end()) rebuild_route_locked(it->second.key.lcm, to_drop);
  }
}

void ServerImpl::client_closed(const std::shared_ptr<Client>& c) {
  std::vector<RawSubscriber> to_drop;
  {
    std::lock_guard l(mu);
    std::set<std::string> lcms;
    std::vector<std::uint32_t> subs;
    for (const auto& [s, ch] : c->subs()) {
      subs.push_back(s);
      if (auto it = channels.find(ch); it != channels.end()) lcms.insert(it->second.key.lcm);
    }
    for (auto s : subs) c->remove_sub(s);
    clients.erase(c);
    for (const auto& lcm : lcms) rebuild_route_locked(lcm, to_drop);
  }
  c->pubs.clear();
  spdlog::info("lcmx foxglove: client {} disconnected", c->id());
}

void ServerImpl::on_message(Route& r, const RawMessage& m) {
  messages_in.fetch_add(1, std::memory_order_relaxed);
  if (r.min_interval_s > 0) {
    const auto now = Clock::now();
    if (r.last_forward.time_since_epoch().count() != 0 &&
        std::chrono::duration<double>(now - r.last_forward).count() < r.min_interval_s) {
      rate_skipped.fetch_add(1, std::memory_order_relaxed);
      return;
    }
    r.last_forward = now;
  }
  const auto targets = r.snapshot();
  if (!targets) return;
  const auto* data = reinterpret_cast<const std::uint8_t*>(m.data.data());
  const auto fp = types::message_fingerprint(data, m.data.size()).value_or(0);
  // The receive time, on the log's clock while `lcmx play` runs one.
  const std::uint64_t received = log_time_ns().value_or(now_ns());
  std::optional<types::Value> value;
  detail::Base64Cache b64;  // a large byte array is encoded once for the struct and its view
  bool failed = false;
  for (const auto& t : *targets) {
    if (t.fingerprint != fp || t.subs.empty()) continue;
    std::shared_ptr<const detail::Payload> payload;
    std::uint64_t ts = received;
    if (t.type == nullptr) {
      payload = detail::Payload::of(detail::unknown_json(fp, data, m.data.size()));
    } else {
      if (!value && !failed) {
        try {
          value = types::decode(*t.type, data, m.data.size());
        } catch (const std::exception& e) {
          failed = true;
          if (decode_errors.fetch_add(1) % 1000 == 0)
            spdlog::warn("lcmx foxglove: channel '{}': a message did not decode as {}: {}", printable(r.lcm),
                         printable(t.type->full_name()), printable(e.what()));
        }
      }
      if (!value) continue;
      if (auto u = detail::utime_ns(*value)) ts = *u;
      if (t.view == ViewKind::none) {
        payload = std::make_shared<const detail::Payload>(detail::to_json(*value, b64));
      } else {
        auto j = detail::to_view_json(t.view, *value, ts, b64);
        if (!j) continue;
        payload = std::make_shared<const detail::Payload>(std::move(*j));
      }
    }
    for (const auto& [c, sub] : t.subs) c->push(sub, ts, payload);
  }
}

void ServerImpl::service_call(const std::shared_ptr<Client>& c, std::uint32_t service, std::uint32_t call,
                                std::string_view encoding, std::span<const std::uint8_t> payload) {
  auto fail = [&](const std::string& why) {
    c->send_text(json{{"op", "serviceCallFailure"}, {"serviceId", service}, {"callId", call}, {"message", why}}.dump());
  };
  if (!o.services) return fail("services are off (--no-services)");
  if (encoding != "json") return fail("encoding '" + std::string(encoding) + "' not supported (json only)");
  std::lock_guard l(mu);
  ServiceEntry* e = nullptr;
  for (auto& [_, s] : services)
    if (s.id == service && s.advertised) e = &s;
  if (e == nullptr) return fail("no service " + std::to_string(service));
  std::vector<std::uint8_t> bytes;
  try {
    bytes = types::encode(*e->request, detail::from_foxglove_json(
                                           *e->request, std::string_view(reinterpret_cast<const char*>(payload.data()),
                                                                         payload.size())));
  } catch (const std::exception& ex) {
    return fail(ex.what());
  }
  const types::StructType* resp = e->response;
  std::weak_ptr<Client> wc = c;
  e->client.call_async(
      std::span<const std::byte>(reinterpret_cast<const std::byte*>(bytes.data()), bytes.size()), o.service_timeout,
      [wc, resp, service, call](RawClient::Result r) {
        auto cl = wc.lock();
        if (!cl) return;
        if (!r.ok()) {
          cl->send_text(json{{"op", "serviceCallFailure"},
                             {"serviceId", service},
                             {"callId", call},
                             {"message", std::string(to_string(r.error())) + ": " + r.message()}}
                            .dump());
          return;
        }
        std::string body;
        try {
          const auto& b = r.value();
          body = detail::to_json(types::decode(*resp, b.data(), b.size()));
        } catch (const std::exception& ex) {
          cl->send_text(json{{"op", "serviceCallFailure"},
                             {"serviceId", service},
                             {"callId", call},
                             {"message", std::string("the response did not decode: ") + ex.what()}}
                            .dump());
          return;
        }
        detail::OutFrame f;
        f.text = false;
        f.head += static_cast<char>(3);
        put_u32(f.head, service);
        put_u32(f.head, call);
        put_u32(f.head, 4);
        f.head += "json";
        f.body = detail::Payload::of(std::move(body));
        cl->send(std::move(f));
      });
}

// ---- Server ----

Server::Server(ServerOptions options) : impl_(std::make_shared<detail::ServerImpl>(std::move(options))) {
  try {
    impl_->start();
  } catch (...) {
    impl_->stop();
    throw;
  }
}

Server::~Server() { impl_->stop(); }

std::uint16_t Server::port() const { return impl_->listener ? impl_->listener->port() : 0; }

ServerStats Server::stats() const {
  ServerStats s;
  {
    std::lock_guard l(impl_->mu);
    s.clients = impl_->clients.size();
    s.channels = impl_->channels.size();
    s.lcm_subscriptions = impl_->routes.size();
    for (const auto& c : impl_->clients) {
      s.per_client.push_back(c->stats());
      s.max_client_queue_bytes = std::max(s.max_client_queue_bytes, s.per_client.back().queued_bytes);
    }
  }
  s.messages_in = impl_->messages_in.load();
  s.messages_out = impl_->messages_out.load();
  s.dropped = impl_->dropped.load();
  s.rate_skipped = impl_->rate_skipped.load();
  s.decode_errors = impl_->decode_errors.load();
  s.time = impl_->clock_valid.load();
  return s;
}

}  // namespace lcmx::foxglove
