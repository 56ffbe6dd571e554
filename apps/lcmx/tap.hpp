// The "channel tap" shared by the tools that look at live traffic (lcmx echo, hz, bw, pub):
//  - ChannelMatcher: which channels a command takes (names, fnmatch globs, or regexes);
//  - StopSignals: SIGINT/SIGTERM (and a stop requested by any thread) as a file descriptor the
//    main thread waits on, so commands end cleanly (goodbye in discovery) and never by a
//    handler running in the middle of lcmx;
//  - Tap: a participant with one node subscribed raw to every matching channel on every path
//    (shm, bridges, UDP of other hosts, stock LCM senders);
//  - load_types(): the type path of --types / LCMX_TYPES_PATH.
#pragma once

#include <fnmatch.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <sys/eventfd.h>
#include <sys/signalfd.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <regex>
#include <stdexcept>
#include <string>
#include <vector>

#include "lcmx/core.hpp"
#include "lcmx/types/types.hpp"
#include "verb.hpp"

namespace lcmx::cli {

// Channel selection. Without `regex`, each pattern is a channel name or an fnmatch glob
// ("CAM_*", "POSE_?"), as LCMX_MIRROR and the bridge's carry globs; with `regex`, an
// ECMAScript regular expression that must match the whole name (as `lcmx record -c`).
// A channel is taken when any pattern matches. Throws std::regex_error for a bad expression.
class ChannelMatcher {
 public:
  ChannelMatcher(std::vector<std::string> patterns, bool regex) : regex_(regex) {
    for (auto& p : patterns) {
      if (regex_) compiled_.emplace_back(p, std::regex::ECMAScript | std::regex::optimize);
      else if (p.find_first_of("*?[") == std::string::npos) exact_.push_back(p);
      else globs_.push_back(p);
    }
  }
  bool operator()(const std::string& channel) const {
    for (const auto& r : compiled_)
      if (std::regex_match(channel, r)) return true;
    for (const auto& e : exact_)
      if (e == channel) return true;
    return matches_glob(channel);
  }
  bool matches_glob(const std::string& channel) const {
    for (const auto& p : globs_)
      if (::fnmatch(p.c_str(), channel.c_str(), 0) == 0) return true;
    return false;
  }
  // Patterns that are plain channel names (no glob characters, not --regex).
  const std::vector<std::string>& exact() const { return exact_; }
  bool has_patterns() const { return regex_ || !globs_.empty(); }

 private:
  bool regex_;
  std::vector<std::string> exact_, globs_;
  std::vector<std::regex> compiled_;
};

// Blocks SIGINT and SIGTERM in the calling thread (construct it on the main thread before the
// Runtime: lcmx's threads inherit the mask, so the signals are only ever read here) and ignores
// SIGPIPE (a closed stdout is a write error the command handles). request_stop() may be called
// from any thread (e.g. an executor callback that reached -n). Restores the mask on destruction
// (after consuming signals still pending).
class StopSignals {
 public:
  StopSignals() {
    sigset_t set;
    sigemptyset(&set);
    sigaddset(&set, SIGINT);
    sigaddset(&set, SIGTERM);
    ::pthread_sigmask(SIG_BLOCK, &set, &old_);
    sigfd_ = ::signalfd(-1, &set, SFD_CLOEXEC | SFD_NONBLOCK);
    evfd_ = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (sigfd_ < 0 || evfd_ < 0) throw std::runtime_error("cannot create signalfd/eventfd");
    ::signal(SIGPIPE, SIG_IGN);
  }
  StopSignals(const StopSignals&) = delete;
  StopSignals& operator=(const StopSignals&) = delete;
  ~StopSignals() {
    // Signals that came after the last wait (a second Ctrl-C) are consumed here: unblocked, they
    // would kill the process on its way out.
    signalfd_siginfo si{};
    while (::read(sigfd_, &si, sizeof si) == static_cast<ssize_t>(sizeof si)) {
    }
    ::close(sigfd_);
    ::close(evfd_);
    ::pthread_sigmask(SIG_SETMASK, &old_, nullptr);
  }

  // Any thread, async-signal-safe.
  void request_stop() noexcept {
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(evfd_, &one, sizeof one);
  }

