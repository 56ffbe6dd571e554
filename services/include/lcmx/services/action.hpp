// Actions: long-running goals with feedback, a result and cancellation (docs/actions.md).
//
//   auto server = node.create_action_server<Goal, Feedback, Result>(
//       "drive", [](lcmx::ActionGoal<Goal, Feedback, Result>& g) {   // a thread per goal
//         while (!g.cancel_requested()) { g.publish_feedback(progress); ... }
//         g.succeed(result);                                            // or abort / canceled
//       });
//   auto client = node.create_action_client<Goal, Feedback, Result>("drive");
//   auto goal = client.send_goal(goal, 1s, [](const Feedback& f) { ... }).value();
//   auto outcome = goal.wait(60s);            // GoalOutcome<Result>: final status and result
//
// An action NAME is three services ("NAME/goal", "NAME/cancel", "NAME/result") and two topics
// ("NAME/feedback", "NAME/status"), envelopes in lcmtypes/action.lcm: a goal finds its server
// by discovery and takes the same path as a message would. Goal states are ROS 2's, plus
// `lost` on the client when the server went away before the goal ended.
//
// Server: `accept` (optional) runs on the node's executor and decides quickly; each accepted
// goal's `execute` runs on a thread of its own, so goals run concurrently (at most
// ActionServerOptions::max_goals; more are rejected). `execute` ends the goal with succeed(),
// abort() or canceled(); if it returns without, or throws, the goal is aborted with a message.
// Cancel requests set cancel_requested() (and wake wait_for_cancel()); `execute` decides when
// to stop. A goal whose client went away (its service client no longer subscribed, locally
// at once, across hosts within the lease) is canceled after client_timeout. The status of
// every live goal, and of recently ended ones, is published on each change and re-announced
// every status_period, so a late client learns it. Destroying the server cancels live goals
// and waits for their `execute` to return.
//
// Client: send_goal() blocks until the server accepted or rejected the goal (or an error:
// no server, timeout, type mismatch). Feedback callbacks run on the client's own thread
// (keep them short; do not block; never call wait() from one). ClientGoal::wait() reports the
// end only after the goal's feedback was delivered (all the server published, or what came
// within 500 ms), and no feedback callback of that goal runs after it returned. Any client can
// ask the status, the result or a cancel of any goal it heard of (its own, or one in a
// server's status) by id.
// Errors: creation throws lcmx::Error (invalid_argument for a bad name, at most 36 bytes);
// calls return CallResult, never throw for call errors. All members are thread-safe.
//
// lcmx::services, like service.hpp; this header also defines Node's action member templates
// (declared in lcmx/core/node.hpp). Include <lcmx/core.hpp>.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "lcmx/core/error.hpp"
#include "lcmx/core/node.hpp"
#include "lcmx/services/service.hpp"

