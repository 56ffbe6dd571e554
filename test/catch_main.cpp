// The one Catch2 main of every lcmx test program (lcmx::catch_main, test/CMakeLists.txt).
// Catch2 v2's implementation is compiled here, once: it was the most expensive translation
// unit of the suite (~20 s of CPU per test program, twice that under ASan).
#define CATCH_CONFIG_MAIN
#include <catch2/catch.hpp>
