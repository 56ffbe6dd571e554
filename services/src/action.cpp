// Actions (lcmx/services/action.hpp, docs/actions.md): three services and two topics per action,
// envelopes from lcmtypes/action.lcm (lcm-gen structs, encoded by lcm-gen's code and decoded
// by lcmx::lcmtypes' checked decoders: every count bounded before anything is sized; actions
// are not on a hot path that would need the in-place encoding of service.cpp).
// Trust: a client takes a goal's status and feedback only from the server its goal went to
// (the envelope's server and the participant of the pair it came through, sender.hpp).
//
// Server: the goal, cancel and result services run on the user's node; a thread of the
// server's own publishes the status (on change and every status_period), checks whether each
// live goal's client is still there (client_timeout) and forgets ended goals
// (result_retention); each accepted goal's execute runs on a thread of its own.
// Client: a goal, a cancel and a result service client, and a manual node of its own run by
// one thread for the status and feedback subscriptions.
#include "lcmx/services/action.hpp"

#include <algorithm>
#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <random>
#include <thread>

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include "lcmx/core/detail/service_hook.hpp"
#include "lcmx/core/node.hpp"
#include "lcmx/lcmtypes/envelope.hpp"
#include "sender.hpp"
#include "lcmx_msgs/action_feedback_t.hpp"
#include "lcmx_msgs/action_goal_ref_t.hpp"
#include "lcmx_msgs/action_goal_reply_t.hpp"
#include "lcmx_msgs/action_goal_status_t.hpp"
#include "lcmx_msgs/action_goal_t.hpp"
#include "lcmx_msgs/action_result_t.hpp"
#include "lcmx_msgs/action_status_t.hpp"

namespace lcmx {

const char* to_string(GoalState s) {
  switch (s) {
    case GoalState::unknown: return "unknown";
    case GoalState::accepted: return "accepted";
    case GoalState::executing: return "executing";
    case GoalState::canceling: return "canceling";
    case GoalState::succeeded: return "succeeded";
    case GoalState::aborted: return "aborted";
    case GoalState::canceled: return "canceled";
    case GoalState::rejected: return "rejected";
    case GoalState::lost: return "lost";
  }
  return "?";
}

namespace detail {
namespace {

using Clock = std::chrono::steady_clock;
using ms = std::chrono::milliseconds;

constexpr std::size_t kMaxActionName = 36;  // "NAME/cancel/rp/<16 hex>" fits LCM's 63 bytes
constexpr std::size_t kMaxListed = 256;     // goals in one status message

std::string goal_channel(const std::string& n) { return n + "/goal"; }
std::string cancel_channel(const std::string& n) { return n + "/cancel"; }
std::string result_channel(const std::string& n) { return n + "/result"; }
std::string feedback_channel(const std::string& n) { return n + "/feedback"; }
std::string status_channel(const std::string& n) { return n + "/status"; }

void check_action_name(const std::string& name, const char* what) {
  if (name.empty() || name.size() > kMaxActionName)
    throw Error(Errc::invalid_argument,
                fmt::format("{} '{}': an action name has 1 to {} bytes", what, name, kMaxActionName));
}

std::string new_goal_id() {
  static std::mutex mu;
  static std::mt19937_64 rng{std::random_device{}() ^
                             static_cast<std::uint64_t>(Clock::now().time_since_epoch().count())};
  std::lock_guard lock(mu);
  return fmt::format("{:016x}{:016x}", rng(), rng());
}

template <class T>
Bytes encode(const T& m) {
  Bytes b(static_cast<std::size_t>(m.getEncodedSize()));
  m.encode(b.data(), 0, static_cast<int>(b.size()));
  return b;
}
template <class T>
bool decode(std::span<const std::byte> b, T& m) {
  return lcmtypes::decode(b, m);
}
std::span<const std::byte> as_bytes(const std::vector<std::uint8_t>& v) {
  return {reinterpret_cast<const std::byte*>(v.data()), v.size()};
}
// The three services' envelope types (request, reply), the same at servers and clients.
template <class Req, class Rep>
ServiceTypes service_types() {
  return {Req::getTypeName(), Rep::getTypeName(), Req::getHash(), Rep::getHash()};
}

// The envelopes travel as bytes (encoded here), announcing their type: tools decode them.
template <class T>
const TypeInfo& envelope_type() {
  return announced_type_info(T::getTypeName(), T::getHash());
}
std::vector<std::uint8_t> to_u8(std::span<const std::byte> b) {
  const auto* p = reinterpret_cast<const std::uint8_t*>(b.data());
  return {p, p + b.size()};
}
bool compatible(std::int64_t a, std::int64_t b) { return a == 0 || b == 0 || a == b; }
std::string type_text(const std::string& name, std::int64_t fp) {
  return fp == 0 ? std::string("raw bytes") : fmt::format("{} ({:016x})", name, static_cast<std::uint64_t>(fp));
}

GoalState state_of(std::int8_t s) {
  return s >= 0 && s <= 7 ? static_cast<GoalState>(s) : GoalState::unknown;
}
// Status messages and replies may arrive out of order: a goal's state only moves forward.
int rank(GoalState s) {
  switch (s) {
    case GoalState::unknown: return 0;
    case GoalState::accepted: return 1;
    case GoalState::executing: return 2;
    case GoalState::canceling: return 3;
    default: return 4;  // ended
  }
}

lcmx_msgs::action_goal_status_t to_msg(const GoalStatus& s, std::int32_t feedback_count = 0) {
  lcmx_msgs::action_goal_status_t m;
  m.goal_id = s.goal_id;
  m.state = static_cast<std::int8_t>(s.state == GoalState::lost ? GoalState::unknown : s.state);
  m.message = s.message;
  m.feedback_count = feedback_count;
  return m;
}
GoalStatus from_msg(const lcmx_msgs::action_goal_status_t& m) {
  return {m.goal_id, state_of(m.state), m.message};
}

}  // namespace

// --- Server ------------------------------------------------------------------------------------

class ActionServerCore : public std::enable_shared_from_this<ActionServerCore> {
 public:
  ActionServerCore(std::shared_ptr<NodeImpl> n, std::string nm, ActionTypes t, GoalAcceptor a, GoalExecutor e,
                   ActionServerOptions o)
      : node(std::move(n)), name(std::move(nm)), types(std::move(t)), accept(std::move(a)), execute(std::move(e)),
        options(o) {}

