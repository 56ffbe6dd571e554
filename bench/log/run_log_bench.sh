#!/bin/bash
# Log tools benchmark (bench/README.md "Log tools"). Root (network namespace). One run, same
# machine; builds nothing: give the build directory (default build/).
#   bench/log/run_log_bench.sh [BUILD_DIR] [--stock-seconds 60] [--burst-seconds 20] [--lcmx-seconds 20] [--play-seconds 30]
# 1. recorder vs lcm-logger: both record the same stock traffic (100 channels x 100 Hz x 1 KB on
#    LCM's host-local group, in a namespace whose multicast is routed to lo): lost, CPU seconds.
#    Twice: phases spread (100 independent publishers, --stock-seconds) and burst (all 100
#    back to back every 10 ms, --burst-seconds).
# 2. lcmx record on lcmx traffic: 6.2 MB images at 30 Hz over shm + 100 channels x 100 Hz small,
#    to tmpfs (/dev/shm, --rotate 2 --split-mb 1000 to bound memory): lost, CPU per MB; default
#    and --rt-priority 10.
# 3. player timing: lcm-logplayer and lcmx play --udp replay scenario 1's lcm-logger logs (the
#    first --play-seconds of each) at speed 1 to a stock observer: |actual - due| p50/p99.
# Prints Markdown tables; raw outputs stay in $WORK (removed at the end unless KEEP=1).
set -euo pipefail
BUILD=build
STOCK_S=60
BURST_S=20
LCMX_S=20
PLAY_S=30
while [ $# -gt 0 ]; do
  case "$1" in
    --stock-seconds) STOCK_S=$2; shift 2;;
    --burst-seconds) BURST_S=$2; shift 2;;
    --lcmx-seconds) LCMX_S=$2; shift 2;;
    --play-seconds) PLAY_S=$2; shift 2;;
    -h|--help) sed -n 2,15p "$0"; exit 0;;
    *) BUILD=$1; shift;;
  esac
done
LCMX=$(realpath "$BUILD/apps/lcmx")
GEN=$(realpath "$BUILD/bench/log/lcmx_bench_log")
URL="udpm://239.255.76.67:7667?ttl=0"
NS=lcmxbench_log_$$
WORK=$(mktemp -d /tmp/lcmx_bench_log_XXXXXX)
TMPFS=$(mktemp -d /dev/shm/bench_log_XXXXXX)  # not lcmx_*: that is lcmx's segment prefix
PIDS=()
cleanup() {
  for p in "${PIDS[@]:-}"; do [ -n "$p" ] && kill -KILL "$p" 2>/dev/null || true; done
  ip netns del "$NS" 2>/dev/null || true
  rm -rf "$TMPFS"
  [ "${KEEP:-0}" = 1 ] || rm -rf "$WORK"
}
trap cleanup EXIT
ip netns add "$NS"
ip -n "$NS" link set lo up
ip -n "$NS" route add 224.0.0.0/4 dev lo
inns() { ip netns exec "$NS" "$@"; }
# CPU seconds (user + system, all threads) of a live process.
cpu_s() { awk -v t="$(getconf CLK_TCK)" '{ print ($14 + $15) / t }' "/proc/$1/stat"; }
# Polls until a log holds channel $2 (bounded).
wait_logged() {
  for _ in $(seq 1 200); do
    if [ -s "$1" ] && "$LCMX" log info --json "$1" 2>/dev/null | grep -q "\"channel\":\"$2\""; then return 0; fi
    inns "$GEN" gen-stock "$URL" 1 20 64 0.05 WARMUP >/dev/null 2>&1 || true   # WARMUP_000
  done
  echo "no $2 in $1" >&2; return 1
}
# Events of the BENCH_* channels in a log (the traffic measured, not the warm-up).
count_events() {
  # (none yet is 0: grep's "no match" must not end the script under pipefail)
  "$LCMX" log info --json "$1" | { grep -o '"channel":"BENCH_[0-9]*","count":[0-9]*' || true; } |
    awk -F: '{ n += $NF } END { print n + 0 }'
}

echo "# lcmx log tools benchmark ($(date -u +%F' '%H:%M' UTC'), $(nproc) CPUs, $(uname -r))"
echo

