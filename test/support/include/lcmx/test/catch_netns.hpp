// For Catch2 tests that need emulated hosts: LCMX_REQUIRE_NETNS() at the top of a TEST_CASE (or
// of the function it calls first) skips the test (LCMX_SKIP, lcmx/test/skip.hpp: CTest reports
// it as "Skipped", reason included) where network namespaces cannot be created (no root, no `ip`).
#pragma once

#include <catch2/catch.hpp>
#include <string>

#include "lcmx/test/netns.hpp"
#include "lcmx/test/skip.hpp"

#define LCMX_REQUIRE_NETNS()                                    \
  do {                                                          \
    std::string why_;                                           \
    if (!lcmx::test::netns_available(&why_))                    \
      LCMX_SKIP("no network namespaces here: " << why_);        \
  } while (0)