namespace lcmx {

// The values of lcmx_msgs.action_goal_status_t's constants; `lost` is the client's own.
enum class GoalState : std::int8_t {
  unknown = 0,    // never heard of (or forgotten: ended longer than result_retention ago)
  accepted = 1,   // accepted, execute not started yet
  executing = 2,
  canceling = 3,  // cancel requested, execute still running
  succeeded = 4,
  aborted = 5,
  canceled = 6,
  rejected = 7,
  lost = 8,  // client only: the server went away before the goal ended; outcome unknown
};
const char* to_string(GoalState s);
constexpr bool is_terminal(GoalState s) {
  return s == GoalState::succeeded || s == GoalState::aborted || s == GoalState::canceled ||
         s == GoalState::rejected || s == GoalState::lost;
}

struct GoalStatus {
  std::string goal_id;  // 32 hex digits
  GoalState state = GoalState::unknown;
  std::string message;  // rejected/aborted: why; canceled: who asked; cancel refused: why
};

// How a goal ended: its final status, and the result execute gave (succeeded, aborted and
// canceled may carry one; empty if execute gave none or it did not decode as R).
template <class R>
struct GoalOutcome {
  GoalStatus status;
  std::optional<R> result;
};

struct ActionServerOptions {
  std::size_t max_goals = 16;                      // goals executing at once; more are rejected
  std::chrono::milliseconds status_period{1000};   // status re-announced this often (and on change)
  std::chrono::milliseconds client_timeout{5000};  // a gone client's goals are canceled after
  std::chrono::milliseconds result_retention{60000};  // ended goals are kept this long...
  std::size_t max_retained = 256;                     // ...at most this many
};

struct ActionServerStats {
  std::uint64_t accepted = 0, rejected = 0, succeeded = 0, aborted = 0, canceled = 0;
  std::uint64_t cancel_requests = 0;      // cancels asked for live goals (client or client gone)
  std::uint64_t client_gone_cancels = 0;  // of which because the goal's client went away
  std::size_t executing = 0;              // live goals now
};

// A goal on the server, as bytes (the typed ActionGoal wraps it). Valid until `execute`
// returns. Methods are thread-safe.
class RawActionGoal {
 public:
  virtual ~RawActionGoal() = default;
  virtual const std::string& id() const = 0;
  virtual std::span<const std::byte> goal() const = 0;
  virtual bool cancel_requested() const = 0;
  // Waits up to `timeout` for a cancel request (use it instead of sleeping). True if one came.
  virtual bool wait_for_cancel(std::chrono::nanoseconds timeout) const = 0;
  virtual void publish_feedback(std::span<const std::byte> feedback) = 0;
  // Ends the goal: state succeeded, aborted or canceled (anything else throws
  // Error(invalid_argument)), with a result and a message (canceled with "": the cancel
  // request's reason). A second end throws Error(invalid_argument).
  virtual void finish(GoalState state, std::span<const std::byte> result, const std::string& message) = 0;
  virtual bool finished() const = 0;
};

namespace detail {
class NodeImpl;
class ActionServerCore;
class ActionClientCore;

struct ActionTypes {
  std::string goal_name, feedback_name, result_name;  // "" and 0: raw bytes
  std::int64_t goal_fingerprint = 0, feedback_fingerprint = 0, result_fingerprint = 0;
};
// "" accepts the goal, anything else rejects it with that reason. Runs on the node's
// executor. May throw BadRequest (the goal did not decode) or anything (rejected with what()).
using GoalAcceptor = std::function<std::string(std::span<const std::byte> goal)>;
using GoalExecutor = std::function<void(RawActionGoal& goal)>;

std::shared_ptr<ActionServerCore> create_action_server(NodeImpl& node, std::string name, ActionTypes types,
                                                       GoalAcceptor accept, GoalExecutor execute,
                                                       ActionServerOptions options);
void close_action_server(const std::shared_ptr<ActionServerCore>& server);
ActionServerStats action_server_stats(const ActionServerCore& server);
std::vector<GoalStatus> action_server_goals(const ActionServerCore& server);
const std::string& action_server_name(const ActionServerCore& server);

std::shared_ptr<ActionClientCore> create_action_client(NodeImpl& node, std::string name, ActionTypes types);
void close_action_client(const std::shared_ptr<ActionClientCore>& client);
bool action_wait_for_server(ActionClientCore& client, std::chrono::milliseconds timeout);
// Sends the goal (`encode` fills `size` bytes); blocks until accepted, rejected or an error.
// On success the value is the goal's status (accepted or rejected). `feedback` (may be empty)
// gets each feedback payload of this goal, on the client's thread.
CallResult<GoalStatus> action_send_goal(ActionClientCore& client, std::size_t size,
                                        const std::function<void(std::span<std::byte>)>& encode,
                                        std::chrono::milliseconds timeout,
                                        std::function<void(std::span<const std::byte>)> feedback);
GoalStatus action_status(const ActionClientCore& client, const std::string& goal_id);
// Waits until the goal ended (or `timeout`), then fetches its result: the final status and
// the result bytes. Errors: timeout (still live), no_server (the goal is unknown here and in
// every status heard), server_gone (the server left while fetching).
CallResult<std::pair<GoalStatus, Bytes>> action_result(ActionClientCore& client, const std::string& goal_id,
                                                       std::chrono::milliseconds timeout);
CallResult<GoalStatus> action_cancel(ActionClientCore& client, const std::string& goal_id,
                                     std::chrono::milliseconds timeout);
std::vector<GoalStatus> action_client_goals(const ActionClientCore& client);
std::vector<ServerInfo> action_client_servers(const ActionClientCore& client);
const std::string& action_client_name(const ActionClientCore& client);
}  // namespace detail

// A goal on the server, typed. `execute` gets it; valid until `execute` returns.
template <class G, class F, class R>
class ActionGoal {
 public:
  ActionGoal(RawActionGoal& raw, G goal) : raw_(raw), goal_(std::move(goal)) {}
  const std::string& id() const { return raw_.id(); }
  const G& goal() const { return goal_; }
  bool cancel_requested() const { return raw_.cancel_requested(); }
  bool wait_for_cancel(std::chrono::nanoseconds timeout) const { return raw_.wait_for_cancel(timeout); }
  void publish_feedback(const F& feedback) { raw_.publish_feedback(encode(feedback)); }
  void succeed(const R& result) { raw_.finish(GoalState::succeeded, encode(result), ""); }
  void abort(const R& result, const std::string& why) { raw_.finish(GoalState::aborted, encode(result), why); }
  // Acknowledges a cancel request: the goal ends canceled (its message says who canceled it).
  void canceled(const R& result) { raw_.finish(GoalState::canceled, encode(result), ""); }
  RawActionGoal& raw() { return raw_; }

