#!/usr/bin/env bash
# Runs the whole test suite, in three stages (CI: .ci/run calls exactly this script):
#  1. the plain suite in build/ (unit, integration, multihost) with CTest, two at a time;
#  2. every libFuzzer target (CTest label `fuzz`, test/fuzz/README.md) for LCMX_FUZZ_SECONDS
#     seconds each (default 40: seven targets, two at a time, about 2.7 minutes): a
#     crash, leak or hang fails;
#  3. the unit and integration tests again, built with ASan + UBSan in build-asan/
#     (scripts/sanitizers.sh address); skipped with LCMX_TEST_SANITIZERS=0.
# A test that cannot run here (no network namespaces, ...) is reported "Skipped" by CTest, not
# "Passed" (test/support/include/lcmx/test/skip.hpp). Where root can make network namespaces,
# every multihost test must run: stage 1 fails if one was skipped.
# With arguments, only stage 1 runs, and the arguments go to ctest: scripts/test.sh -R shm
set -euo pipefail
cd "$(dirname "$0")/.."

stage() { printf '\n==== %s (%s)\n' "$1" "$(date -u +%H:%M:%S)"; }

if (($# > 0)); then
  exec ctest --test-dir build --output-on-failure -j2 --timeout 300 "$@"
fi

# Whether this machine can run the multihost tests: root, and a new network namespace allowed.
netns_possible() { [[ $(id -u) == 0 ]] && unshare --net true 2>/dev/null; }

stage "plain suite (build/)"
rc=0
ctest --test-dir build --output-on-failure -j2 --timeout 300 -LE fuzz | tee build/ctest-plain.out || rc=$?
if netns_possible; then
  # CTest's closing list: "<tab><number> - <name> (Skipped)".
  skipped=$(sed -n 's/^[[:space:]]*[0-9]* - \(.*\) (Skipped)$/\1/p' build/ctest-plain.out | sort -u |
            comm -12 - <(ctest --test-dir build -N -L multihost | sed -n 's/^ *Test *#[0-9]*: //p' | sort))
  if [[ -n $skipped ]]; then
    echo "test.sh: root can make network namespaces here, yet these multihost tests were skipped:" >&2
    echo "$skipped" | sed 's/^/  /' >&2
    rc=1
  fi
fi
((rc == 0)) || exit "$rc"

stage "fuzz targets, ${LCMX_FUZZ_SECONDS:=26} s each"
export LCMX_FUZZ_SECONDS
ctest --test-dir build --output-on-failure -j2 -L fuzz

if [[ ${LCMX_TEST_SANITIZERS:-1} != 0 ]]; then
  stage "ASan + UBSan: unit and integration tests (build-asan/)"
  bash scripts/sanitizers.sh address
fi
stage "all stages passed"
