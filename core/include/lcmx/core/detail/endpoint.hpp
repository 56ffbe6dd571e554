// Internals shared by the Publisher/Subscriber templates and the runtime. Installed, not
// stable: use publisher.hpp / subscriber.hpp / raw.hpp.
#pragma once

#include <atomic>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <span>
#include <string>
#include <vector>

#include "lcmx/shm/segment.hpp"

#include "lcmx/core/error.hpp"
#include "lcmx/core/options.hpp"
#include "lcmx/core/stats.hpp"

namespace lcmx {
class Runtime;
struct RawMessage;
namespace detail {

class RuntimeImpl;
class NodeImpl;
struct SubscriberState;

// What a publisher or subscriber knows about its message type. Raw byte channels have
// fingerprint 0 and no encode functions; they match any fingerprint. A raw publisher may
// announce a type (name + fingerprint, e.g. `lcmx play` replaying a log): it then matches
// like a typed one, but still carries bytes (no encode functions).
struct TypeInfo {
  std::string name;
  std::int64_t fingerprint = 0;
  // Typed only: size of the LCM encoding (with fingerprint) and encode into `out`.
  std::size_t (*encoded_size)(const void* object) = nullptr;
  void (*encode)(const void* object, std::byte* out, std::size_t size) = nullptr;
  bool raw() const { return fingerprint == 0; }
  // The publisher's intra-process objects are bytes (Bytes), not a T.
  bool carries_bytes() const { return encode == nullptr; }
};

template <class T>
const TypeInfo& type_info_of() {
  static const TypeInfo info{
      T::getTypeName(), T::getHash(),
      [](const void* o) { return static_cast<std::size_t>(static_cast<const T*>(o)->getEncodedSize()); },
      [](const void* o, std::byte* out, std::size_t size) {
        static_cast<const T*>(o)->encode(out, 0, static_cast<int>(size));
      }};
  return info;
}

// Raw payloads travel intra-process as a shared immutable byte vector.
using Bytes = std::vector<std::byte>;

// Per publisher->subscriber pair statistics (see lcmx_msgs::match_t), and the pair's
// publisher: set when the match is made, before any message goes through it, and never
// changed after (so read without a lock by whoever holds a message of the pair). 0 and 0 for
// a sender that is no lcmx participant (a stock LCM program over UDP). Over UDP a message
// names its sender's participant (its address) but not the endpoint: a participant's
// messages on one channel all come through its first UDP match there.
struct PairCounters {
  std::atomic<std::uint64_t> received{0};
  std::atomic<std::uint64_t> drops{0};
  std::uint64_t publisher_participant = 0;
  std::uint64_t publisher_endpoint = 0;
  Path path = Path::intra;
};

// A message handed to a subscriber on the intra-process path (or queued from UDP).
struct IntraItem {
  // const T (a typed publisher's object), or, when type->carries_bytes(), whatever owns
  // `bytes` (a Bytes copy, a UDP reassembly buffer).
  std::shared_ptr<const void> object;
  const TypeInfo* type = nullptr;  // the publisher's type
  std::shared_ptr<PairCounters> pair;
  std::span<const std::byte> bytes;  // type->carries_bytes(): the message, kept alive by `object`
};

// Type-erased subscriber. Owned by shared_ptr (Subscriber handle, node executor, runtime).
// deliver_* run on the node's executor thread(s), never concurrently for one subscriber.
class SubscriberCore {
 public:
  SubscriberCore(std::string channel, const TypeInfo& type, SubscriberOptions options)
      : channel_(std::move(channel)), type_(type), options_(options) {}
  virtual ~SubscriberCore() = default;