 private:
  template <class T>
  static Bytes encode(const T& m) {
    Bytes b(static_cast<std::size_t>(m.getEncodedSize()));
    m.encode(b.data(), 0, static_cast<int>(b.size()));
    return b;
  }
  RawActionGoal& raw_;
  G goal_;
};

// An action server. Destroying it cancels live goals and waits for their execute functions.
class ActionServer {
 public:
  ActionServer() = default;
  ActionServer(ActionServer&&) noexcept = default;
  ActionServer& operator=(ActionServer&& o) noexcept {
    reset();
    core_ = std::move(o.core_);
    return *this;
  }
  ~ActionServer() { reset(); }
  ActionServerStats stats() const { return detail::action_server_stats(*core_); }
  // Live goals, then retained ended ones.
  std::vector<GoalStatus> goals() const { return detail::action_server_goals(*core_); }
  const std::string& name() const { return detail::action_server_name(*core_); }
  explicit operator bool() const { return core_ != nullptr; }
  void reset() {
    if (core_) detail::close_action_server(core_);
    core_.reset();
  }

 private:
  friend class Node;
  explicit ActionServer(std::shared_ptr<detail::ActionServerCore> c) : core_(std::move(c)) {}
  std::shared_ptr<detail::ActionServerCore> core_;
};

namespace detail {
// What ActionClient<G, F, R> and RawActionClient have in common.
class ActionClientHandle {
 public:
  ActionClientHandle() = default;
  ActionClientHandle(ActionClientHandle&&) noexcept = default;
  ActionClientHandle& operator=(ActionClientHandle&& o) noexcept {
    reset();
    core_ = std::move(o.core_);
    return *this;
  }
  ~ActionClientHandle() { reset(); }
  // Returns once a server answered (goal, cancel and result paths all work), false after
  // `timeout`.
  bool wait_for_server(std::chrono::milliseconds timeout) const {
    return action_wait_for_server(*core_, timeout);
  }
  // The last status heard of a goal (own or from a server's status), unknown if none.
  GoalStatus status(const std::string& goal_id) const { return action_status(*core_, goal_id); }
  CallResult<GoalStatus> cancel(const std::string& goal_id, std::chrono::milliseconds timeout) {
    return action_cancel(*core_, goal_id, timeout);
  }
  // Goals this client sent or heard of, with their last status.
  std::vector<GoalStatus> goals() const { return action_client_goals(*core_); }
  std::vector<ServerInfo> servers() const { return action_client_servers(*core_); }
  const std::string& name() const { return action_client_name(*core_); }
  explicit operator bool() const { return core_ != nullptr; }
  // Stops the client; its goals go on at the server (canceled there after client_timeout).
  void reset() {
    if (core_) close_action_client(core_);
    core_.reset();
  }

