// Node: a named unit of a program inside a participant (like a ROS 2 node). It creates
// publishers and subscribers and owns the executor that runs its subscribers' callbacks.
//
// Threading rule (ExecutorOptions, options.hpp):
//  - own_threads, threads = 1 (default): one thread per node runs all its callbacks, one at
//    a time; messages of one publisher are delivered in publish order.
//  - own_threads, threads = N > 1: different subscriptions' callbacks may run in parallel;
//    one subscription's callbacks still run one at a time and in order per publisher.
//  - manual: no thread; callbacks run inside spin_once(), on the caller's thread.
// Errors: advertise/subscribe throw lcmx::Error (channel_too_long, invalid_argument).
// Move-only handle; the node lives while the handle or any of its endpoints does.
#pragma once

#include <chrono>
#include <functional>
#include <memory>
#include <string>
#include <type_traits>

#include "lcmx/core/action.hpp"
#include "lcmx/core/options.hpp"
#include "lcmx/core/publisher.hpp"
#include "lcmx/core/service.hpp"
#include "lcmx/core/subscriber.hpp"

namespace lcmx {

class Node {
 public:
  Node(Node&&) noexcept = default;
  Node& operator=(Node&&) noexcept = default;
  ~Node();

  template <class T>
  Publisher<T> advertise(std::string channel, PublisherOptions options = {}) {
    return Publisher<T>(
        detail::create_publisher(*impl_, std::move(channel), detail::type_info_of<T>(), options));
  }

  // callback: void(const T&) or void(const std::shared_ptr<const T>&).
  template <class T, class F>
  Subscriber<T> subscribe(std::string channel, F&& callback, SubscriberOptions options = {}) {
    using Core = detail::TypedSubscriberCore<T>;
    std::shared_ptr<detail::SubscriberCore> core;
    if constexpr (std::is_invocable_v<F&, const std::shared_ptr<const T>&>) {
      core = std::make_shared<Core>(std::move(channel), options,
                                    typename Core::SharedCallback(std::forward<F>(callback)),
                                    nullptr);
    } else {
      static_assert(std::is_invocable_v<F&, const T&>,
                    "subscribe<T>: callback must take const T& or std::shared_ptr<const T>");
      core = std::make_shared<Core>(std::move(channel), options, nullptr,
                                    typename Core::RefCallback(std::forward<F>(callback)));
    }
    detail::add_subscriber(*impl_, core);
    return Subscriber<T>(std::move(core));
  }

  RawPublisher advertise_raw(std::string channel, PublisherOptions options = {});
  RawSubscriber subscribe_raw(std::string channel, std::function<void(const RawMessage&)> callback,
                              SubscriberOptions options = {});
  // A raw subscriber that announces a type (name and lcm-gen fingerprint) in discovery: it
  // matches publishers of that type only (others get a type-mismatch error) and gets their
  // encodings as bytes. Used by the Python binding (lcm-gen's Python types).
  RawSubscriber subscribe_raw(std::string channel, const std::string& type_name,
                              std::int64_t fingerprint,
                              std::function<void(const RawMessage&)> callback,
                              SubscriberOptions options = {});
  // A raw publisher that announces a type (name and lcm-gen fingerprint) in discovery, so
  // typed subscribers of that type match it and others get a type-mismatch error; it
  // publishes encodings (bytes starting with that fingerprint). Used by `lcmx play`.
  RawPublisher advertise_raw(std::string channel, const std::string& type_name,
                             std::int64_t fingerprint, PublisherOptions options = {});

  // Subscribes raw to every channel whose name `filter` accepts, on every path: channels of
  // lcmx publishers in this process, on this host (shm, bridges) and on other hosts (UDP),
  // and channels that stock LCM programs send on either group (from their first message on).
  // One raw subscriber (with `options`) per channel is created when the channel is first
  // seen, at most `max_channels` (more are counted as refused and logged once); they show in
  // discovery like any subscriber (`lcmx topics`). The discovery channel LCMX_BEACON is never
  // delivered. Used by `lcmx record`.
  // `filter` is called once per new channel name, under the runtime's lock, from any lcmx
  // thread: keep it fast, thread-safe, and never call lcmx from it. `callback` runs on this
  // node's executor like a raw subscriber's (RawMessage::channel names the channel).
  ChannelSubscription subscribe_channels(std::function<bool(const std::string&)> filter,
                                         std::function<void(const RawMessage&)> callback,
                                         SubscriberOptions options = {},
                                         std::size_t max_channels = 10000);

