#!/usr/bin/env bash
# Runs lcmx_bench_latency three ways (unpinned, --pin same, --pin split) and writes one report,
# bench/results/latency-<date>.md (+ one CSV per run). Builds nothing: build first with
#   cmake -S . -B build-bench -DLCMX_BUILD_TESTS=OFF
#   cmake --build build-bench -j2 --target lcmx_bench_latency
# Usage: bench/run_latency.sh [extra lcmx_bench_latency options, e.g. --wait spin]
# Env: LCMX_BENCH_BIN = path of the binary (default: <repo>/build-bench/bench/lcmx_bench_latency).
# Needs root (the liblcm pair runs in a network namespace). Exit status: non-zero if any run failed.
set -uo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(dirname "$here")"
bin="${LCMX_BENCH_BIN:-$repo/build-bench/bench/lcmx_bench_latency}"
if [[ ! -x "$bin" ]]; then
  echo "run_latency.sh: $bin not found; build it first (see the top of this script)" >&2
  exit 2
fi

results="$here/results"
mkdir -p "$results"
stamp="$(date +%Y-%m-%d)"
out="$results/latency-$stamp.md"
[[ -e "$out" ]] && { stamp="$(date +%Y-%m-%d-%H%M%S)"; out="$results/latency-$stamp.md"; }

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

{
  echo "# lcmx one-way latency: $stamp"
  echo
  echo "Three runs of \`lcmx_bench_latency${*:+ $*}\`: unpinned, \`--pin same\`, \`--pin split\`."
  echo "Commit: \`$(git -C "$repo" rev-parse --short HEAD 2>/dev/null || echo unknown)\`."
  echo "Small-message figures are bound by wake-up (same vCPU ~2-5 us, other vCPU ~20-25 us);"
  echo "compare methods within one run only; differences under 1.3x are noise (DESIGN.md)."
  echo
} > "$out"

rc=0
for pin in none same split; do
  echo "run_latency.sh: --pin $pin" >&2
  if ! "$bin" --pin "$pin" "$@" --markdown "$tmp/$pin.md" --csv "$results/latency-$stamp-$pin.csv" >/dev/null; then
    echo "run_latency.sh: the --pin $pin run failed (exit $?); see its report" >&2
    rc=1
  fi
  if [[ -s "$tmp/$pin.md" ]]; then
    sed "1s/.*/## --pin $pin/" "$tmp/$pin.md" >> "$out"
  else
    echo "## --pin $pin" >> "$out"; echo; echo "run failed before writing a report" >> "$out"
  fi
  echo >> "$out"
done
echo "run_latency.sh: wrote $out" >&2
exit $rc