  // Typed subscribers: the publisher's object (same type) or raw bytes to decode.
  // Raw subscribers: bytes, or a typed object to encode. Returns false if undecodable.
  virtual bool deliver_intra(const IntraItem& item) = 0;
  // `sample`: the shm sample `bytes` views (nullptr: bytes of our own). Typed subscribers
  // decode, then check sample->intact() before the callback; raw subscribers check it before
  // and after their zero-copy callback. A sample found not intact sets `*torn` (a drop for
  // the caller to count); withheld unless found only after a raw callback.
  // A raw subscriber's callback may detach `sample` (RawMessage::retain): *sample is then
  // empty when deliver_bytes returns. `pair`: the pair the bytes came through (who sent
  // them, RawMessage's source), or nullptr.
  virtual bool deliver_bytes(std::span<const std::byte> bytes,
                             shm::ReadSample* sample = nullptr, bool* torn = nullptr,
                             const PairCounters* pair = nullptr) = 0;

  const std::string& channel() const { return channel_; }
  const TypeInfo& type() const { return type_; }
  const SubscriberOptions& options() const { return options_; }

  std::uint64_t id = 0;                   // endpoint id, set by the runtime
  std::shared_ptr<SubscriberState> state;  // the runtime's side (matches, queue), core/src
  // Set before the subscriber is added, never after. A message received over UDP is first
  // offered to it, on the runtime's receive thread (concurrently with deliver_* on the
  // executor): true takes it (counted as received and delivered), false queues it for the
  // executor as usual. lcmx's own service clients use it to complete a blocking call where its
  // reply arrives, without a hand-over through the client's thread. Must be short, never block
  // or publish, and must not throw.
  std::function<bool(const RawMessage&)> udp_inline;
  std::atomic<std::uint64_t> delivered{0};
  std::atomic<std::uint64_t> decode_errors{0};

 private:
  std::string channel_;
  const TypeInfo& type_;
  SubscriberOptions options_;
};

const TypeInfo& raw_type_info();
// A byte-carrying TypeInfo that announces `name` and `fingerprint`; interned (lives forever,
// one per distinct pair).
const TypeInfo& announced_type_info(const std::string& name, std::int64_t fingerprint);

// Copies in, for intra-process delivery of raw bytes.
std::shared_ptr<const Bytes> make_bytes(std::span<const std::byte> data);

}  // namespace detail
}  // namespace lcmx


namespace lcmx::detail {

// Type-erased publisher, implemented in core/src. Thread-safe: publish calls are serialised.
class PublisherCore {
 public:
  virtual ~PublisherCore() = default;
  // Typed: `object` is a const T of the publisher's type. Copies it (TypeInfo::copy) only
  // when intra-process subscribers exist; encodes straight into a shm slot only when
  // shm subscribers exist. Throws Error(message_too_large).
  virtual void publish_ref(const void* object, std::shared_ptr<const void> (*copy)(const void*)) = 0;
  virtual void publish_shared(std::shared_ptr<const void> object) = 0;
  // Raw bytes (an LCM encoding, with its fingerprint, or any payload on a raw channel).
  virtual void publish_bytes(std::span<const std::byte> data) = 0;
  // One Loan per publisher at a time (the shm Writer lends one slot). While it is out,
  // publish_*() and loan() from other threads wait until it is published or dropped; from
  // the thread that took it they throw Error(invalid_argument) (they would wait forever).
  virtual shm::WriteLoan loan(std::size_t size) = 0;
  virtual void publish_loan(shm::WriteLoan&& loan, std::size_t size) = 0;
  // The Loan was dropped unpublished: gives the slot back and lets waiting publishers on.
  virtual void drop_loan(shm::WriteLoan&& loan) noexcept = 0;

  virtual std::size_t subscriber_count() const = 0;
  virtual bool wait_for_subscribers(std::size_t n, std::chrono::milliseconds timeout) const = 0;
  virtual std::uint64_t published() const = 0;
  virtual PublisherStats stats() const = 0;
  virtual const std::string& channel() const = 0;
};

// Called by Node's templates; defined in core/src/node.cpp.
std::shared_ptr<PublisherCore> create_publisher(NodeImpl& node, std::string channel,
                                                const TypeInfo& type, PublisherOptions options);
void add_subscriber(NodeImpl& node, const std::shared_ptr<SubscriberCore>& sub);
// Unregisters and waits until no callback of `sub` runs (unless called from inside one).
void remove_subscriber(const std::shared_ptr<SubscriberCore>& sub);

}  // namespace lcmx::detail
