// lcmx/core/detail/service_hook.hpp: what lcmx::services (services/) may ask of the runtime
// beyond publish/subscribe. Nothing else in lcmx calls these.
#include "lcmx/core/detail/service_hook.hpp"

#include "internal.hpp"

namespace lcmx::detail::hook {

std::uint64_t participant_id(const NodeImpl& node) noexcept { return node.runtime->participant_id; }
const std::string& node_name(const NodeImpl& node) noexcept { return node.name; }
std::shared_ptr<NodeImpl> shared(NodeImpl& node) { return node.shared_from_this(); }
std::uint64_t endpoint_id(const PublisherCore& publisher) noexcept {
  return static_cast<const PublisherImpl&>(publisher).id;  // every PublisherCore is one
}

std::shared_ptr<NodeImpl> create_manual_node(NodeImpl& beside, std::string name) {
  NodeOptions o;
  o.executor.kind = ExecutorKind::manual;
  auto node = std::make_shared<NodeImpl>(beside.runtime, std::move(name), o);
  node->start();
  beside.runtime->add_node(node);
  return node;
}
std::size_t run_once(NodeImpl& node, std::chrono::nanoseconds timeout) { return node.run_once(timeout); }
void interrupt(NodeImpl& node) noexcept { node.interrupt(); }
bool stopped(const NodeImpl& node) noexcept { return node.stopped(); }
void stop(NodeImpl& node) { node.stop(); }
void interrupt_on_match(PublisherCore& publisher) noexcept {
  static_cast<PublisherImpl&>(publisher).interrupt_on_match.store(true);
}

std::uint64_t add_event_tap(NodeImpl& node, std::function<void(const Event&)> tap) {
  return node.runtime->add_event_tap(std::move(tap));
}
void remove_event_tap(NodeImpl& node, std::uint64_t id) { node.runtime->remove_event_tap(id); }
std::uint64_t add_housekeeping(NodeImpl& node, std::function<void()> job) {
  return node.runtime->add_housekeeping(std::move(job));
}
void remove_housekeeping(NodeImpl& node, std::uint64_t id) { node.runtime->remove_housekeeping(id); }
bool endpoint_announced(NodeImpl& node, std::uint64_t participant, std::uint64_t endpoint) {
  return node.runtime->endpoint_announced(participant, endpoint);
}
bool subscriber_announced(NodeImpl& node, std::uint64_t participant, const std::string& channel) {
  if (participant == node.runtime->participant_id) return true;  // this process trusts itself
  for (const auto& e : node.runtime->peers.endpoints_on(channel, lcmx_msgs::endpoint_t::KIND_SUBSCRIBER))
    if (static_cast<std::uint64_t>(e.participant) == participant) return true;
  return false;
}

}  // namespace lcmx::detail::hook