# ---- 1. recorder vs lcm-logger on stock traffic, in two phasings (gen-stock spread|burst):
# spread = 100 independent publishers (phases spread over the period: the issue's scenario);
# burst = one program publishing all 100 channels back to back every 10 ms (the stress case).
# (ip netns exec execs: $! is the recorder itself)
run_rec1() {  # PHASE SECONDS
  local phase=$1 secs=$2
  ip netns exec "$NS" lcm-logger -q -f "$WORK/lcm-logger-$phase.lcmlog" & PIDS+=($!); local LOGGER=$!
  ip netns exec "$NS" env -u LCMX_DISCOVERY_URL "$LCMX" record -q -f "$WORK/lcmx-record-$phase.lcmlog" --json > "$WORK/record1-$phase.json" & PIDS+=($!); local REC=$!
  wait_logged "$WORK/lcm-logger-$phase.lcmlog" WARMUP_000
  wait_logged "$WORK/lcmx-record-$phase.lcmlog" WARMUP_000
  local W1 W2 C1 C2 SENT A B
  W1=$(count_events "$WORK/lcm-logger-$phase.lcmlog"); W2=$(count_events "$WORK/lcmx-record-$phase.lcmlog")
  C1=$(cpu_s $LOGGER); C2=$(cpu_s $REC)
  SENT=$(inns "$GEN" gen-stock "$URL" 100 100 1024 "$secs" BENCH "$phase" | sed -n 's/^sent \([0-9]*\).*/\1/p')
  # Let the last datagrams arrive and be flushed (both flush every 100 ms).
  for _ in $(seq 1 50); do
    A=$(( $(count_events "$WORK/lcm-logger-$phase.lcmlog") - W1 )); B=$(( $(count_events "$WORK/lcmx-record-$phase.lcmlog") - W2 ))
    [ "$A" -ge "$SENT" ] && [ "$B" -ge "$SENT" ] && break
    sleep 0.1
  done
  C1=$(awk -v a="$(cpu_s $LOGGER)" -v b="$C1" 'BEGIN { printf "%.2f", a - b }')
  C2=$(awk -v a="$(cpu_s $REC)" -v b="$C2" 'BEGIN { printf "%.2f", a - b }')
  kill -INT $LOGGER $REC; wait $LOGGER $REC || true
  A=$(( $(count_events "$WORK/lcm-logger-$phase.lcmlog") - W1 )); B=$(( $(count_events "$WORK/lcmx-record-$phase.lcmlog") - W2 ))
  echo "| lcm-logger | $phase | $secs | $SENT | $A | $((SENT - A)) | $C1 | 1.00 |"
  echo "| lcmx record | $phase | $secs | $SENT | $B | $((SENT - B)) | $C2 | $(awk -v a="$C2" -v b="$C1" 'BEGIN { printf "%.2f", a / b }') |"
}
echo "## 1. Recorder vs lcm-logger: stock traffic, 100 channels x 100 Hz x 1 KB, host-local group"
echo
echo "| recorder | phasing | s | sent | recorded | lost | CPU s | CPU vs lcm-logger |"
echo "|---|---|---:|---:|---:|---:|---:|---:|"
run_rec1 spread "$STOCK_S"
run_rec1 burst "$BURST_S"
echo
echo "spread: the 100 channels' phases spread over each 10 ms period (100 independent publishers); burst: all 100 sent back to back every 10 ms (one program publishing them in one loop)."
echo

