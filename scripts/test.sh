#!/usr/bin/env bash
# Runs the whole test suite (unit, integration, multihost) with CTest, two at a time.
set -euo pipefail
cd "$(dirname "$0")/.."
ctest --test-dir build --output-on-failure -j2 --timeout 300 "$@"
