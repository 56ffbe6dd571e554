// The hook of lcmx::services (services/: service servers and clients, action servers and
// clients) into the runtime: exactly what they need beyond the public publish/subscribe API
// (detail/endpoint.hpp's create_publisher/add_subscriber/remove_subscriber, RawSubscriberCore,
// PublisherCore's loans, subscriber_stats). Services are built on publish/subscribe and
// discovery; this is the one narrow door they reach the runtime through, and nothing else in
// lcmx uses it. Installed, not stable.
//
// Ownership: NodeImpl is core's (opaque here); services hold it by std::shared_ptr (a node
// lives while anything holds it). Every function is thread-safe unless it says otherwise, and
// none throws but where it says so. Implemented in core/src/service_hook.cpp.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "lcmx/core/detail/endpoint.hpp"
#include "lcmx/core/stats.hpp"
#include "lcmx/core/subscriber.hpp"

namespace lcmx::detail {
class NodeImpl;
}  // namespace lcmx::detail

namespace lcmx::detail::hook {

// --- Identity ----------------------------------------------------------------------------------

// The participant (Runtime) `node` belongs to: its id in beacons and envelopes.
std::uint64_t participant_id(const NodeImpl& node) noexcept;
const std::string& node_name(const NodeImpl& node) noexcept;
// `node` shared (it is always owned by a shared_ptr).
std::shared_ptr<NodeImpl> shared(NodeImpl& node);
// A publisher's endpoint id (announced in beacons; a reply names its server's reply publisher
// by it).
std::uint64_t endpoint_id(const PublisherCore& publisher) noexcept;

// --- A node of lcmx's own, run by its own thread ------------------------------------------------

// A node of `beside`'s runtime with a manual executor (no thread of lcmx's: its owner runs
// it), registered with the runtime (shut down with it). Throws Error like Runtime::create_node.
std::shared_ptr<NodeImpl> create_manual_node(NodeImpl& beside, std::string name);
// Runs what is ready on `node` and waits up to `timeout` for more; returns the callbacks run.
// One thread at a time per manual node (its owner's).
std::size_t run_once(NodeImpl& node, std::chrono::nanoseconds timeout);
// Makes the current or next run_once() of `node` return as soon as it has run what is ready
// (the owner has something else to do). Any thread; never blocks.
void interrupt(NodeImpl& node) noexcept;
// The node was stopped (its runtime shut down, or stop()): nothing arrives any more.
bool stopped(const NodeImpl& node) noexcept;
// Stops `node`: run_once() returns at once from now on. Idempotent.
void stop(NodeImpl& node);
// From now on, `publisher`'s node is interrupt()ed whenever the number of subscribers
// matched with `publisher` changes (a service client probes a new server at once).
void interrupt_on_match(PublisherCore& publisher) noexcept;

// --- Runtime events, housekeeping, discovery ----------------------------------------------------

// Calls `tap` for every Event of `node`'s runtime, before Runtime::on_event's callback, on the
// thread that emits it, with no lcmx lock held but possibly discovery's delivery lock: it must
// be quick and must not call into the runtime (set a flag, interrupt a node). It may still run
// once after remove_event_tap() returned: capture weak pointers. Returns the tap's id.
std::uint64_t add_event_tap(NodeImpl& node, std::function<void(const Event&)> tap);
void remove_event_tap(NodeImpl& node, std::uint64_t id);
// Calls `job` about once a second on the runtime's receive thread with no lcmx lock held (it
// may call into the runtime, e.g. destroy a publisher); it must be quick. It may still run once
// after remove_housekeeping() returned: capture weak pointers. Returns the job's id.
std::uint64_t add_housekeeping(NodeImpl& node, std::function<void()> job);
void remove_housekeeping(NodeImpl& node, std::uint64_t id);
// Whether a participant of another process is known (its beacon not expired, either scope or
// a neighbour) and announces endpoint `endpoint`.
bool endpoint_announced(NodeImpl& node, std::uint64_t participant, std::uint64_t endpoint);
// Whether `participant` announces a subscriber of `channel` in its beacon (not expired, either
// scope or a neighbour's). Always true for `node`'s own participant: a process trusts itself.
bool subscriber_announced(NodeImpl& node, std::uint64_t participant, const std::string& channel);

// --- Who sent a message -------------------------------------------------------------------------

// The publisher of the pair a message came through (RawMessage::source's pair, PairCounters).
struct Sender {
  std::uint64_t participant = 0;
  // The publisher's endpoint id: exact on the intra and shm paths; over UDP the first UDP
  // match of `participant` on the channel (a datagram names its sender's participant, by its
  // address, not its endpoint); over the bridge, this host's bridge republisher.
  std::uint64_t endpoint = 0;
  Path path = Path::intra;
};
// Who sent `m`, during its callback (a raw subscriber's, or SubscriberCore::udp_inline: a
// message received over UDP offered on the receive thread first). nullopt when the message
// names no pair (made by hand) or its sender is no lcmx participant (a stock LCM program over
// UDP). Any thread, no lock: a pair's publisher is set before any message goes through it.
inline std::optional<Sender> sender_of(const RawMessage& m) noexcept {
  if (m.source == nullptr || m.source->pair == nullptr || m.source->pair->publisher_participant == 0)
    return std::nullopt;
  const auto& p = *m.source->pair;
  return Sender{p.publisher_participant, p.publisher_endpoint, p.path};
}

}  // namespace lcmx::detail::hook