  void start();
  void close();
  ActionServerStats stats() const {
    std::lock_guard lock(mu);
    ActionServerStats s = counters;
    for (const auto& [id, g] : goals) s.executing += is_terminal(g->status.state) ? 0 : 1;
    return s;
  }
  std::vector<GoalStatus> list() const;
  // The goals as announced (live first, then ended ones, most recent first).
  std::vector<lcmx_msgs::action_goal_status_t> announced() const;

  const std::shared_ptr<NodeImpl> node;
  const std::string name;
  const ActionTypes types;
  const GoalAcceptor accept;
  const GoalExecutor execute;
  const ActionServerOptions options;

 private:
  class Goal final : public RawActionGoal {
   public:
    Goal(ActionServerCore& s, std::string goal_id, std::uint64_t client, Bytes g)
        : server(s), client_id(client), bytes(std::move(g)) {
      status.goal_id = std::move(goal_id);
      status.state = GoalState::accepted;
    }
    const std::string& id() const override { return status.goal_id; }
    std::span<const std::byte> goal() const override { return bytes; }
    bool cancel_requested() const override { return cancel.load(); }
    bool wait_for_cancel(std::chrono::nanoseconds timeout) const override {
      std::unique_lock lock(server.mu);
      return server.goal_cv.wait_for(lock, timeout, [this] { return cancel.load(); });
    }
    void publish_feedback(std::span<const std::byte> feedback) override {
      lcmx_msgs::action_feedback_t m;
      m.goal_id = status.goal_id;
      m.size = static_cast<std::int32_t>(feedback.size());
      m.feedback = to_u8(feedback);
      std::lock_guard lock(feedback_mu);  // counted and published in one order
      server.feedback_pub->publish_bytes(encode(m));
      feedback_count.fetch_add(1);
    }
    void finish(GoalState state, std::span<const std::byte> result, const std::string& message) override {
      server.finish(*this, state, result, message);
    }
    bool finished() const override {
      std::lock_guard lock(server.mu);
      return is_terminal(status.state);
    }

    ActionServerCore& server;
    const std::uint64_t client_id;
    const Bytes bytes;
    std::atomic<bool> cancel{false};
    std::mutex feedback_mu;
    std::atomic<std::int32_t> feedback_count{0};
    // Guarded by server.mu:
    GoalStatus status;
    Bytes result;
    Clock::time_point ended_at{};
    std::optional<Clock::time_point> client_missing_since;
  };

  void on_goal(std::span<const std::byte> request, ResponseWriter& out);    // node executor
  void on_cancel(std::span<const std::byte> request, ResponseWriter& out);  // node executor
  void on_result(std::span<const std::byte> request, ResponseWriter& out);  // node executor
  void run(std::shared_ptr<Goal> goal);                                     // the goal's thread
  void finish(Goal& g, GoalState state, std::span<const std::byte> result, const std::string& message);
  void request_cancel_locked(Goal& g, const std::string& why);
  void publish_status();
  void loop();  // the server's thread

  std::shared_ptr<ServerCore> goal_server, cancel_server, result_server;
  std::shared_ptr<PublisherCore> feedback_pub, status_pub;
  std::uint64_t tap = 0;
  std::thread thread;