  // Services (service.hpp). `handler`: Resp(const Req&) or void(const Req&, Resp&); it runs
  // on this node's executor. What it throws reaches the client as CallErrc::handler_failed.
  // Throws Error(invalid_argument / channel_too_long) for a bad name (at most 43 bytes).
  template <class Req, class Resp, class F>
  Service create_service(std::string name, F&& handler) {
    if constexpr (std::is_constructible_v<bool, const std::remove_reference_t<F>&>)
      if (!static_cast<bool>(handler))
        throw Error(Errc::invalid_argument, "create_service '" + name + "': empty handler");
    detail::ServiceTypes types{Req::getTypeName(), Resp::getTypeName(), Req::getHash(),
                               Resp::getHash()};
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
  // A server over raw bytes. `handler` gets the request payload (valid during the call) and
  // either returns the response, Bytes(std::span<const std::byte>), or writes it in place,
  // void(std::span<const std::byte>, ResponseWriter&) (no copy: see ResponseWriter).
  template <class F>
  Service create_service_raw(std::string name, F&& handler) {
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
  Client<Req, Resp> create_client(std::string name) {
    return Client<Req, Resp>(detail::create_client(
        *impl_, std::move(name),
        {Req::getTypeName(), Resp::getTypeName(), Req::getHash(), Resp::getHash()}));
  }
  // A client over raw bytes: matches servers of any type.
  RawClient create_client_raw(std::string name);
  // A raw server / client that announce lcm-gen types (names and fingerprints, as typed ones
  // do), so a peer of other types gets CallErrc::type_mismatch. Bytes are not checked here.
  // Used by the Python binding (lcm-gen's Python types).
  Service create_service_raw(std::string name, detail::ServiceTypes types, detail::ServerHandler handler);
  RawClient create_client_raw(std::string name, detail::ServiceTypes types);

  // Actions (action.hpp). `execute`: void(ActionGoal<G, F, R>&), on a thread of its own per
  // goal. `accept` (optional): bool(const G&), or std::string(const G&) ("" accepts, anything
  // else rejects with that reason), on this node's executor; without it every goal is
  // accepted (up to ActionServerOptions::max_goals at once). Throws Error(invalid_argument /
  // channel_too_long) for a bad name (at most 36 bytes).
  template <class G, class F, class R, class E>
  ActionServer create_action_server(std::string name, E&& execute, ActionServerOptions options = {}) {
    return create_action_server<G, F, R>(std::move(name), std::forward<E>(execute),
                                         [](const G&) { return true; }, options);
  }
  template <class G, class F, class R, class E, class A>
  ActionServer create_action_server(std::string name, E&& execute, A&& accept, ActionServerOptions options = {}) {
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
  // Over raw bytes: `execute` void(RawActionGoal&); `accept` as GoalAcceptor (may be empty).
  ActionServer create_action_server_raw(std::string name, std::function<void(RawActionGoal&)> execute,
                                        std::function<std::string(std::span<const std::byte>)> accept = {},
                                        ActionServerOptions options = {});
  template <class G, class F, class R>
  ActionClient<G, F, R> create_action_client(std::string name) {
    return ActionClient<G, F, R>(detail::create_action_client(
        *impl_, std::move(name),
        {G::getTypeName(), F::getTypeName(), R::getTypeName(), G::getHash(), F::getHash(), R::getHash()}));
  }
  RawActionClient create_action_client_raw(std::string name);
  // The same with lcm-gen types announced (Python binding): peers of other types get
  // CallErrc::type_mismatch.
  ActionServer create_action_server_raw(std::string name, detail::ActionTypes types,
                                        std::function<void(RawActionGoal&)> execute,
                                        std::function<std::string(std::span<const std::byte>)> accept,
                                        ActionServerOptions options);
  RawActionClient create_action_client_raw(std::string name, detail::ActionTypes types);

  // Manual executor only: waits up to `timeout` for messages and runs the callbacks of what
  // arrived. Returns the number of callbacks run. Throws Error(invalid_argument) on a node
  // with its own threads.
  std::size_t spin_once(std::chrono::nanoseconds timeout);

  const std::string& name() const;

 private:
  friend class Runtime;
  explicit Node(std::shared_ptr<detail::NodeImpl> impl) : impl_(std::move(impl)) {}
  std::shared_ptr<detail::NodeImpl> impl_;
};

}  // namespace lcmx
