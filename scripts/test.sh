#!/usr/bin/env bash
# Runs the whole test suite, in three stages (CI: .ci/run calls exactly this script):
#  1. the plain suite in build/ (unit, integration, multihost) with CTest, two at a time;
#  2. every libFuzzer target (CTest label `fuzz`, test/fuzz/README.md) for LCMX_FUZZ_SECONDS
#     seconds each (default 40: seven targets, two at a time, about 2.7 minutes): a
#     crash, leak or hang fails;
#  3. the unit and integration tests again, built with ASan + UBSan in build-asan/
#     (scripts/sanitizers.sh address); skipped with LCMX_TEST_SANITIZERS=0.
# With arguments, only stage 1 runs, and the arguments go to ctest: scripts/test.sh -R shm
set -euo pipefail
cd "$(dirname "$0")/.."

stage() { printf '\n==== %s (%s)\n' "$1" "$(date -u +%H:%M:%S)"; }

if (($# > 0)); then
  exec ctest --test-dir build --output-on-failure -j2 --timeout 300 "$@"
fi

stage "plain suite (build/)"
ctest --test-dir build --output-on-failure -j2 --timeout 300 -LE fuzz

stage "fuzz targets, ${LCMX_FUZZ_SECONDS:=26} s each"
export LCMX_FUZZ_SECONDS
ctest --test-dir build --output-on-failure -j2 -L fuzz

if [[ ${LCMX_TEST_SANITIZERS:-1} != 0 ]]; then
  stage "ASan + UBSan: unit and integration tests (build-asan/)"
  bash scripts/sanitizers.sh address
fi
stage "all stages passed"