 protected:
  explicit ActionClientHandle(std::shared_ptr<ActionClientCore> c) : core_(std::move(c)) {}
  std::shared_ptr<ActionClientCore> core_;
};
}  // namespace detail

// A goal sent by an ActionClient<G, F, R> (R: the result type; Bytes for raw).
template <class R>
class ClientGoal {
 public:
  ClientGoal() = default;
  const std::string& id() const { return status_.goal_id; }
  // Rejected goals come back as a ClientGoal too: check accepted().
  bool accepted() const { return status_.state != GoalState::rejected; }
  const std::string& message() const { return status_.message; }
  GoalStatus status() const { return core_ ? detail::action_status(*core_, id()) : status_; }
  // Waits for the end of the goal and its result (timeout: the goal is still live).
  CallResult<GoalOutcome<R>> wait(std::chrono::milliseconds timeout) const {
    if (!accepted()) return CallResult<GoalOutcome<R>>::success({status_, std::nullopt}, {});
    auto r = detail::action_result(*core_, id(), timeout);
    if (!r) return CallResult<GoalOutcome<R>>::failure(r.error(), r.message(), r.server());
    GoalOutcome<R> out{r.value().first, std::nullopt};
    const Bytes& b = r.value().second;
    if constexpr (std::is_same_v<R, Bytes>) {
      out.result = b;
    } else if (!b.empty() && b.size() <= static_cast<std::size_t>(INT32_MAX)) {
      R result;
      if (result.decode(b.data(), 0, static_cast<int>(b.size())) >= 0) out.result = std::move(result);
    }
    return CallResult<GoalOutcome<R>>::success(std::move(out), r.server());
  }
  CallResult<GoalStatus> cancel(std::chrono::milliseconds timeout) const {
    return detail::action_cancel(*core_, id(), timeout);
  }

 private:
  template <class, class, class>
  friend class ActionClient;
  friend class RawActionClient;
  ClientGoal(std::shared_ptr<detail::ActionClientCore> c, GoalStatus s) : core_(std::move(c)), status_(std::move(s)) {}
  std::shared_ptr<detail::ActionClientCore> core_;  // keeps the client alive while goals are held
  GoalStatus status_;                               // as sent (accepted or rejected)
};

template <class G, class F, class R>
class ActionClient : public detail::ActionClientHandle {
 public:
  ActionClient() = default;
  // Blocks until the server accepted or rejected the goal (a rejected goal is a success with
  // accepted() false), or an error: no_server, timeout, type_mismatch, bad_request.
  // `on_feedback` runs on the client's thread for each feedback of this goal.
  CallResult<ClientGoal<R>> send_goal(const G& goal, std::chrono::milliseconds timeout,
                                      std::function<void(const F&)> on_feedback = {}) {
    std::function<void(std::span<const std::byte>)> fb;
    if (on_feedback)
      fb = [f = std::move(on_feedback)](std::span<const std::byte> b) {
        F feedback;
        if (b.size() <= static_cast<std::size_t>(INT32_MAX) &&
            feedback.decode(b.data(), 0, static_cast<int>(b.size())) >= 0)
          f(feedback);
      };
    auto r = detail::action_send_goal(
        *core_, static_cast<std::size_t>(goal.getEncodedSize()),
        [&goal](std::span<std::byte> out) { goal.encode(out.data(), 0, static_cast<int>(out.size())); }, timeout,
        std::move(fb));
    if (!r) return CallResult<ClientGoal<R>>::failure(r.error(), r.message(), r.server());
    return CallResult<ClientGoal<R>>::success(ClientGoal<R>(core_, r.value()), r.server());
  }
  // The goal `goal_id` (sent by any client) as a handle: wait(), cancel(), status().
  ClientGoal<R> goal(const std::string& goal_id) const {
    return ClientGoal<R>(core_, GoalStatus{goal_id, GoalState::unknown, ""});
  }

