// A watchdog for test fixtures: if the scope is still alive after `timeout`, it prints what hung,
// kills the live Childs, deletes the live Emulations' namespaces (emergency_teardown) and aborts
// the process, so a hang fails fast and leaves nothing behind.
#pragma once

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <string>
#include <thread>

namespace lcmx::test {

class Watchdog {
 public:
  // `what` names the guarded scope in the message. The timer runs on its own thread.
  Watchdog(std::chrono::milliseconds timeout, std::string what);
  Watchdog(const Watchdog&) = delete;
  Watchdog& operator=(const Watchdog&) = delete;
  ~Watchdog();  // disarms and joins

 private:
  std::mutex m_;
  std::condition_variable cv_;
  bool done_ = false;
  std::thread t_;
};

}  // namespace lcmx::test
