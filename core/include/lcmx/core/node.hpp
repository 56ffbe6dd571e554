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
//
// Services and actions (create_service, create_client, create_action_server,
// create_action_client) are a layer above this library, lcmx::services (services/): their
// members are declared here and defined there (lcmx/services/service.hpp, action.hpp, and
// services/src). Include <lcmx/core.hpp> and link lcmx::core, which bring both.
#pragma once

#include <chrono>
#include <cstddef>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <type_traits>

#include "lcmx/core/error.hpp"
#include "lcmx/core/options.hpp"
#include "lcmx/core/publisher.hpp"
#include "lcmx/core/subscriber.hpp"

namespace lcmx {

// lcmx::services' types (lcmx/services/service.hpp, action.hpp).
class Service;
class RawClient;
template <class Req, class Resp>
class Client;
class ResponseWriter;
class ActionServer;
class RawActionClient;
template <class G, class F, class R>
class ActionClient;
class RawActionGoal;
struct ActionServerOptions;
namespace detail {
struct ServiceTypes;
struct ActionTypes;
}  // namespace detail

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

  // Services (lcmx/services/service.hpp). `handler`: Resp(const Req&) or
  // void(const Req&, Resp&); it runs on this node's executor. What it throws reaches the client
  // as CallErrc::handler_failed. Throws Error(invalid_argument / channel_too_long) for a bad
  // name (at most 43 bytes).
  template <class Req, class Resp, class F>
  Service create_service(std::string name, F&& handler);
  // A server over raw bytes. `handler` gets the request payload (valid during the call) and
  // either returns the response, Bytes(std::span<const std::byte>), or writes it in place,
  // void(std::span<const std::byte>, ResponseWriter&) (no copy: see ResponseWriter).
  template <class F>
  Service create_service_raw(std::string name, F&& handler);

  template <class Req, class Resp>
  Client<Req, Resp> create_client(std::string name);
  // A client over raw bytes: matches servers of any type.
  RawClient create_client_raw(std::string name);
  // A raw server / client that announce lcm-gen types (names and fingerprints, as typed ones
  // do), so a peer of other types gets CallErrc::type_mismatch. Bytes are not checked here.
  // Used by the Python binding (lcm-gen's Python types). `handler` is a
  // detail::ServerHandler.
  Service create_service_raw(std::string name, detail::ServiceTypes types,
                             std::function<void(std::span<const std::byte>, ResponseWriter&)> handler);
  RawClient create_client_raw(std::string name, detail::ServiceTypes types);

  // Actions (lcmx/services/action.hpp). `execute`: void(ActionGoal<G, F, R>&), on a thread of
  // its own per goal. `accept` (optional): bool(const G&), or std::string(const G&) (""
  // accepts, anything else rejects with that reason), on this node's executor; without it
  // every goal is accepted (up to ActionServerOptions::max_goals at once). `options` default
  // to ActionServerOptions{}. Throws Error(invalid_argument / channel_too_long) for a bad name
  // (at most 36 bytes).
  template <class G, class F, class R, class E>
  ActionServer create_action_server(std::string name, E&& execute);
  template <class G, class F, class R, class E>
  ActionServer create_action_server(std::string name, E&& execute, ActionServerOptions options);
  template <class G, class F, class R, class E, class A>
  ActionServer create_action_server(std::string name, E&& execute, A&& accept);
  template <class G, class F, class R, class E, class A>
  ActionServer create_action_server(std::string name, E&& execute, A&& accept, ActionServerOptions options);
  // Over raw bytes: `execute` void(RawActionGoal&); `accept` as detail::GoalAcceptor (may be
  // empty: every goal accepted).
  ActionServer create_action_server_raw(std::string name, std::function<void(RawActionGoal&)> execute);
  ActionServer create_action_server_raw(std::string name, std::function<void(RawActionGoal&)> execute,
                                        std::function<std::string(std::span<const std::byte>)> accept);
  ActionServer create_action_server_raw(std::string name, std::function<void(RawActionGoal&)> execute,
                                        std::function<std::string(std::span<const std::byte>)> accept,
                                        ActionServerOptions options);
  template <class G, class F, class R>
  ActionClient<G, F, R> create_action_client(std::string name);
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