 private:
  friend class Node;
  explicit ActionClient(std::shared_ptr<detail::ActionClientCore> c) : ActionClientHandle(std::move(c)) {}
};

// A client over raw bytes: goals, feedback and results are any payload; matches servers of
// any type.
class RawActionClient : public detail::ActionClientHandle {
 public:
  RawActionClient() = default;
  CallResult<ClientGoal<Bytes>> send_goal(std::span<const std::byte> goal, std::chrono::milliseconds timeout,
                                          std::function<void(std::span<const std::byte>)> on_feedback = {}) {
    auto r = detail::action_send_goal(
        *core_, goal.size(), [goal](std::span<std::byte> out) { std::copy(goal.begin(), goal.end(), out.begin()); },
        timeout, std::move(on_feedback));
    if (!r) return CallResult<ClientGoal<Bytes>>::failure(r.error(), r.message(), r.server());
    return CallResult<ClientGoal<Bytes>>::success(ClientGoal<Bytes>(core_, r.value()), r.server());
  }
  ClientGoal<Bytes> goal(const std::string& goal_id) const {
    return ClientGoal<Bytes>(core_, GoalStatus{goal_id, GoalState::unknown, ""});
  }

 private:
  friend class Node;
  explicit RawActionClient(std::shared_ptr<detail::ActionClientCore> c) : ActionClientHandle(std::move(c)) {}
};

}  // namespace lcmx

// --- Node's action members (declared in lcmx/core/node.hpp) -----------------------------------

namespace lcmx {

template <class G, class F, class R, class E>
ActionServer Node::create_action_server(std::string name, E&& execute) {
  return create_action_server<G, F, R>(std::move(name), std::forward<E>(execute), ActionServerOptions{});
}

template <class G, class F, class R, class E>
ActionServer Node::create_action_server(std::string name, E&& execute, ActionServerOptions options) {
  return create_action_server<G, F, R>(std::move(name), std::forward<E>(execute), [](const G&) { return true; },
                                       options);
}

template <class G, class F, class R, class E, class A>
ActionServer Node::create_action_server(std::string name, E&& execute, A&& accept) {
  return create_action_server<G, F, R>(std::move(name), std::forward<E>(execute), std::forward<A>(accept),
                                       ActionServerOptions{});
}

template <class G, class F, class R, class E, class A>
ActionServer Node::create_action_server(std::string name, E&& execute, A&& accept, ActionServerOptions options) {
  static_assert(std::is_invocable_v<E&, ActionGoal<G, F, R>&>,
                "create_action_server<G, F, R>: execute must be void(ActionGoal<G, F, R>&)");
  detail::ActionTypes types{G::getTypeName(), F::getTypeName(), R::getTypeName(),
                            G::getHash(),     F::getHash(),     R::getHash()};
  auto decode = [](std::span<const std::byte> in) {
    G goal;
    if (in.size() > static_cast<std::size_t>(INT32_MAX) || goal.decode(in.data(), 0, static_cast<int>(in.size())) < 0)
      throw detail::BadRequest(std::string("the goal did not decode as ") + G::getTypeName());
    return goal;
  };
  detail::GoalAcceptor a = [decode, f = std::forward<A>(accept)](std::span<const std::byte> in) mutable {
    static_assert(std::is_invocable_v<A&, const G&>,
                  "create_action_server: accept must be bool(const G&) or std::string(const G&)");
    const G goal = decode(in);
    if constexpr (std::is_same_v<std::invoke_result_t<A&, const G&>, bool>)
      return f(goal) ? std::string() : std::string("rejected by the server");
    else
      return std::string(f(goal));
  };
  detail::GoalExecutor e = [decode, f = std::forward<E>(execute)](RawActionGoal& raw) mutable {
    ActionGoal<G, F, R> goal(raw, decode(raw.goal()));
    f(goal);
  };
  return ActionServer(detail::create_action_server(*impl_, std::move(name), std::move(types), std::move(a),
                                                   std::move(e), options));
}

template <class G, class F, class R>
ActionClient<G, F, R> Node::create_action_client(std::string name) {
  return ActionClient<G, F, R>(detail::create_action_client(
      *impl_, std::move(name),
      {G::getTypeName(), F::getTypeName(), R::getTypeName(), G::getHash(), F::getHash(), R::getHash()}));
}

}  // namespace lcmx
