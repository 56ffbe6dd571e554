// Publisher<T> for an lcm-gen type T, and RawPublisher for untyped bytes.
//
// Delivery (DESIGN.md "Delivery"): subscribers in this process get the message as a
// std::shared_ptr<const T> (no encoding); subscribers in other processes of this host read
// it from shared memory, encoded once straight into a slot. Each path is used only when a
// subscriber needs it.
// Publishing never blocks on subscribers: slow ones lose the oldest messages (counted as
// drops on their side).
// Threads: publish() may be called from any thread; calls are serialised per publisher.
// Errors: publish() throws lcmx::Error(message_too_large) when the encoding exceeds
// PublisherOptions::max_message_size, lcmx::Error(transport) if shared memory fails.
#pragma once

#include <chrono>
#include <memory>
#include <optional>
#include <span>

#include "lcmx/core/detail/endpoint.hpp"

namespace lcmx {

namespace detail {
// What Publisher<T> and RawPublisher have in common: matching state and counters.
class PublisherHandle {
 public:
  // Subscribers currently matched (this process, other processes, other hosts).
  std::size_t subscriber_count() const { return core_->subscriber_count(); }
  // Waits until at least n subscribers are matched. Returns false on timeout.
  bool wait_for_subscribers(std::size_t n, std::chrono::milliseconds timeout) const {
    return core_->wait_for_subscribers(n, timeout);
  }
  std::uint64_t published() const { return core_->published(); }
  // Counters (thread-safe): published, and shm_dropped (see PublisherStats).
  PublisherStats stats() const { return core_->stats(); }
  const std::string& channel() const { return core_->channel(); }
  explicit operator bool() const { return core_ != nullptr; }

 protected:
  PublisherHandle() = default;
  explicit PublisherHandle(std::shared_ptr<PublisherCore> c) : core_(std::move(c)) {}
  std::shared_ptr<PublisherCore> core_;
};
}  // namespace detail

template <class T>
class Publisher : public detail::PublisherHandle {
 public:
  Publisher() = default;  // empty handle; assign from Node::advertise()

  void publish(const T& message) {
    core_->publish_ref(&message, [](const void* o) -> std::shared_ptr<const void> {
      return std::make_shared<const T>(*static_cast<const T*>(o));
    });
  }
  void publish(std::shared_ptr<const T> message) { core_->publish_shared(std::move(message)); }

 private:
  friend class Node;
  explicit Publisher(std::shared_ptr<detail::PublisherCore> c) : PublisherHandle(std::move(c)) {}
};

// A slot loaned from shared memory by RawPublisher::loan(): write at data(), then
// RawPublisher::publish(std::move(loan), size). Dropped unpublished: nothing is sent.
// Ownership: the Loan keeps its publisher (and its shared memory) alive, so it may outlive
// the RawPublisher handle it came from; it is then only dropped (nothing can publish it).
// Contract: one Loan per publisher at a time. While it is out, publish() and loan() of the
// same publisher from other threads wait until it is published or dropped; from the thread
// that took it they throw lcmx::Error(invalid_argument) (waiting would never end).
class Loan {
 public:
  Loan() = default;  // empty
  Loan(Loan&& other) noexcept : owner_(std::move(other.owner_)), loan_(std::move(other.loan_)) {
    other.loan_.reset();
  }
  Loan& operator=(Loan&& other) noexcept {
    if (this != &other) {
      release();
      owner_ = std::move(other.owner_);
      loan_ = std::move(other.loan_);
      other.loan_.reset();
    }
    return *this;
  }
  ~Loan() { release(); }

  std::byte* data() const noexcept { return loan_ ? loan_->data() : nullptr; }
  std::size_t capacity() const noexcept { return loan_ ? loan_->capacity() : 0; }
  explicit operator bool() const noexcept { return owner_ != nullptr; }

 private:
  friend class RawPublisher;
  Loan(std::shared_ptr<detail::PublisherCore> owner, shm::WriteLoan l)
      : owner_(std::move(owner)), loan_(std::move(l)) {}
  void release() noexcept {
    if (owner_ && loan_) owner_->drop_loan(std::move(*loan_));
    owner_.reset();
    loan_.reset();
  }
  std::shared_ptr<detail::PublisherCore> owner_;  // first: outlives loan_
  std::optional<shm::WriteLoan> loan_;            // empty in an empty Loan
};

class RawPublisher : public detail::PublisherHandle {
 public:
  RawPublisher() = default;

  // Copies `data` once: into a shm slot and/or one buffer shared by in-process subscribers.
  void publish(std::span<const std::byte> data) { core_->publish_bytes(data); }
  // Zero-copy: write straight into a shared-memory slot of at least `size` bytes.
  Loan loan(std::size_t size) { return Loan(core_, core_->loan(size)); }
  // Throws Error(invalid_argument) for an empty Loan or one of another publisher (the Loan
  // is then left as it was).
  void publish(Loan&& loan, std::size_t size) {
    if (!loan.owner_ || !loan.loan_ || loan.owner_ != core_)
      throw Error(Errc::invalid_argument, "publish on '" + core_->channel() +
                                              "': the Loan is empty or of another publisher");
    core_->publish_loan(std::move(*loan.loan_), size);
    loan.owner_.reset();
    loan.loan_.reset();
  }

 private:
  friend class Node;
  explicit RawPublisher(std::shared_ptr<detail::PublisherCore> c) : PublisherHandle(std::move(c)) {}
};

}  // namespace lcmx
