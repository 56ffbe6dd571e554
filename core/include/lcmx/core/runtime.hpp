// Runtime: the participant, one per process. It owns discovery, the transports and the
// registry of publishers and subscribers, and chooses the path of every pair by itself.
//
//   auto rt = lcmx::Runtime::create();            // options from the environment
//   auto node = rt.create_node("camera");
//   auto pub = node.advertise<lcmx_examples::image_t>("CAMERA");
//
// Lifetime: nodes and endpoints keep the runtime alive; when the last of them goes, the
// runtime says goodbye to the other participants and removes its shared memory.
// Errors: create() throws lcmx::Error(already_exists) if another Runtime lives in this
// process, lcmx::Error(transport) if the discovery group cannot be opened.
// Threads: all members are thread-safe. Event callbacks run on the discovery thread or on
// the thread that created the endpoint; keep them short.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "lcmx/core/node.hpp"
#include "lcmx/core/options.hpp"
#include "lcmx/core/stats.hpp"

namespace lcmx {

class Runtime {
 public:
  static Runtime create(RuntimeOptions options = RuntimeOptions::from_env());

  Runtime(Runtime&&) noexcept = default;
  Runtime& operator=(Runtime&&) noexcept = default;
  ~Runtime();

  Node create_node(std::string name, NodeOptions options = {});

  // Called for every Event (type mismatches, matches, participants). Replaces the previous.
  void on_event(std::function<void(const Event&)> callback);

  std::uint64_t participant_id() const;
  std::uint64_t host_id() const;
  // This participant's UDP groups: counters and receive filters, as of now.
  UdpStats udp_stats() const;

 private:
  explicit Runtime(std::shared_ptr<detail::RuntimeImpl> impl) : impl_(std::move(impl)) {}
  std::shared_ptr<detail::RuntimeImpl> impl_;
};

}  // namespace lcmx
