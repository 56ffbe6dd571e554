// Subscriber<T> for an lcm-gen type T, and RawSubscriber for bytes.
//
// Callbacks run on the subscriber's node executor (see node.hpp): by default one thread per
// node, so a node's callbacks never run concurrently, and messages of one publisher arrive
// in publish order. A typed callback may take `const T&` (valid during the call; its
// storage is reused) or `std::shared_ptr<const T>` (keep it as long as you like; in-process
// publishers hand over their own pointer, no copy).
// Destroying the handle unsubscribes and waits for a running callback of it to finish
// (unless destroyed from inside that callback).
#pragma once

#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <type_traits>
#include <utility>
#include <vector>

#include <spdlog/spdlog.h>

#include "lcmx/core/detail/endpoint.hpp"
#include "lcmx/core/stats.hpp"

namespace lcmx {

namespace detail {
SubscriberStats subscriber_stats(const SubscriberCore& core);
bool wait_for_publishers(const SubscriberCore& core, std::size_t n,
                         std::chrono::milliseconds timeout);

template <class T>
class TypedSubscriberCore final : public SubscriberCore {
 public:
  using SharedCallback = std::function<void(const std::shared_ptr<const T>&)>;
  using RefCallback = std::function<void(const T&)>;

  TypedSubscriberCore(std::string channel, SubscriberOptions o, SharedCallback shared,
                      RefCallback ref)
      : SubscriberCore(std::move(channel), type_info_of<T>(), o),
        shared_(std::move(shared)), ref_(std::move(ref)) {}

  bool deliver_intra(const IntraItem& item) override {
    if (!item.type->carries_bytes() && item.type->fingerprint == T::getHash()) {
      auto p = std::static_pointer_cast<const T>(item.object);
      if (shared_) shared_(p); else ref_(*p);
      return true;
    }
    return deliver_bytes(item.bytes);
  }

  bool deliver_bytes(std::span<const std::byte> bytes, shm::ReadSample* sample = nullptr,
                     bool* torn = nullptr, const PairCounters* = nullptr) override {
    // Reuse the last decoded object when nobody kept it: decoding into the same object
    // reuses its buffers (no allocation for same-sized images).
    if (!scratch_ || scratch_.use_count() > 1) scratch_ = std::make_shared<T>();
    if (bytes.size() > static_cast<std::size_t>(INT32_MAX) ||
        scratch_->decode(bytes.data(), 0, static_cast<int>(bytes.size())) < 0) {
      if (decode_errors.fetch_add(1) == 0)
        spdlog::error("lcmx: channel '{}': a message did not decode as {} (wrong type?)",
                      channel(), T::getTypeName());
      return false;
    }
    // Decoded from shared memory: if the slot was rewritten (or the file truncated) while we
    // read it, the object may mix two messages. Withheld; the caller counts a drop.
    if (sample != nullptr && !sample->intact()) {
      if (torn != nullptr) *torn = true;
      return false;
    }
    if (shared_) shared_(std::const_pointer_cast<const T>(scratch_)); else ref_(*scratch_);
    return true;
  }

 private:
  SharedCallback shared_;
  RefCallback ref_;
  std::shared_ptr<T> scratch_;
};
}  // namespace detail

template <class T>
class Subscriber {
 public:
  Subscriber() = default;
  Subscriber(Subscriber&&) noexcept = default;
  Subscriber& operator=(Subscriber&& o) noexcept {
    reset();
    core_ = std::move(o.core_);
    return *this;
  }
  ~Subscriber() { reset(); }

  SubscriberStats stats() const { return detail::subscriber_stats(*core_); }
  std::size_t publisher_count() const { return stats().publishers.size(); }
  // Waits until at least n publishers are matched. Returns false on timeout.
  bool wait_for_publishers(std::size_t n, std::chrono::milliseconds timeout) const {
    return detail::wait_for_publishers(*core_, n, timeout);
  }
  const std::string& channel() const { return core_->channel(); }
  explicit operator bool() const { return core_ != nullptr; }
  void reset() {
    if (core_) detail::remove_subscriber(core_);
    core_.reset();
  }

 private:
  friend class Node;
  explicit Subscriber(std::shared_ptr<detail::SubscriberCore> c) : core_(std::move(c)) {}
  std::shared_ptr<detail::SubscriberCore> core_;
};

// The bytes of a RawMessage kept beyond its callback (RawMessage::retain()). Move-only in
// spirit (copies share `owner`); destroy it on any thread. `data` stays valid and unchanged
// while `owner` lives.
struct RetainedBytes {
  std::span<const std::byte> data;
  std::shared_ptr<const void> owner;  // keeps `data` alive
  // True: `data` is the message's own storage, no byte copied (a pinned shared-memory slot,
  // or the in-process/UDP message's buffer). False: a private copy (see retain()).
  bool zero_copy = false;
};

namespace detail {
// Where RawMessage::retain() takes the message from (set by the runtime; nullptr: copy), and
// the pair it came through.
struct RetainSource {
  // The publisher->subscriber pair the message came through: who sent it (its publisher's
  // participant and endpoint, and the path). nullptr when unknown (a RawMessage made by hand).
  const PairCounters* pair = nullptr;
  shm::ReadSample* sample = nullptr;           // shm path: detached on the first retain()
  std::shared_ptr<const void> owner;           // intra-process/UDP path: the shared buffer
  std::shared_ptr<const shm::DetachedSample> detached;  // after a successful detach
  std::shared_ptr<const Bytes> copy;           // after a copying retain()
  std::uint64_t copies = 0;                    // messages retain() had to copy
};
}  // namespace detail

// A received raw message: a zero-copy view (into shared memory for the shm path), valid only
// during the callback.
struct RawMessage {
  std::string_view channel;
  std::span<const std::byte> data;
  detail::RetainSource* source = nullptr;  // the runtime's; see retain()

