// Skipped tests: a test that cannot run on this machine (no network namespaces, a libzmq
// without CURVE, ...) says so with LCMX_SKIP(reason) in its TEST_CASE's own body (not in a
// SECTION: it returns from the enclosing function). It warns with the reason and returns, and
// the test program's main (lcmx::catch_main, test/catch_main.cpp) exits with kSkipReturnCode
// instead of 0 when nothing failed. CTest shows that as "Skipped" (not "Passed") for tests with
// the property SKIP_RETURN_CODE 77, which every catch_discover_tests() call of a program that
// can skip sets. A program that skips without the property shows "Failed": never a silent pass.
// scripts/test.sh fails when a multihost test was skipped where root can make namespaces.
#pragma once

#include <atomic>
#include <catch2/catch.hpp>

namespace lcmx::test {

inline constexpr int kSkipReturnCode = 77;

// How many tests of this program skipped (any thread).
inline std::atomic<int>& skipped_tests() {
  static std::atomic<int> n{0};
  return n;
}

}  // namespace lcmx::test

#define LCMX_SKIP(reason)                           \
  do {                                              \
    ::lcmx::test::skipped_tests().fetch_add(1);     \
    WARN("skipped: " << reason);                    \
    return;                                         \
  } while (0)
