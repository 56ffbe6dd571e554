// The one Catch2 main of every lcmx test program (lcmx::catch_main, test/CMakeLists.txt).
// Catch2 v2's implementation is compiled here, once: it was the most expensive translation
// unit of the suite (~20 s of CPU per test program, twice that under ASan).
//
// Exit code: Catch2's (the number of failed assertions, at most 255; 0 when all passed), except
// that a run where nothing failed and some test skipped (LCMX_SKIP, lcmx/test/skip.hpp) exits
// with kSkipReturnCode (77), which CTest reports as "Skipped" (SKIP_RETURN_CODE). A failing run
// never exits with 77.
#define CATCH_CONFIG_RUNNER
#include <catch2/catch.hpp>

#include "lcmx/test/skip.hpp"

int main(int argc, char* argv[]) {
  const int failed = Catch::Session().run(argc, argv);
  if (failed == lcmx::test::kSkipReturnCode) return failed + 1;
  if (failed == 0 && lcmx::test::skipped_tests().load() > 0) return lcmx::test::kSkipReturnCode;
  return failed;
}