  mutable std::mutex mu;                // guards what follows (and Goal's guarded fields)
  std::condition_variable goal_cv;      // a goal's cancel flag or a goal ended
  std::condition_variable loop_cv;      // wakes the server's thread
  bool stopping = false;
  bool status_due = true;               // publish at the thread's next turn
  bool check_clients = false;           // a participant left: check at once
  std::map<std::string, std::shared_ptr<Goal>> goals;
  std::size_t running = 0;              // goal threads not finished
  ActionServerStats counters;
  std::mutex publish_mu;                // one status publication at a time, in order
};

void ActionServerCore::start() {
  auto self = shared_from_this();
  ActionServerCore* raw = this;
  feedback_pub = create_publisher(*node, feedback_channel(name), envelope_type<lcmx_msgs::action_feedback_t>(),
                                  PublisherOptions{});
  status_pub = create_publisher(*node, status_channel(name), envelope_type<lcmx_msgs::action_status_t>(),
                                PublisherOptions{});
  // The services' handlers use `raw`: close() removes the services before the core goes.
  cancel_server = create_server(*node, cancel_channel(name), service_types<lcmx_msgs::action_goal_ref_t, lcmx_msgs::action_goal_status_t>(),
                                [raw](std::span<const std::byte> in, ResponseWriter& out) { raw->on_cancel(in, out); });
  result_server = create_server(*node, result_channel(name), service_types<lcmx_msgs::action_goal_ref_t, lcmx_msgs::action_result_t>(),
                                [raw](std::span<const std::byte> in, ResponseWriter& out) { raw->on_result(in, out); });
  goal_server = create_server(*node, goal_channel(name), service_types<lcmx_msgs::action_goal_t, lcmx_msgs::action_goal_reply_t>(),
                              [raw](std::span<const std::byte> in, ResponseWriter& out) { raw->on_goal(in, out); });
  std::weak_ptr<ActionServerCore> weak = self;
  tap = hook::add_event_tap(*node, [weak](const Event& e) {
    if (e.kind != Event::Kind::participant_left && e.kind != Event::Kind::publisher_unmatched) return;
    if (auto s = weak.lock()) {
      {
        std::lock_guard lock(s->mu);
        s->check_clients = true;
      }
      s->loop_cv.notify_all();
    }
  });
  thread = std::thread([this] { loop(); });
}

void ActionServerCore::close() {
  close_server(goal_server);  // no new goals
  {
    std::lock_guard lock(mu);
    for (auto& [id, g] : goals)
      if (!is_terminal(g->status.state)) request_cancel_locked(*g, "the action server is shutting down");
    goal_cv.notify_all();
  }
  {
    std::unique_lock lock(mu);
    goal_cv.wait(lock, [this] { return running == 0; });
  }
  publish_status();  // the goals' final states
  close_server(cancel_server);
  close_server(result_server);
  hook::remove_event_tap(*node, tap);
  {
    std::lock_guard lock(mu);
    stopping = true;
  }
  loop_cv.notify_all();
  if (thread.joinable()) thread.join();
}

std::vector<GoalStatus> ActionServerCore::list() const {
  std::vector<GoalStatus> out;
  for (const auto& m : announced()) out.push_back(from_msg(m));
  return out;
}

std::vector<lcmx_msgs::action_goal_status_t> ActionServerCore::announced() const {
  std::lock_guard lock(mu);
  std::vector<const Goal*> all;
  for (const auto& [id, g] : goals) all.push_back(g.get());
  // Live goals first, then ended ones, most recent first.
  std::stable_sort(all.begin(), all.end(), [](const Goal* a, const Goal* b) {
    const bool ea = is_terminal(a->status.state), eb = is_terminal(b->status.state);
    if (ea != eb) return !ea;
    return ea && a->ended_at > b->ended_at;
  });
  std::vector<lcmx_msgs::action_goal_status_t> out;
  for (const Goal* g : all) out.push_back(to_msg(g->status, g->feedback_count.load()));
  return out;
}

void ActionServerCore::on_goal(std::span<const std::byte> in, ResponseWriter& out) {
  lcmx_msgs::action_goal_t m;
  if (!decode(in, m) || m.goal_id.size() != 32 || m.size < 0)
    throw BadRequest("a malformed action goal envelope");
  lcmx_msgs::action_goal_reply_t reply;
  reply.accepted = false;
  reply.types_ok = compatible(m.goal_fingerprint, types.goal_fingerprint) &&
                   compatible(m.feedback_fingerprint, types.feedback_fingerprint) &&
                   compatible(m.result_fingerprint, types.result_fingerprint);
  reply.cancel_server_id = static_cast<std::int64_t>(server_id(*cancel_server));
  reply.result_server_id = static_cast<std::int64_t>(server_id(*result_server));
  reply.goal_type = types.goal_name;
  reply.feedback_type = types.feedback_name;
  reply.result_type = types.result_name;
  auto answer = [&] {
    const Bytes b = encode(reply);
    auto span = out.allocate(b.size());
    std::copy(b.begin(), b.end(), span.begin());
  };
  if (!reply.types_ok) {
    reply.message = fmt::format("action '{}': the server's goal/feedback/result are {}, {}, {}", name,
                                type_text(types.goal_name, types.goal_fingerprint),
                                type_text(types.feedback_name, types.feedback_fingerprint),
                                type_text(types.result_name, types.result_fingerprint));
    std::lock_guard lock(mu);
    ++counters.rejected;
    return answer();
  }
  {
    std::lock_guard lock(mu);
    if (auto it = goals.find(m.goal_id); it != goals.end()) {  // the same goal again: same answer
      reply.accepted = true;
      return answer();
    }
    std::size_t live = 0;
    for (const auto& [id, g] : goals) live += is_terminal(g->status.state) ? 0 : 1;
    if (live >= options.max_goals) {
      ++counters.rejected;
      reply.message = fmt::format("busy: {} goals are executing (max_goals)", live);
      return answer();
    }
  }
  std::string why;
  try {
    why = accept ? accept(as_bytes(m.goal)) : std::string();
  } catch (const BadRequest&) {
    throw;
  } catch (const std::exception& e) {
    why = std::string("the accept function threw: ") + e.what();
  }
  std::shared_ptr<Goal> goal;
  {
    std::lock_guard lock(mu);
    if (!why.empty() || stopping) {
      ++counters.rejected;
      reply.message = why.empty() ? "the action server is shutting down" : why;
      return answer();
    }
    goal = std::make_shared<Goal>(*this, m.goal_id, static_cast<std::uint64_t>(m.client_id), Bytes(as_bytes(m.goal).begin(), as_bytes(m.goal).end()));
    goals[m.goal_id] = goal;
    ++counters.accepted;
    ++running;
    status_due = true;
  }
  reply.accepted = true;
  answer();
  loop_cv.notify_all();
  std::thread([self = shared_from_this(), goal] { self->run(goal); }).detach();
}

void ActionServerCore::run(std::shared_ptr<Goal> goal) {
  {
    std::lock_guard lock(mu);
    if (goal->status.state == GoalState::accepted) goal->status.state = GoalState::executing;
    status_due = true;
  }
  loop_cv.notify_all();
  std::string error;
  try {
    execute(*goal);
  } catch (const std::exception& e) {
    error = std::string("execute threw: ") + e.what();
  } catch (...) {
    error = "execute threw a non-std::exception";
  }
  if (!goal->finished()) {
    if (error.empty()) error = "execute returned without ending the goal";
    spdlog::warn("lcmx: action '{}': goal {}: {}", name, goal->id(), error);
    try {
      finish(*goal, GoalState::aborted, {}, error);
    } catch (const Error&) {  // ended meanwhile by another thread of execute's
    }
  }
  {
    std::lock_guard lock(mu);
    --running;
  }
  goal_cv.notify_all();
}

void ActionServerCore::finish(Goal& g, GoalState state, std::span<const std::byte> result, const std::string& message) {
  if (state != GoalState::succeeded && state != GoalState::aborted && state != GoalState::canceled)
    throw Error(Errc::invalid_argument, fmt::format("action '{}': a goal ends succeeded, aborted or canceled, not {}",
                                                    name, to_string(state)));
  {
    std::lock_guard lock(mu);
    if (is_terminal(g.status.state))
      throw Error(Errc::invalid_argument,
                  fmt::format("action '{}': goal {} already ended {}", name, g.id(), to_string(g.status.state)));
    if (!(state == GoalState::canceled && message.empty() && g.cancel.load())) g.status.message = message;
    g.status.state = state;
    g.result.assign(result.begin(), result.end());
    g.ended_at = Clock::now();
    switch (state) {
      case GoalState::succeeded: ++counters.succeeded; break;
      case GoalState::aborted: ++counters.aborted; break;
      default: ++counters.canceled; break;
    }
  }
  goal_cv.notify_all();
  publish_status();  // at once, on the goal's thread: the client fetches the result on it
}

void ActionServerCore::request_cancel_locked(Goal& g, const std::string& why) {
  if (is_terminal(g.status.state) || g.cancel.load()) return;
  g.cancel.store(true);
  g.status.state = GoalState::canceling;
  g.status.message = why;
  ++counters.cancel_requests;
  status_due = true;
}

void ActionServerCore::on_cancel(std::span<const std::byte> in, ResponseWriter& out) {
  lcmx_msgs::action_goal_ref_t m;
  if (!decode(in, m)) throw BadRequest("a malformed action cancel envelope");
  GoalStatus s{m.goal_id, GoalState::unknown, "no such goal at this server"};
  {
    std::lock_guard lock(mu);
    if (auto it = goals.find(m.goal_id); it != goals.end()) {
      request_cancel_locked(*it->second, "canceled by a client");
      s = it->second->status;  // canceling, or how it ended (a cancel after the end changes nothing)
    }
  }
  goal_cv.notify_all();
  loop_cv.notify_all();
  const Bytes b = encode(to_msg(s));
  auto span = out.allocate(b.size());
  std::copy(b.begin(), b.end(), span.begin());
}

void ActionServerCore::on_result(std::span<const std::byte> in, ResponseWriter& out) {
  lcmx_msgs::action_goal_ref_t m;
  if (!decode(in, m)) throw BadRequest("a malformed action result envelope");
  lcmx_msgs::action_result_t r;
  r.size = 0;
  {
    std::lock_guard lock(mu);
    if (auto it = goals.find(m.goal_id); it != goals.end()) {
      r.status = to_msg(it->second->status);
      if (is_terminal(it->second->status.state)) {
        r.result = to_u8(it->second->result);
        r.size = static_cast<std::int32_t>(r.result.size());
      }
    } else {
      r.status = to_msg({m.goal_id, GoalState::unknown, "no such goal at this server"});
    }
  }
  const Bytes b = encode(r);
  auto span = out.allocate(b.size());
  std::copy(b.begin(), b.end(), span.begin());
}

void ActionServerCore::publish_status() {
  lcmx_msgs::action_status_t m;
  m.server_participant = static_cast<std::int64_t>(hook::participant_id(*node));
  m.goal_server_id = static_cast<std::int64_t>(server_id(*goal_server));
  m.cancel_server_id = static_cast<std::int64_t>(server_id(*cancel_server));
  m.result_server_id = static_cast<std::int64_t>(server_id(*result_server));
  m.goal_type = types.goal_name;
  m.feedback_type = types.feedback_name;
  m.result_type = types.result_name;
  m.goal_fingerprint = types.goal_fingerprint;
  m.feedback_fingerprint = types.feedback_fingerprint;
  m.result_fingerprint = types.result_fingerprint;
  std::lock_guard publish_lock(publish_mu);
  m.goals = announced();
  if (m.goals.size() > kMaxListed) m.goals.resize(kMaxListed);
  m.num_goals = static_cast<std::int32_t>(m.goals.size());
  status_pub->publish_bytes(encode(m));
}

void ActionServerCore::loop() {
  // At most 100 ms between turns: a new status subscriber (a client, a tool) hears the status
  // within that, and a gone client is noticed within a fifth of client_timeout.
  const auto tick = std::clamp<ms>(std::min<ms>(options.status_period, options.client_timeout / 5), ms(10), ms(100));
  auto next_status = Clock::now();
  auto next_check = Clock::now();
  std::size_t status_subscribers = 0;
  std::unique_lock lock(mu);
  while (!stopping) {
    const auto now = Clock::now();
    if (const auto n = status_pub->subscriber_count(); n != status_subscribers) {
      if (n > status_subscribers) status_due = true;
      status_subscribers = n;
    }
    // Goals whose client went away: canceled after client_timeout.
    if (check_clients || now >= next_check) {
      check_clients = false;
      next_check = now + tick;
      std::vector<std::shared_ptr<Goal>> live;
      for (auto& [id, g] : goals)
        if (!is_terminal(g->status.state) && !g->cancel.load()) live.push_back(g);
      lock.unlock();
      std::vector<std::pair<std::shared_ptr<Goal>, bool>> seen;
      for (auto& g : live) seen.emplace_back(g, server_client_connected(*goal_server, g->client_id));
      lock.lock();
      bool woke = false;
      for (auto& [g, connected] : seen) {
        if (connected) {
          g->client_missing_since.reset();
        } else if (!g->client_missing_since) {
          g->client_missing_since = now;
        } else if (now - *g->client_missing_since >= options.client_timeout) {
          spdlog::info("lcmx: action '{}': goal {}: its client is gone; canceling", name, g->id());
          ++counters.client_gone_cancels;
          request_cancel_locked(*g, "canceled: the client went away");
          woke = true;
        }
      }
      if (woke) goal_cv.notify_all();
    }
    // Forget ended goals past their retention (and the oldest beyond max_retained).
    std::vector<std::pair<Clock::time_point, std::string>> ended;
    for (auto& [id, g] : goals)
      if (is_terminal(g->status.state)) ended.emplace_back(g->ended_at, id);
    std::sort(ended.begin(), ended.end());
    for (std::size_t i = 0; i < ended.size(); ++i)
      if (now - ended[i].first > options.result_retention || ended.size() - i > options.max_retained)
        goals.erase(ended[i].second);
    if (status_due || now >= next_status) {
      status_due = false;
      next_status = now + options.status_period;
      lock.unlock();
      publish_status();
      lock.lock();
      continue;
    }
    const auto wake = std::min(next_check, next_status);
    loop_cv.wait_until(lock, wake, [this] { return stopping || status_due || check_clients; });
  }
}

std::shared_ptr<ActionServerCore> create_action_server(NodeImpl& node, std::string name, ActionTypes types,
                                                       GoalAcceptor accept, GoalExecutor execute,
                                                       ActionServerOptions options) {
  check_action_name(name, "create_action_server");
  if (!execute) throw Error(Errc::invalid_argument, "create_action_server '" + name + "': empty execute function");
  if (options.max_goals == 0 || options.status_period <= ms(0) || options.client_timeout <= ms(0) ||
      options.result_retention < ms(0))
    throw Error(Errc::invalid_argument,
                "create_action_server '" + name + "': max_goals, status_period and client_timeout must be positive");
  auto s = std::make_shared<ActionServerCore>(hook::shared(node), std::move(name), std::move(types),
                                              std::move(accept), std::move(execute), options);
  s->start();
  return s;
}
void close_action_server(const std::shared_ptr<ActionServerCore>& server) { server->close(); }
ActionServerStats action_server_stats(const ActionServerCore& server) { return server.stats(); }
std::vector<GoalStatus> action_server_goals(const ActionServerCore& server) { return server.list(); }
const std::string& action_server_name(const ActionServerCore& server) { return server.name; }

// --- Client ------------------------------------------------------------------------------------

class ActionClientCore : public std::enable_shared_from_this<ActionClientCore> {
 public:
  ActionClientCore(std::string nm, ActionTypes t) : name(std::move(nm)), types(std::move(t)) {}
  void start(NodeImpl& user_node);
  void close();
  CallResult<GoalStatus> send_goal(std::size_t size, const std::function<void(std::span<std::byte>)>& encode_goal,
                                   ms timeout, std::function<void(std::span<const std::byte>)> feedback);
  GoalStatus status(const std::string& id) const;
  CallResult<std::pair<GoalStatus, Bytes>> result(const std::string& id, ms timeout);
  CallResult<GoalStatus> cancel(const std::string& id, ms timeout);
  std::vector<GoalStatus> list() const;