# ---- 2. lcmx record on lcmx traffic, to tmpfs (default, then --rt-priority 10)
echo "## 2. lcmx record on lcmx traffic: 6.2 MB images at 30 Hz (shm) + 100 channels x 100 Hz x 100 B, ${LCMX_S} s, to tmpfs"
echo
echo "| recorder | sent | recorded | lost (recorder's count) | sent - recorded | MB recorded | CPU s | CPU ms per MB |"
echo "|---|---:|---:|---:|---:|---:|---:|---:|"
run_rec2() {
  local label=$1; shift
  rm -f "$TMPFS"/lcmx.lcmlog.*
  ip netns exec "$NS" env -u LCMX_DISCOVERY_URL "$LCMX" record -q --rotate 2 --split-mb 1000 "$@" "$TMPFS/lcmx.lcmlog" --json > "$WORK/record2-$label.json" & PIDS+=($!); local REC=$!
  # The generator waits until the recorder subscribed to each of its channels.
  local C0; C0=$(cpu_s $REC)
  local GENOUT; GENOUT=$(inns env -u LCMX_DISCOVERY_URL "$GEN" gen-lcmx 100 100 100 6220800 30 "$LCMX_S" 2>/dev/null)
  local SENT; SENT=$(echo "$GENOUT" | sed -n 's/^sent \([0-9]*\) .*/\1/p')
  for _ in $(seq 1 50); do sleep 0.1; done   # drain: the recorder writes its queue (bounded wait)
  local CR; CR=$(awk -v a="$(cpu_s $REC)" -v b="$C0" 'BEGIN { printf "%.2f", a - b }')
  kill -INT $REC; wait $REC || true
  local J; J=$(cat "$WORK/record2-$label.json")
  local MSGS BYTES LOST
  MSGS=$(echo "$J" | sed -n 's/.*"seconds":[0-9.]*,"messages":\([0-9]*\).*/\1/p')
  BYTES=$(echo "$J" | sed -n 's/.*,"bytes":\([0-9]*\),"lost".*/\1/p')
  LOST=$(echo "$J" | sed -n 's/.*,"lost":\([0-9]*\),"channels".*/\1/p')
  echo "| $label | $SENT | $MSGS | $LOST | $((SENT - MSGS)) | $(awk -v b="$BYTES" 'BEGIN { printf "%.0f", b / 1e6 }') | $CR | $(awk -v c="$CR" -v b="$BYTES" 'BEGIN { printf "%.3f", c * 1000 / (b / 1e6) }') |"
}
run_rec2 "lcmx record"
run_rec2 "lcmx record --rt-priority 10" --rt-priority 10
echo

# ---- 3. player timing on scenario 1's lcm-logger logs (spread, then burst)
"$LCMX" play --help >/dev/null
run_player() {  # NAME LOG SECONDS COMMAND...
  local name=$1 log=$2 secs=$3; shift 3
  local out="$WORK/observe-$name.txt"
  # The observer runs SCHED_FIFO so that its own wake-ups add as little as possible (the same
  # for every player).
  chrt -f 20 ip netns exec "$NS" "$GEN" observe "$URL" "$log" "$((secs + 4))" > "$out" & local OBS=$!; PIDS+=($OBS)
  for _ in $(seq 1 100); do grep -q ready "$out" 2>/dev/null && break; sleep 0.05; done
  inns timeout "$((secs + 3))" "$@" > "$WORK/player-$name.txt" 2>&1 || true
  wait $OBS || true
  sed -n 's/^timing //p' "$out"
}
field() { echo "$1" | sed -n "s/.*$2=\([0-9.]*\).*/\1/p"; }
echo "## 3. Player timing: replaying scenario 1's lcm-logger logs at speed 1 (10 000 msg/s), stock observer"
echo
echo "| log | player | received | p50 us | p99 us | max us |"
echo "|---|---|---:|---:|---:|---:|"
for phase in spread burst; do
  LOG="$WORK/lcm-logger-$phase.lcmlog"
  secs=$PLAY_S; [ "$phase" = burst ] && secs=$((BURST_S < PLAY_S ? BURST_S : PLAY_S))
  T1=$(run_player "logplayer-$phase" "$LOG" "$secs" lcm-logplayer -s 1 "$LOG")
  T2=$(run_player "lcmx-$phase" "$LOG" "$secs" env -u LCMX_DISCOVERY_URL "$LCMX" play --udp --delay 0.5 --json --end "$secs" "$LOG")
  echo "| $phase, first $secs s | lcm-logplayer | $(field "$T1" matched) | $(field "$T1" p50_us) | $(field "$T1" p99_us) | $(field "$T1" max_us) |"
  echo "| $phase, first $secs s | lcmx play --udp | $(field "$T2" matched) | $(field "$T2" p50_us) | $(field "$T2" p99_us) | $(field "$T2" max_us) |"
done
echo
echo "|actual - due| at a stock observer (SCHED_FIFO): due = start + (log timestamp - first log timestamp), start = the median over all messages (a constant delay is not an error)."
for n in lcmx-spread lcmx-burst; do echo "lcmx play ($n) own measure of publish time - due: $(sed -n 's/.*"late_us":\({[^}]*}\).*/\1/p' "$WORK/player-$n.txt")"; done
echo "lcm-logplayer has no --end: it is stopped by timeout after the log's seconds + 3 s (so it replays a little more of the log); the observer counts what arrives in the log's seconds + 4 s."