  // Waits up to `timeout` (negative: forever) for a stop, or for `extra_fd` to be readable
  // (when >= 0; *extra_ready says so). Returns true once a stop was signalled or requested
  // (then and afterwards).
  bool wait(std::chrono::nanoseconds timeout, int extra_fd = -1, bool* extra_ready = nullptr) {
    if (extra_ready) *extra_ready = false;
    if (stopped_) return true;
    pollfd p[3] = {{sigfd_, POLLIN, 0}, {evfd_, POLLIN, 0}, {extra_fd, POLLIN, 0}};
    timespec ts{};
    timespec* tp = nullptr;
    if (timeout.count() >= 0) {
      ts.tv_sec = static_cast<time_t>(timeout.count() / 1'000'000'000);
      ts.tv_nsec = static_cast<long>(timeout.count() % 1'000'000'000);
      tp = &ts;
    }
    const int n = ::ppoll(p, extra_fd >= 0 ? 3 : 2, tp, nullptr);
    if (n <= 0) return false;
    if (p[0].revents & POLLIN) {
      signalfd_siginfo si{};
      if (::read(sigfd_, &si, sizeof si) == sizeof si) signal_ = static_cast<int>(si.ssi_signo);
      stopped_ = true;
    }
    if (p[1].revents & POLLIN) stopped_ = true;
    if (extra_ready && extra_fd >= 0 && (p[2].revents & (POLLIN | POLLHUP | POLLERR))) *extra_ready = true;
    return stopped_;
  }
  bool wait_until(std::chrono::steady_clock::time_point deadline) {
    return wait(std::max(deadline - std::chrono::steady_clock::now(), std::chrono::steady_clock::duration::zero()));
  }
  bool stopped() const { return stopped_; }
  int signal() const { return signal_; }  // the signal that stopped us, 0 if none

 private:
  sigset_t old_{};
  int sigfd_ = -1, evfd_ = -1;
  bool stopped_ = false;
  int signal_ = 0;
};

// A participant with one node that receives every channel `match` accepts, raw.
// Channels named exactly get an ordinary raw subscriber each (Node::subscribe_raw): it is
// announced in discovery at once, so a bridge of this host asks its peers for the channel
// before anything of it was published here. Globs and regexes use one channel subscription
// (Node::subscribe_channels), which takes channels as they show up on this host, on the UDP
// groups or in beacons; a large topic of another host that only bridges carry shows up as a
// republisher of this host's bridge, which announces its peers' catalogues while a participant
// here has a channel subscription (docs/bridge.md "Pattern subscribers").
// `on_message` runs on the node's executor thread (one at a time); RawMessage's view is valid
// only during the call. Throws lcmx::Error (or what RuntimeOptions::from_env throws).
class Tap {
 public:
  Tap(const Globals& g, const std::string& node_name, std::shared_ptr<const ChannelMatcher> match,
      std::function<void(const RawMessage&)> on_message, SubscriberOptions options = {}) {
    rt_.emplace(Runtime::create(runtime_options(g)));
    node_.emplace(rt_->create_node(node_name));
    for (const auto& ch : match->exact()) {
      bool dup = false;
      for (const auto& s : exact_subs_) dup = dup || s.channel() == ch;
      if (!dup) exact_subs_.push_back(node_->subscribe_raw(ch, on_message, options));
    }
    if (match->has_patterns()) {
      // Channels named exactly are left to their own subscribers.
      auto filter = [match](const std::string& ch) {
        for (const auto& e : match->exact())
          if (e == ch) return false;
        return (*match)(ch);
      };
      sub_ = node_->subscribe_channels(filter, std::move(on_message), options);
    }
  }
  Tap(const Tap&) = delete;
  Tap& operator=(const Tap&) = delete;
  // Stops receiving first (no callback runs after), then leaves (goodbye).
  ~Tap() {
    sub_.reset();
    exact_subs_.clear();
    node_.reset();
    rt_.reset();
  }
  // Per channel subscribed so far: its statistics.
  std::vector<std::pair<std::string, SubscriberStats>> stats() const {
    std::vector<std::pair<std::string, SubscriberStats>> out;
    for (const auto& s : exact_subs_) out.emplace_back(s.channel(), s.stats());
    if (sub_)
      for (auto& x : sub_.stats()) out.push_back(std::move(x));
    return out;
  }

 private:
  std::optional<Runtime> rt_;
  std::optional<Node> node_;
  std::vector<RawSubscriber> exact_subs_;
  ChannelSubscription sub_;
};

// The type path: --types values (each may be a ':' list), else LCMX_TYPES_PATH. Empty registry
// when neither is given. Throws types::Error / types::ParseError (file:line:col).
inline types::TypeRegistry load_types(const std::vector<std::string>& types_args) {
  const auto paths = types::TypeRegistry::paths_or_env(types_args);
  if (paths.empty()) return {};
  return types::TypeRegistry::load(paths);
}

inline std::string hex_fingerprint(std::uint64_t fp) {
  char b[24];
  std::snprintf(b, sizeof b, "0x%016llx", static_cast<unsigned long long>(fp));
  return b;
}

}  // namespace lcmx::cli
