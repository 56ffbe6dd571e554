#!/usr/bin/env bash
# ThreadSanitizer run of the unit and integration tests in build-tsan/ (not part of CI:
# see README "Sanitizers"). Extra arguments go to ctest, e.g. scripts/tsan.sh -R bridge.
set -euo pipefail
exec bash "$(dirname "$0")/sanitizers.sh" thread "$@"
