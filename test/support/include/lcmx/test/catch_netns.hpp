// For Catch2 tests that need emulated hosts: LCMX_REQUIRE_NETNS() at the top of a TEST_CASE
// returns from it with a "skipped" warning (reason included) where network namespaces cannot
// be created (no root, no `ip`), so the suite still passes there.
#pragma once

#include <catch2/catch.hpp>
#include <string>

#include "lcmx/test/netns.hpp"

#define LCMX_REQUIRE_NETNS()                                 \
  do {                                                       \
    std::string why_;                                        \
    if (!lcmx::test::netns_available(&why_)) {               \
      WARN("skipped: no network namespaces here: " << why_); \
      return;                                                \
    }                                                        \
  } while (0)
