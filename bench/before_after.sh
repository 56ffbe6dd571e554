#!/bin/bash
# The three landed benchmarks (lcmx_bench_latency, lcmx_bench_udp, lcmx_bench_bridge) for two
# builds of lcmx, alternating before/after in one run (issue 15 "Benchmark"). Builds nothing:
# configure both trees with -DLCMX_BUILD_TESTS=ON (the UDP and bridge benches need the test
# support library) and build the three bench targets and apps/lcmx first. Root (network
# namespaces). Each build's bridge bench runs its own build's `lcmx bridge`.
#
#   sudo bench/before_after.sh BEFORE_BUILD AFTER_BUILD OUTDIR [LATENCY_ROUNDS]
#
# OUTDIR gets latency-{before,after}-<round>.md, udp-{before,after}.md, bridge-{before,after}.md
# and progress.txt (start time and load average of each run); bench/tools/before_after_tables.py
# OUTDIR prints the before/after tables.
set -euo pipefail
usage() { sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; }
if [ "${1:-}" = "--help" ] || [ "${1:-}" = "-h" ]; then usage; exit 0; fi
if [ $# -lt 3 ]; then usage >&2; exit 2; fi
before=$(cd "$1" && pwd)
after=$(cd "$2" && pwd)
out=$3
rounds=${4:-2}
for b in "$before" "$after"; do
  for t in bench/lcmx_bench_latency bench/udp/lcmx_bench_udp bench/bridge/lcmx_bench_bridge apps/lcmx; do
    [ -x "$b/$t" ] || { echo "before_after.sh: $b/$t is missing (build it first)" >&2; exit 2; }
  done
done
mkdir -p "$out"
cd "$out"
dir_of() { [ "$1" = before ] && echo "$before" || echo "$after"; }
note() { echo "== $* $(date +%T) load $(cut -d' ' -f1 /proc/loadavg)" | tee -a progress.txt >&2; }
for r in $(seq 1 "$rounds"); do
  for w in before after; do
    note "latency $w round $r"
    "$(dir_of $w)/bench/lcmx_bench_latency" --markdown "latency-$w-$r.md" > "latency-$w-$r.out" 2>&1 || true
  done
done
for w in before after; do
  note "udp $w"
  "$(dir_of $w)/bench/udp/lcmx_bench_udp" --markdown "udp-$w.md" > "udp-$w.out" 2>&1 || true
done
for w in before after; do
  note "bridge $w"
  "$(dir_of $w)/bench/bridge/lcmx_bench_bridge" --lcmx "$(dir_of $w)/apps/lcmx" --markdown "bridge-$w.md" \
    > "bridge-$w.out" 2>&1 || true
done
note done
