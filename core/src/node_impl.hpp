// A node: a named unit of a program and its executor (core/src/node.cpp). Owns its threads,
// its doorbell and the list of its subscribers (NodeImpl::mu, the last lock in the order).
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "lcmx/core/runtime.hpp"
#include "subscriber_state.hpp"

namespace lcmx::detail {

class RuntimeImpl;

class NodeImpl : public std::enable_shared_from_this<NodeImpl> {
 public:
  NodeImpl(std::shared_ptr<RuntimeImpl> rt, std::string name, NodeOptions options);
  ~NodeImpl();
  void start();
  void stop();

  void add(const std::shared_ptr<SubscriberCore>& sub);
  void remove(const SubscriberCore* sub);
  // Something arrived or changed: wake an executor thread.
  void ring();
  // Makes the current (or next) run_once() return 0 as soon as it has run what is ready.
  // For a manual node run by lcmx's own thread (service clients), which has more to do.
  void interrupt() {
    interrupted.store(true, std::memory_order_seq_cst);
    ring();
  }
  bool stopped() const { return stopping.load(std::memory_order_acquire); }
  // Runs ready callbacks, waiting up to `timeout` for some. Returns callbacks run.
  std::size_t run_once(std::chrono::nanoseconds timeout);

  const std::shared_ptr<RuntimeImpl> runtime;
  const std::string name;
  const NodeOptions options;
  const std::uint64_t uid;  // unique in the process, never reused (unlike the address)

  // A fault the executor survived (an exception on its thread): log + Event::Kind::error.
  void report_fault(const std::string& what) noexcept;
  std::uint64_t fault_count() const {
    std::lock_guard lock(fault_mu);
    return faults;
  }

 private:
  mutable std::mutex fault_mu;
  std::uint64_t faults = 0;
  std::chrono::steady_clock::time_point last_fault_report{};
  std::size_t poll_all(std::vector<std::shared_ptr<SubscriberCore>>& subs);
  std::size_t poll_one(SubscriberCore& sub);
  std::size_t poll_intra(SubscriberCore& sub);
  void refresh(std::vector<std::shared_ptr<SubscriberCore>>& local, std::uint64_t& version);

  std::mutex mu;
  std::vector<std::shared_ptr<SubscriberCore>> subs;
  std::atomic<std::uint64_t> subs_version{0};
  // Blocks in epoll on the UDP sockets + wake_fd instead of futex_waitv (see run_once).
  // Returns false if this thread cannot (another thread of the node waits so already).
  bool wait_udp(std::uint32_t bell, std::chrono::steady_clock::time_point deadline);

  std::atomic<std::uint32_t> doorbell{0};
  std::atomic<int> sleepers{0};      // threads blocked (futex or epoll) after reading doorbell
  std::atomic<int> fd_sleepers{0};   // of which in epoll: ring() must write wake_fd
  std::atomic<bool> stopping{false};
  std::atomic<bool> interrupted{false};
  // WaitStrategy::adaptive: steady_clock time (ns since its epoch) when a run_once() pass last
  // handled a message; relaxed (a stale value only shortens or lengthens one spin).
  std::atomic<std::int64_t> last_work_ns{0};
  std::vector<std::thread> threads;
  // UDP waiting (one thread of the node at a time, `fd_waiter` held): an eventfd for ring()
  // and an epoll set with it and the runtime's group sockets. Created on first use.
  std::atomic<bool> fd_waiter{false};
  int wake_fd = -1;
  int epoll_fd = -1;
};

}  // namespace lcmx::detail
