#!/usr/bin/env bash
# Builds lcmx with a sanitizer into its own build directory and runs the unit and integration
# tests there (CTest labels `unit` and `integration`; multihost, stress and fuzz tests are not
# run: the fuzz targets are sanitized already, see test/fuzz/README.md; nor the consumer test,
# which builds an unsanitized project against the installed libraries).
#   scripts/sanitizers.sh address   ASan + UBSan (gcc -fsanitize=address,undefined
#                                   -fno-sanitize-recover=undefined) in build-asan/; run by
#                                   scripts/test.sh after the plain suite
#   scripts/sanitizers.sh thread    TSan in build-tsan/ (scripts/tsan.sh; not in CI)
# Extra arguments go to ctest (e.g. -R shm). Any sanitizer report fails the test that made it:
# ASan and TSan exit non-zero, UBSan aborts (no recovery).
set -euo pipefail
cd "$(dirname "$0")/.."

mode=${1:-}
shift || true
case "$mode" in
  address) dir=build-asan; option=LCMX_SANITIZE_ADDRESS ;;
  thread)  dir=build-tsan; option=LCMX_SANITIZE_THREAD ;;
  *) echo "usage: scripts/sanitizers.sh address|thread [ctest arguments...]" >&2; exit 2 ;;
esac

# Benchmarks and the libFuzzer targets (clang, already sanitized) are not built here. -O1, the
# usual level for sanitizers: g++ -O2 with ASan+UBSan took 3.2x the CPU of a plain -O2 compile
# (core/src/runtime.cpp: 41 s vs 13 s), -O1 1.9x (25 s), which keeps CI under 30 minutes; the
# test programs' own code is -O0 here (test/CMakeLists.txt), the libraries and tools -O1.
# -g1: line tables only, so reports still name file:line, without the cost of full debug info.
cmake -S . -B "$dir" -DCMAKE_BUILD_TYPE=RelWithDebInfo -D"$option"=ON \
  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g1 -DNDEBUG" -DCMAKE_C_FLAGS_RELWITHDEBINFO="-O1 -g1 -DNDEBUG" \
  -DLCMX_BUILD_BENCH=OFF -DLCMX_BUILD_FUZZERS=OFF >/dev/null
# Only the unit and integration test programs (and what they start): see test/CMakeLists.txt.
cmake --build "$dir" -j"$(nproc)" --target lcmx_unit_integration_tests

# detect_leaks=1: a leak fails the test. abort_on_error=0 keeps ASan's exit code (1) so
# CTest reports a failure rather than a signal. halt_on_error for TSan: the first race fails.
export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:abort_on_error=0:strict_string_checks=1:detect_stack_use_after_return=0}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}
export TSAN_OPTIONS=${TSAN_OPTIONS:-halt_on_error=1:second_deadlock_stack=1}
ctest --test-dir "$dir" --output-on-failure -j2 --timeout 300 -L 'unit|integration' -E '^consumer/' "$@"