  // Keeps the message beyond the callback. Call only during the callback, on its thread.
  // Shared-memory path: the pinned slot itself (zero_copy): the slot stays pinned, and the
  // publisher skips it, until the result (and every copy of its owner) is destroyed, on any
  // thread; it stays valid after the subscriber, its publisher match or the publisher are
  // gone. At most shm::Reader::kMaxDetached messages per publisher are held this way; beyond
  // that (a slow holder) retain() copies the bytes (zero_copy false), so a slow holder can
  // never make this subscriber stop receiving nor hold more than kMaxDetached slots of a
  // publisher. Intra-process and UDP paths: shares the received buffer (zero_copy true);
  // a typed in-process publisher's encoded bytes: copied. Calling it again in the same
  // callback returns the same bytes. Throws std::bad_alloc only.
  RetainedBytes retain() const;
  // As retain(), but never copies: nullopt where retain() would copy (kMaxDetached samples of
  // this publisher held, encoded bytes, or no source). May be called again later in the same
  // callback (e.g. after waiting for a holder to release a sample). Never throws.
  std::optional<RetainedBytes> retain_zero_copy() const noexcept;
  // The publisher's class of this very message, as it routed it: true when large (it leaves
  // the message to this host's Message Bridges to reach other hosts), false when small (it
  // sends it over UDP where other hosts want it). Shared-memory path only (lcmx publishers
  // stamp it into the slot); nullopt on the other paths. Any thread, during the callback.
  std::optional<bool> published_large() const noexcept;
};

using RawSubscriber = Subscriber<void>;

namespace detail {
class RawSubscriberCore final : public SubscriberCore {
 public:
  // `type`: raw_type_info(), or an announced_type_info() for a raw subscriber that announces
  // a type in discovery (service envelopes) and matches only publishers of that type.
  RawSubscriberCore(std::string channel, SubscriberOptions o,
                    std::function<void(const RawMessage&)> cb,
                    const TypeInfo& type = raw_type_info());
  bool deliver_intra(const IntraItem& item) override;
  bool deliver_bytes(std::span<const std::byte> bytes, shm::ReadSample* sample = nullptr,
                     bool* torn = nullptr, const PairCounters* pair = nullptr) override;
  // retain() calls that copied (pins exhausted, or encoded from a typed publisher).
  std::uint64_t retain_copies() const noexcept { return copies_.load(std::memory_order_relaxed); }

 private:
  bool deliver(std::span<const std::byte> bytes, RetainSource& src, shm::ReadSample* sample,
               bool* torn);
  std::function<void(const RawMessage&)> cb_;
  Bytes scratch_;
  std::atomic<std::uint64_t> copies_{0};
};

struct ChannelSubscriptionCore;
void remove_channel_subscription(const std::shared_ptr<ChannelSubscriptionCore>& core);
std::vector<std::pair<std::string, SubscriberStats>> channel_subscription_stats(
    const ChannelSubscriptionCore& core);
std::uint64_t channel_subscription_refused(const ChannelSubscriptionCore& core);
}  // namespace detail

// Raw subscription to every channel whose name a filter accepts (Node::subscribe_channels):
// one raw subscriber per channel, created as channels appear. Destroying the handle removes
// them all and waits for running callbacks (as Subscriber does).
class ChannelSubscription {
 public:
  ChannelSubscription() = default;
  ChannelSubscription(ChannelSubscription&&) noexcept = default;
  ChannelSubscription& operator=(ChannelSubscription&& o) noexcept {
    reset();
    core_ = std::move(o.core_);
    return *this;
  }
  ~ChannelSubscription() { reset(); }

  // Per channel subscribed so far: its statistics (drops per publisher pair, ...).
  std::vector<std::pair<std::string, SubscriberStats>> stats() const {
    return detail::channel_subscription_stats(*core_);
  }
  // Channels the filter accepted but that were not subscribed (over max_channels).
  std::uint64_t refused() const { return detail::channel_subscription_refused(*core_); }
  explicit operator bool() const { return core_ != nullptr; }
  void reset() {
    if (core_) detail::remove_channel_subscription(core_);
    core_.reset();
  }

 private:
  friend class Node;
  explicit ChannelSubscription(std::shared_ptr<detail::ChannelSubscriptionCore> c)
      : core_(std::move(c)) {}
  std::shared_ptr<detail::ChannelSubscriptionCore> core_;
};

}  // namespace lcmx
