#!/bin/bash
# `lcmx monitor` CPU benchmark (bench/README.md "lcmx monitor"). One run, same machine; builds
# nothing: give the build directory (default build/). No root needed: everything on lo.
#   bench/tools/run_monitor_bench.sh [BUILD_DIR] [--seconds 10] [--channels 100] [--rate 100] [--size 64]
# Traffic: lcmx_bench_monitor load, CHANNELS raw lcmx publishers at RATE Hz of bench_t with SIZE
# data bytes (shm); the monitor decodes with the repository's lcmtypes/ as its type path.
# Measured over the same windows (CPU seconds, user + system, all threads, /proc/PID/stat):
#   - `lcmx monitor` on a real terminal (tmux, 80x24, default redraw), 1. the channel table,
#     2. with the first channel opened (its latest message decoded, live);
#   - the peer: a plain raw subscriber of every channel (lcmx_bench_monitor sink: the same
#     subscription, counting only), i.e. the floor of receiving this traffic at all.
#     (lcm-spy, the reference, does not start on Debian 12: Java 17 rejects its -Xincgc;
#     lcm-logger cannot see shm traffic.)
# Target: monitor <= 10 % of one core. Prints a Markdown table; raw outputs in $WORK (KEEP=1).
set -euo pipefail
BUILD=build
SECS=10
CHANNELS=100
RATE=100
SIZE=64
while [ $# -gt 0 ]; do
  case "$1" in
    --seconds) SECS=$2; shift 2;;
    --channels) CHANNELS=$2; shift 2;;
    --rate) RATE=$2; shift 2;;
    --size) SIZE=$2; shift 2;;
    -h|--help) sed -n 2,15p "$0"; exit 0;;
    *) BUILD=$1; shift;;
  esac
done
LCMX=$(realpath "$BUILD/apps/lcmx")
TYPES=$(realpath "$(dirname "$0")/../../lcmtypes")
GEN=$(realpath "$BUILD/bench/tools/lcmx_bench_monitor")
# A discovery group of this run's own, on lo.
A=$(( ($$ / 250) % 250 + 1 )); B=$(( $$ % 250 + 1 ))
export LCMX_DISCOVERY_URL="udpm://239.254.$A.$B:$(( 20000 + $$ % 40000 ))?ttl=0&iface=lo"
SOCK=lcmxbench_mon_$$
WORK=$(mktemp -d /tmp/lcmx_bench_monitor_XXXXXX)
TOTAL=$(( 2 * SECS + 40 ))  # bounds every process of the run
PIDS=()
cleanup() {
  tmux -L "$SOCK" kill-server 2>/dev/null || true
  for p in "${PIDS[@]:-}"; do [ -n "$p" ] && kill -INT "$p" 2>/dev/null || true; done
  for p in "${PIDS[@]:-}"; do [ -n "$p" ] && wait "$p" 2>/dev/null || true; done
  [ "${KEEP:-0}" = 1 ] || rm -rf "$WORK"
}
trap cleanup EXIT
cpu_s() { awk -v t="$(getconf CLK_TCK)" '{ print ($14 + $15) / t }' "/proc/$1/stat"; }
pct() { awk -v a="$1" -v b="$2" -v s="$3" 'BEGIN { printf "%.1f", (b - a) / s * 100 }'; }
# Polls `cmd` until it succeeds (bounded).
wait_for() {
  local what=$1; shift
  for _ in $(seq 1 400); do "$@" && return 0; sleep 0.05; done
  echo "timed out waiting for $what" >&2; exit 1
}
screen() { tmux -L "$SOCK" capture-pane -p -t mon; }

"$GEN" load BENCHMON "$CHANNELS" "$RATE" "$SIZE" "$TOTAL" > "$WORK/load.out" 2>&1 &
LOAD=$!; PIDS+=("$LOAD")
"$GEN" sink "$TOTAL" > "$WORK/sink.out" 2>&1 &
SINK=$!; PIDS+=("$SINK")
wait_for "load" grep -q ready "$WORK/load.out"
wait_for "sink" grep -q ready "$WORK/sink.out"
tmux -L "$SOCK" new-session -d -s mon -x 80 -y 24 "exec '$LCMX' monitor --types '$TYPES'"
MON=$(tmux -L "$SOCK" display -p -t mon '#{pane_pid}')
wait_for "$CHANNELS channels on the monitor" sh -c "tmux -L '$SOCK' capture-pane -p -t mon | grep -q '^lcmx monitor  $CHANNELS channels'"
sleep 3  # warm-up: rates settle (measurement window, not synchronisation)

measure() {  # $1: label; prints "label mon% sink% load%"
  local m0 s0 l0 m1 s1 l1
  m0=$(cpu_s "$MON"); s0=$(cpu_s "$SINK"); l0=$(cpu_s "$LOAD")
  sleep "$SECS"
  m1=$(cpu_s "$MON"); s1=$(cpu_s "$SINK"); l1=$(cpu_s "$LOAD")
  echo "$1|$(pct "$m0" "$m1" "$SECS")|$(pct "$s0" "$s1" "$SECS")|$(pct "$l0" "$l1" "$SECS")"
}
R1=$(measure "channel table")
screen > "$WORK/screen_table.txt"
tmux -L "$SOCK" send-keys -t mon Enter
wait_for "the opened channel" sh -c "tmux -L '$SOCK' capture-pane -p -t mon | grep -q 'rate (max'"
R2=$(measure "channel opened (decoded live)")
screen > "$WORK/screen_open.txt"
tmux -L "$SOCK" send-keys -t mon q
wait_for "monitor exit" sh -c "! kill -0 $MON 2>/dev/null"
kill -INT "$SINK" "$LOAD"
wait "$SINK" "$LOAD" || true
PIDS=()

echo "# lcmx monitor CPU ($(date -u +%F' '%H:%M' UTC'), $(nproc) CPUs, load average $(cut -d' ' -f1-3 /proc/loadavg))"
echo
echo "Traffic: $CHANNELS channels x $RATE Hz x $SIZE B (bench_t) over shm ($(grep published "$WORK/load.out")," \
     "peer $(grep received "$WORK/sink.out")); $SECS s per window; monitor in tmux 80x24."
echo
echo "| window | lcmx monitor (% of one core) | peer: raw subscriber of all channels | ratio monitor / peer | publisher process |"
echo "|---|---|---|---|---|"
for r in "$R1" "$R2"; do
  IFS='|' read -r label m s l <<< "$r"
  ratio=$(awk -v m="$m" -v s="$s" 'BEGIN { if (s > 0) printf "%.2f", m / s; else print "-" }')
  ok=$(awk -v m="$m" 'BEGIN { print (m <= 10.0) ? "within" : "ABOVE" }')
  echo "| $label | $m % ($ok the 10 % target) | $s % | $ratio | $l % |"
done
echo
echo "Screen (channel table, first rows):"
echo '```'
head -6 "$WORK/screen_table.txt"
echo '```'