  const std::string name;
  const ActionTypes types;
  std::shared_ptr<ClientCore> goal_client, cancel_client, result_client;

 private:
  // The server a goal of ours was last sent to: written on the goal client's sending thread
  // under its lock (detail::client_call's on_sent), read under `mu`. `mu` of its own: a leaf.
  struct GoalTarget {
    std::mutex mu;
    std::uint64_t participant = 0, goal_server = 0;  // 0: not sent yet
    bool is(std::uint64_t p, std::uint64_t id) {
      std::lock_guard lock(mu);
      return participant != 0 && participant == p && goal_server == id;
    }
    std::uint64_t participant_now() {
      std::lock_guard lock(mu);
      return participant;
    }
  };
  struct Tracked {
    GoalStatus status;
    std::shared_ptr<GoalTarget> target;  // own goals: where the goal request went
    std::uint64_t participant = 0, goal_server = 0, cancel_server = 0, result_server = 0;
    std::function<void(std::span<const std::byte>)> feedback;  // own goals with a callback
    std::int64_t feedback_heard = 0;     // feedback messages of the goal received
    std::int64_t feedback_sent = 0;      // ... published, as the last status said
    bool feedback_closed = false;        // the end was reported: no more callbacks
    int in_feedback = 0;                 // callbacks running now
    bool mine = false;
    Clock::time_point heard;  // last status (forgetting goals of others)
  };
  void on_status(const RawMessage& message);    // client thread
  void on_feedback(const RawMessage& message);  // client thread
  void on_servers_gone(const std::vector<ServerInfo>& gone);
  // Delivers the goal's trailing feedback, then stops its callbacks (the end is reported).
  void close_feedback(const std::string& id, Clock::time_point deadline);
  static constexpr ms kFeedbackGrace{500};
  void update_locked(Tracked& t, const GoalStatus& s);
  // A synchronous call on one of our service clients, pinned to a server.
  template <class Resp>
  CallResult<Resp> call(ClientCore& c, const Bytes& request, ms timeout, const ServerInfo* pin,
                        std::function<void(const ServerInfo&)> on_sent = {});

