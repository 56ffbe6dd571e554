// TopicPolicy: what decides a topic's class and whether it is mirrored — the configuration
// (RuntimeOptions: topic_class, mirror, mirror_channels) and the Message Bridges of this host
// (their `carried` globs, from host-scope beacons, set by Pairs::update_bridges).
//
// Threads: every member is thread-safe and cheap; its lock is a leaf, so publishers may ask
// with their publish_mu held.
#pragma once

#include <atomic>
#include <mutex>
#include <string>
#include <vector>

#include "lcmx/core/options.hpp"

namespace lcmx::detail {

class TopicPolicy {
 public:
  // `options` must outlive the policy (the runtime's own). Throws Error(invalid_argument) for
  // a bridge_carry or mirror_channels glob that is empty or longer than 255 characters.
  explicit TopicPolicy(const RuntimeOptions& options);

  // Configured class, else large when a bridge of this host carries the channel, else automatic.
  TopicClass class_of(const std::string& channel) const;
  // RuntimeOptions::mirror, or a mirror_channels glob matches.
  bool mirrored(const std::string& channel) const;
  // A Message Bridge runs on this host (or this participant is one): large topics go to
  // other hosts through it, never as UDP fragments.
  bool bridge_on_host() const { return options_.bridge || bridge_seen_.load(); }
  // The bridges of this host now: whether one is seen, and the globs they carry (ours
  // included). Returns true if `seen` changed.
  bool set_bridges(bool seen, std::vector<std::string> globs);

 private:
  const RuntimeOptions& options_;
  mutable std::mutex mu_;                 // guards carried_
  std::vector<std::string> carried_;      // globs carried by this host's bridges (and ours)
  std::atomic<bool> bridge_seen_{false};  // a same-host participant has FLAG_BRIDGE
};

}  // namespace lcmx::detail
