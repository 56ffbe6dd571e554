#include "lcmx/test/watchdog.hpp"

#include <cstdio>
#include <cstdlib>

#include "lcmx/test/netns.hpp"

namespace lcmx::test {

Watchdog::Watchdog(std::chrono::milliseconds timeout, std::string what) {
  t_ = std::thread([this, timeout, what = std::move(what)] {
    std::unique_lock lock(m_);
    if (cv_.wait_for(lock, timeout, [this] { return done_; })) return;
    std::fprintf(stderr, "watchdog: '%s' still running after %lld ms: tearing down and aborting\n",
                 what.c_str(), static_cast<long long>(timeout.count()));
    std::fflush(stderr);
    emergency_teardown();
    std::abort();
  });
}

Watchdog::~Watchdog() {
  {
    std::lock_guard lock(m_);
    done_ = true;
  }
  cv_.notify_all();
  t_.join();
}

}  // namespace lcmx::test