  std::shared_ptr<NodeImpl> node;  // manual, run by `thread`
  std::shared_ptr<SubscriberCore> status_sub, feedback_sub;
  std::thread thread;
  std::atomic<bool> stop{false};

  mutable std::mutex mu;
  std::condition_variable cv;  // a goal's state changed
  std::map<std::string, Tracked> goals;
  static constexpr std::size_t kMaxTracked = 4096;  // goals of others heard in statuses
};

void ActionClientCore::start(NodeImpl& user_node) {
  // The status and feedback subscribers first: a server learns of them (our beacons list
  // their matches) before it can answer our goal client's probe, so a goal it accepts has its
  // first feedback sent to us (made after the goal client, they sometimes matched the server's
  // feedback publisher only after it accepted a goal sent at once: the first feedback was lost).
  node = hook::create_manual_node(user_node, hook::node_name(user_node) + "/action_client:" + name);
  status_sub = std::make_shared<RawSubscriberCore>(
      status_channel(name), SubscriberOptions{.queue_depth = 64}, [this](const RawMessage& m) { on_status(m); },
      envelope_type<lcmx_msgs::action_status_t>());
  feedback_sub = std::make_shared<RawSubscriberCore>(
      feedback_channel(name), SubscriberOptions{.queue_depth = 256},
      [this](const RawMessage& m) { on_feedback(m); }, envelope_type<lcmx_msgs::action_feedback_t>());
  add_subscriber(*node, status_sub);
  add_subscriber(*node, feedback_sub);
  std::weak_ptr<ActionClientCore> weak = weak_from_this();
  goal_client = create_client(user_node, goal_channel(name), service_types<lcmx_msgs::action_goal_t, lcmx_msgs::action_goal_reply_t>(), [weak](const std::vector<ServerInfo>& gone) {
    if (auto self = weak.lock()) self->on_servers_gone(gone);
  });
  cancel_client = create_client(user_node, cancel_channel(name), service_types<lcmx_msgs::action_goal_ref_t, lcmx_msgs::action_goal_status_t>());
  result_client = create_client(user_node, result_channel(name), service_types<lcmx_msgs::action_goal_ref_t, lcmx_msgs::action_result_t>());
  thread = std::thread([this] {
    while (!stop.load() && !hook::stopped(*node)) hook::run_once(*node, std::chrono::seconds(1));
  });
}

void ActionClientCore::close() {
  if (stop.exchange(true)) return;
  hook::interrupt(*node);
  if (thread.joinable()) {
    if (thread.get_id() == std::this_thread::get_id()) thread.detach();  // from a feedback callback
    else thread.join();
  }
  close_client(goal_client);
  close_client(cancel_client);
  close_client(result_client);
  remove_subscriber(status_sub);
  remove_subscriber(feedback_sub);
  hook::stop(*node);
  cv.notify_all();
}

template <class Resp>
CallResult<Resp> ActionClientCore::call(ClientCore& c, const Bytes& request, ms timeout, const ServerInfo* pin,
                                        std::function<void(const ServerInfo&)> on_sent) {
  std::promise<CallResult<Resp>> promise;
  auto future = promise.get_future();
  client_call(
      c, request.size(), copy_request(request), timeout,
      [&promise](std::span<const std::byte> bytes, CallErrc error, bool ok, const std::string& message,
                 const ServerInfo& server, const RawMessage*) {
        if (!ok) return promise.set_value(CallResult<Resp>::failure(error, message, server));
        Resp r;
        if (!decode(bytes, r))
          return promise.set_value(
              CallResult<Resp>::failure(CallErrc::type_mismatch, "a malformed action reply envelope", server));
        promise.set_value(CallResult<Resp>::success(std::move(r), server));
      },
      pin, false, std::move(on_sent));
  return future.get();
}

CallResult<GoalStatus> ActionClientCore::send_goal(std::size_t size,
                                                   const std::function<void(std::span<std::byte>)>& encode_goal,
                                                   ms timeout, std::function<void(std::span<const std::byte>)> feedback) {
  if (size > static_cast<std::size_t>(INT32_MAX))
    return CallResult<GoalStatus>::failure(CallErrc::bad_request, "a goal is limited to 2 GiB");
  lcmx_msgs::action_goal_t m;
  m.goal_id = new_goal_id();
  m.client_id = static_cast<std::int64_t>(client_id(*goal_client));
  m.goal_fingerprint = types.goal_fingerprint;
  m.feedback_fingerprint = types.feedback_fingerprint;
  m.result_fingerprint = types.result_fingerprint;
  m.size = static_cast<std::int32_t>(size);
  m.goal.resize(size);
  encode_goal({reinterpret_cast<std::byte*>(m.goal.data()), size});
  auto target = std::make_shared<GoalTarget>();
  {
    // Tracked before the request goes: feedback and status may overtake the reply (they are
    // taken from the server the request was sent to, `target`).
    std::lock_guard lock(mu);
    auto& t = goals[m.goal_id];
    t.status = {m.goal_id, GoalState::unknown, ""};
    t.feedback = std::move(feedback);
    t.mine = true;
    t.heard = Clock::now();
    t.target = target;
  }
  auto r = call<lcmx_msgs::action_goal_reply_t>(*goal_client, encode(m), timeout, nullptr,
                                                [target](const ServerInfo& s) {
                                                  std::lock_guard lock(target->mu);
                                                  target->participant = s.participant;
                                                  target->goal_server = s.id;
                                                });
  std::lock_guard lock(mu);
  auto it = goals.find(m.goal_id);
  if (!r || !r.value().types_ok || !r.value().accepted) {
    if (it != goals.end()) goals.erase(it);
    if (!r) return CallResult<GoalStatus>::failure(r.error(), r.message(), r.server());
    if (!r.value().types_ok)
      return CallResult<GoalStatus>::failure(
          CallErrc::type_mismatch,
          fmt::format("{}; the client's are {}, {}, {}", r.value().message, type_text(types.goal_name, types.goal_fingerprint),
                      type_text(types.feedback_name, types.feedback_fingerprint),
                      type_text(types.result_name, types.result_fingerprint)),
          r.server());
    return CallResult<GoalStatus>::success({m.goal_id, GoalState::rejected, r.value().message}, r.server());
  }
  if (it == goals.end()) return CallResult<GoalStatus>::failure(CallErrc::shutdown, "the action client was closed");
  auto& t = it->second;
  t.participant = r.server().participant;
  t.goal_server = r.server().id;
  t.cancel_server = static_cast<std::uint64_t>(r.value().cancel_server_id);
  t.result_server = static_cast<std::uint64_t>(r.value().result_server_id);
  update_locked(t, {m.goal_id, GoalState::accepted, ""});
  // The server may already have gone (its removal is not repeated for us): check now.
  bool known = false;
  for (const auto& s : client_servers(*goal_client)) known = known || (s.participant == t.participant && s.id == t.goal_server);
  if (!known) update_locked(t, {m.goal_id, GoalState::lost, "the action server went away"});
  return CallResult<GoalStatus>::success({m.goal_id, GoalState::accepted, ""}, r.server());
}

void ActionClientCore::update_locked(Tracked& t, const GoalStatus& s) {
  if (rank(s.state) < rank(t.status.state)) return;
  if (rank(s.state) == rank(t.status.state) && (is_terminal(t.status.state) || s.state == t.status.state)) return;
  t.status.state = s.state;
  t.status.message = s.message;
  cv.notify_all();
}

void ActionClientCore::on_status(const RawMessage& message) {
  lcmx_msgs::action_status_t m;
  if (!decode(message.data, m)) return;
  const auto server = static_cast<std::uint64_t>(m.server_participant);
  const auto goal_server = static_cast<std::uint64_t>(m.goal_server_id);
  // Only from the server it names (its status publisher's participant); through this host's
  // bridge, which names no origin, the envelope's own fields must do.
  const auto from = sender_of(message);
  if (!from || (from->path != Path::bridge && from->participant != server)) return;
  const auto now = Clock::now();
  std::lock_guard lock(mu);
  for (const auto& g : m.goals) {
    auto it = goals.find(g.goal_id);
    if (it == goals.end()) {
      if (goals.size() >= kMaxTracked) {  // forget the goal of others heard least recently
        auto oldest = goals.end();
        for (auto j = goals.begin(); j != goals.end(); ++j)
          if (!j->second.mine && (oldest == goals.end() || j->second.heard < oldest->second.heard)) oldest = j;
        if (oldest == goals.end()) continue;
        goals.erase(oldest);
      }
      it = goals.emplace(g.goal_id, Tracked{}).first;
      it->second.status.goal_id = g.goal_id;
    }
    auto& t = it->second;
    // A goal is one server's: the one that accepted it, or the first whose status named it.
    if (t.participant != 0 && (t.participant != server || t.goal_server != goal_server)) continue;
    if (t.participant == 0) {  // a goal of another client, or ours before its reply
      if (t.mine) {
        // Its reply has not arrived: take the state (not the server: the reply sets it), and
        // only from the server the goal request went to.
        if (!t.target || !t.target->is(server, goal_server)) continue;
      } else {
        t.participant = static_cast<std::uint64_t>(m.server_participant);
        t.goal_server = static_cast<std::uint64_t>(m.goal_server_id);
        t.cancel_server = static_cast<std::uint64_t>(m.cancel_server_id);
        t.result_server = static_cast<std::uint64_t>(m.result_server_id);
      }
    }
    t.heard = now;
    t.feedback_sent = std::max<std::int64_t>(t.feedback_sent, g.feedback_count);
    update_locked(t, from_msg(g));
  }
}

void ActionClientCore::on_feedback(const RawMessage& message) {
  lcmx_msgs::action_feedback_t m;
  if (!decode(message.data, m)) return;
  const auto from = sender_of(message);
  if (!from) return;
  std::function<void(std::span<const std::byte>)> f;
  {
    std::lock_guard lock(mu);
    auto it = goals.find(m.goal_id);
    if (it == goals.end()) return;
    // Only from the goal's server (before its reply: the server the request went to); through
    // this host's bridge, which names no origin, as it comes.
    const std::uint64_t server =
        it->second.participant != 0 ? it->second.participant
                                    : (it->second.target ? it->second.target->participant_now() : 0);
    if (from->path != Path::bridge && (server == 0 || from->participant != server)) return;
    ++it->second.feedback_heard;
    cv.notify_all();
    if (!it->second.feedback || it->second.feedback_closed) return;
    f = it->second.feedback;
    ++it->second.in_feedback;
  }
  try {
    f(as_bytes(m.feedback));
  } catch (const std::exception& e) {
    spdlog::error("lcmx: action '{}': a feedback callback threw: {}", name, e.what());
  }
  std::lock_guard lock(mu);
  if (auto it = goals.find(m.goal_id); it != goals.end()) --it->second.in_feedback;
  cv.notify_all();
}

void ActionClientCore::close_feedback(const std::string& id, Clock::time_point deadline) {
  std::unique_lock lock(mu);
  auto it = goals.find(id);
  if (it == goals.end() || it->second.feedback_closed) return;
  // Feedback travels on its own topic and may trail the end: deliver what the server said it
  // published (a dropped message is waited for kFeedbackGrace at most), then no more.
  const auto until = std::min(deadline, Clock::now() + kFeedbackGrace);
  cv.wait_until(lock, until, [&] {
    auto i = goals.find(id);
    return i == goals.end() || !i->second.feedback || i->second.feedback_heard >= i->second.feedback_sent;
  });
  it = goals.find(id);
  if (it == goals.end()) return;
  it->second.feedback_closed = true;
  if (thread.get_id() != std::this_thread::get_id())  // not from inside a feedback callback
    cv.wait(lock, [&] {
      auto i = goals.find(id);
      return i == goals.end() || i->second.in_feedback == 0;
    });
}

void ActionClientCore::on_servers_gone(const std::vector<ServerInfo>& gone) {
  std::lock_guard lock(mu);
  for (auto& [id, t] : goals)
    for (const auto& s : gone)
      if (t.participant == s.participant && t.goal_server == s.id && !is_terminal(t.status.state))
        update_locked(t, {id, GoalState::lost, "the action server went away before the goal ended"});
}

GoalStatus ActionClientCore::status(const std::string& id) const {
  std::lock_guard lock(mu);
  auto it = goals.find(id);
  return it == goals.end() ? GoalStatus{id, GoalState::unknown, ""} : it->second.status;
}

std::vector<GoalStatus> ActionClientCore::list() const {
  std::lock_guard lock(mu);
  std::vector<GoalStatus> out;
  for (const auto& [id, t] : goals) out.push_back(t.status);
  return out;
}

CallResult<std::pair<GoalStatus, Bytes>> ActionClientCore::result(const std::string& id, ms timeout) {
  using Result = CallResult<std::pair<GoalStatus, Bytes>>;
  const auto deadline = Clock::now() + timeout;
  ServerInfo server;
  GoalStatus st;
  bool mine = false;
  std::uint64_t goal_server = 0;
  {
    std::unique_lock lock(mu);
    // The end of the goal, from the status topic (or `lost`).
    cv.wait_until(lock, deadline, [&] {
      auto it = goals.find(id);
      return stop.load() || (it != goals.end() && is_terminal(it->second.status.state));
    });
    auto it = goals.find(id);
    if (stop.load()) return Result::failure(CallErrc::shutdown, "the action client was closed");
    if (it == goals.end() || it->second.participant == 0)
      return Result::failure(CallErrc::no_server,
                             fmt::format("action '{}': goal {} is not known (no server's status named it)", name, id));
    st = it->second.status;
    server.participant = it->second.participant;
    server.id = it->second.result_server;
    mine = it->second.mine;
    goal_server = it->second.goal_server;
    if (!is_terminal(st.state)) {
      // The status may have been dropped (a slow client): ask the server once before giving up.
      lock.unlock();
      lcmx_msgs::action_goal_ref_t ref;
      ref.goal_id = id;
      auto r = call<lcmx_msgs::action_result_t>(*result_client, encode(ref), ms(200), &server);
      if (r && is_terminal(state_of(r.value().status.state))) {
        close_feedback(id, deadline);
        return Result::success({from_msg(r.value().status), Bytes(as_bytes(r.value().result).begin(), as_bytes(r.value().result).end())}, r.server());
      }
      return Result::failure(CallErrc::timeout, fmt::format("action '{}': goal {} is still {} after {} ms", name, id,
                                                            to_string(st.state), timeout.count()),
                             server);
    }
  }
  close_feedback(id, deadline);
  if (st.state == GoalState::lost || st.state == GoalState::rejected) return Result::success({st, {}}, server);
  // Our goal's server may be gone already (destroyed right after its final status): then the
  // end is all there is; asking would wait for a server that never answers.
  auto alive = [&] {
    bool listed = !mine;
    for (const auto& s : client_servers(*goal_client))
      listed = listed || (s.participant == server.participant && s.id == goal_server);
    return listed;
  };
  if (!alive()) {
    st.message += st.message.empty() ? "" : "; ";
    st.message += "the action server went away before its result was fetched";
    return Result::success({st, {}}, server);
  }
  lcmx_msgs::action_goal_ref_t ref;
  ref.goal_id = id;
  // Asked in slices of at most 1 s: a server that leaves right after the check above may never
  // have answered the result client's probe, and then nothing tells the pinned call that it
  // went away (it waited for the whole timeout); between slices, a server no longer listed
  // ends the wait.
  std::optional<CallResult<lcmx_msgs::action_result_t>> answer;
  bool gone = false;
  for (;;) {
    const auto left = std::max<ms>(ms(100), std::chrono::duration_cast<ms>(deadline - Clock::now()));
    const auto slice = std::min<ms>(left, ms(1000));
    answer = call<lcmx_msgs::action_result_t>(*result_client, encode(ref), slice, &server);
    if (answer->ok() || answer->error() != CallErrc::timeout || slice == left) break;
    if ((gone = !alive())) break;
  }
  auto& r = *answer;
  if (!r) {
    if (gone || r.error() == CallErrc::server_gone || r.error() == CallErrc::no_server) {
      st.state = GoalState::lost;
      st.message = "the action server went away before the result was fetched";
      return Result::success({st, {}}, server);
    }
    return Result::failure(r.error(), r.message(), r.server());
  }
  GoalStatus final_status = from_msg(r.value().status);
  if (final_status.state == GoalState::unknown) final_status = st;  // forgotten (retention) meanwhile
  return Result::success({final_status, Bytes(as_bytes(r.value().result).begin(), as_bytes(r.value().result).end())},
                         r.server());
}

CallResult<GoalStatus> ActionClientCore::cancel(const std::string& id, ms timeout) {
  ServerInfo server;
  {
    std::lock_guard lock(mu);
    auto it = goals.find(id);
    if (it == goals.end() || it->second.participant == 0)
      return CallResult<GoalStatus>::failure(
          CallErrc::no_server, fmt::format("action '{}': goal {} is not known (no server's status named it)", name, id));
    if (it->second.status.state == GoalState::lost)
      return CallResult<GoalStatus>::failure(CallErrc::server_gone,
                                             fmt::format("action '{}': the server of goal {} went away", name, id));
    server.participant = it->second.participant;
    server.id = it->second.cancel_server;
  }
  lcmx_msgs::action_goal_ref_t ref;
  ref.goal_id = id;
  auto r = call<lcmx_msgs::action_goal_status_t>(*cancel_client, encode(ref), timeout, &server);
  if (!r) return CallResult<GoalStatus>::failure(r.error(), r.message(), r.server());
  GoalStatus s = from_msg(r.value());
  {
    std::lock_guard lock(mu);
    if (auto it = goals.find(id); it != goals.end()) update_locked(it->second, s);
  }
  return CallResult<GoalStatus>::success(std::move(s), r.server());
}

std::shared_ptr<ActionClientCore> create_action_client(NodeImpl& node, std::string name, ActionTypes types) {
  check_action_name(name, "create_action_client");
  auto c = std::make_shared<ActionClientCore>(std::move(name), std::move(types));
  c->start(node);
  return c;
}
void close_action_client(const std::shared_ptr<ActionClientCore>& client) { client->close(); }
bool action_wait_for_server(ActionClientCore& client, ms timeout) {
  const auto deadline = Clock::now() + timeout;
  auto left = [&] { return std::max<ms>(ms(0), std::chrono::duration_cast<ms>(deadline - Clock::now())); };
  return client_wait_for_service(*client.goal_client, left()) && client_wait_for_service(*client.cancel_client, left()) &&
         client_wait_for_service(*client.result_client, left());
}
CallResult<GoalStatus> action_send_goal(ActionClientCore& client, std::size_t size,
                                        const std::function<void(std::span<std::byte>)>& encode_goal, ms timeout,
                                        std::function<void(std::span<const std::byte>)> feedback) {
  return client.send_goal(size, encode_goal, timeout, std::move(feedback));
}
GoalStatus action_status(const ActionClientCore& client, const std::string& goal_id) { return client.status(goal_id); }
CallResult<std::pair<GoalStatus, Bytes>> action_result(ActionClientCore& client, const std::string& goal_id,
                                                       ms timeout) {
  return client.result(goal_id, timeout);
}
CallResult<GoalStatus> action_cancel(ActionClientCore& client, const std::string& goal_id, ms timeout) {
  return client.cancel(goal_id, timeout);
}
std::vector<GoalStatus> action_client_goals(const ActionClientCore& client) { return client.list(); }
std::vector<ServerInfo> action_client_servers(const ActionClientCore& client) {
  return client_servers(*client.goal_client);
}
const std::string& action_client_name(const ActionClientCore& client) { return client.name; }

}  // namespace detail

ActionServer Node::create_action_server_raw(std::string name, std::function<void(RawActionGoal&)> execute) {
  return create_action_server_raw(std::move(name), std::move(execute), {}, ActionServerOptions{});
}

ActionServer Node::create_action_server_raw(std::string name, std::function<void(RawActionGoal&)> execute,
                                            std::function<std::string(std::span<const std::byte>)> accept) {
  return create_action_server_raw(std::move(name), std::move(execute), std::move(accept), ActionServerOptions{});
}

ActionServer Node::create_action_server_raw(std::string name, std::function<void(RawActionGoal&)> execute,
                                            std::function<std::string(std::span<const std::byte>)> accept,
                                            ActionServerOptions options) {
  return ActionServer(detail::create_action_server(*impl_, std::move(name), {}, std::move(accept),
                                                   std::move(execute), options));
}

RawActionClient Node::create_action_client_raw(std::string name) {
  return RawActionClient(detail::create_action_client(*impl_, std::move(name), {}));
}

ActionServer Node::create_action_server_raw(std::string name, detail::ActionTypes types,
                                            std::function<void(RawActionGoal&)> execute,
                                            std::function<std::string(std::span<const std::byte>)> accept,
                                            ActionServerOptions options) {
  return ActionServer(detail::create_action_server(*impl_, std::move(name), std::move(types), std::move(accept),
                                                   std::move(execute), options));
}

RawActionClient Node::create_action_client_raw(std::string name, detail::ActionTypes types) {
  return RawActionClient(detail::create_action_client(*impl_, std::move(name), std::move(types)));
}

}  // namespace lcmx
