#!/usr/bin/env bash
# lcmx foxglove under load (issue 36; README.md here): 100 channels x 100 Hz small messages + a
# 1920x1080 rgb8 image (6.2 MB) at 10 Hz, in two runs of the same publisher process, one after the
# other in this invocation:
#   without: a plain lcmx subscriber of every channel (so the publishers encode into shared
#            memory exactly as with the server: a fair baseline of publish());
#   with:    `lcmx foxglove`, two reading WebSocket clients subscribed to everything (100 small
#            channels, the image and its /image RawImage view) and one that subscribes to
#            everything and never reads (lcmx_bench_foxglove client: C++, it reads only the frame
#            header, so the server is what is measured).
# Reports: server CPU (% of one core) over the measured window, each reading client's delivered
# rates and publish -> receipt latency p50/p99 (frame timestamp = utime, CLOCK_REALTIME at
# publish), the stuck client's queue (bounded by --queue-mb) and the server's RSS, and publish()
# p50/p99 without vs with the server.
# Usage: bench/foxglove/run.sh [BUILD_DIR] [SECONDS] [WARMUP]   (loopback; a private discovery group)
# Environment: PUB_CPUS / REST_CPUS (taskset -c lists, e.g. 0 and 1): pin the publishers, and
# everything else (plain subscriber, server, clients), to those CPUs; SERVER_ARGS: extra
# `lcmx foxglove` options; PERF=FILE: a perf profile of the server over the window; KEEP=1 keeps
# the outputs.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
build=${1:-$root/build}
secs=${2:-15}
warm=${3:-3}
pub_run=${PUB_CPUS:+taskset -c $PUB_CPUS}
run=${REST_CPUS:+taskset -c $REST_CPUS}
lcmx=$build/apps/lcmx
bench=$build/bench/foxglove/lcmx_bench_foxglove
tmp=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; if [[ -n ${KEEP:-} ]]; then echo "outputs kept in $tmp"; else rm -rf "$tmp"; fi; }
trap cleanup EXIT
export LCMX_DISCOVERY_URL="udpm://239.255.$((RANDOM % 200 + 20)).$((RANDOM % 250 + 1)):$((20000 + RANDOM % 20000))?ttl=0&iface=lo"
export LCMX_VEHICLE_URL=
export SPDLOG_LEVEL=warn
pub_secs=$((warm + secs + 6))

ticks() { awk '{print $14 + $15}' "/proc/$1/stat"; }
# Waits (bounded) until FILE has a line matching RE.
wait_for() { for _ in $(seq 600); do grep -q "$2" "$1" 2>/dev/null && return 0; sleep 0.1; done; echo "timeout waiting for '$2' in $1" >&2; cat "$1" >&2; exit 1; }
hz=$(getconf CLK_TCK)
cpu() { python3 -c "print(round(100*($2-$1)/$hz/$3,1))"; }

load0=$(cut -d' ' -f1-3 /proc/loadavg)
echo "== without the server: a plain lcmx subscriber of every channel ($warm s warm-up, $secs s measured)"
$run "$bench" sub --seconds "$secs" --warmup "$warm" > "$tmp/sub.out" &
sp=$!; pids+=("$sp")
wait_for "$tmp/sub.out" READY
$pub_run "$bench" pub --seconds "$pub_secs" > "$tmp/pub0.out" &
pp=$!; pids+=("$pp")
wait_for "$tmp/pub0.out" MATCHED
sleep "$warm"
p0=$(ticks "$pp"); s0=$(ticks "$sp"); w0=$(date +%s.%N)
sleep "$secs"
p1=$(ticks "$pp"); s1=$(ticks "$sp"); w1=$(date +%s.%N)
wait "$pp" "$sp"
win=$(python3 -c "print($w1-$w0)")
pub0_cpu=$(cpu "$p0" "$p1" "$win"); sub_cpu=$(cpu "$s0" "$s1" "$win")

echo "== with lcmx foxglove: 2 reading clients + 1 that never reads ($warm s warm-up, $secs s measured)"
$run "$lcmx" foxglove --port 0 --json --types "$root/lcmtypes" --types "$here" --stats 1 ${SERVER_ARGS:-} > "$tmp/server.out" 2>&1 &
srv=$!; pids+=("$srv")
wait_for "$tmp/server.out" '"ready":true'
port=$(grep -m1 '"ready":true' "$tmp/server.out" | sed 's/.*"port":\([0-9]*\).*/\1/')
$pub_run "$bench" pub --seconds "$pub_secs" > "$tmp/pub1.out" &
pp=$!; pids+=("$pp")
$run "$bench" client --port "$port" --clients 2 --slow 1 --seconds "$secs" --warmup "$warm" > "$tmp/clients.out" &
cp=$!; pids+=("$cp")
wait_for "$tmp/pub1.out" MATCHED
sleep "$warm"
t0=$(ticks "$srv"); p0=$(ticks "$pp"); c0=$(ticks "$cp"); w0=$(date +%s.%N)
if [[ -n ${PERF:-} ]]; then  # PERF=FILE: a perf profile of the server over the window
  perf record -q -F 499 -g -p "$srv" -o "$PERF" -- sleep "$secs" 2>/dev/null
else
  sleep "$secs"
fi
t1=$(ticks "$srv"); p1=$(ticks "$pp"); c1=$(ticks "$cp"); w1=$(date +%s.%N)
rss=$(awk '/VmRSS/ {print $2}' "/proc/$srv/status"); hwm=$(awk '/VmHWM/ {print $2}' "/proc/$srv/status")
wait "$cp" "$pp"
win=$(python3 -c "print($w1-$w0)")
srv_cpu=$(cpu "$t0" "$t1" "$win"); pub1_cpu=$(cpu "$p0" "$p1" "$win"); cl_cpu=$(cpu "$c0" "$c1" "$win")
grep '^{"clients":3' "$tmp/server.out" > "$tmp/stats.json" || true

echo "pinning: publishers ${PUB_CPUS:-any CPU}, the rest ${REST_CPUS:-any CPU}; load average before: $load0"
python3 - "$tmp" "$srv_cpu" "$rss" "$hwm" "$pub0_cpu" "$pub1_cpu" "$sub_cpu" "$cl_cpu" <<'PY'
import json, sys
tmp, srv_cpu, rss, hwm, pub0_cpu, pub1_cpu, sub_cpu, cl_cpu = sys.argv[1:]
base = json.loads(open(f"{tmp}/pub0.out").read().splitlines()[-1])
with_ = json.loads(open(f"{tmp}/pub1.out").read().splitlines()[-1])
sub = json.loads([l for l in open(f"{tmp}/sub.out") if l.startswith('{')][-1])
clients = [json.loads(l) for l in open(f"{tmp}/clients.out") if l.startswith('{')]
stats_lines = [json.loads(l) for l in open(f"{tmp}/stats.json")]
stats = {"max_client_queue_bytes": max([s["max_client_queue_bytes"] for s in stats_lines] or [0]),
         "dropped": stats_lines[-1]["dropped"] if stats_lines else "?",
         "per_client": stats_lines[-1].get("per_client", []) if stats_lines else []}
print(f"\nCPU (% of one core): server {srv_cpu}, clients process {cl_cpu}, publishers {pub0_cpu} -> {pub1_cpu}, plain subscriber (without run) {sub_cpu}")
print(f"server RSS {int(rss)/1024:.0f} MiB (peak {int(hwm)/1024:.0f} MiB); fullest client queue (1 s samples) {stats['max_client_queue_bytes']/2**20:.1f} MiB; "
      f"messages dropped from client queues {stats['dropped']}")
print("\n| receiver | small msgs/s (of 10000) | small delivered (of published in window) | slowest small channel (Hz) | image Hz | RawImage view Hz | small p50/p99 ms | image p50/p99 ms | view p50/p99 ms |")
print("|---|---|---|---|---|---|---|---|---|")
f = lambda us: f"{us/1000:.2f}" if us >= 0 else "-"
print(f"| plain lcmx subscriber (without) | {sub['small_hz']:.0f} | | | {sub['image_hz']:.1f} | | {f(sub['small_p50_us'])} / {f(sub['small_p99_us'])} | {f(sub['image_p50_us'])} / {f(sub['image_p99_us'])} | |")
for c in clients:
    if c["role"] == "client":
        err = f" ({c['error']})" if c["error"] else ""
        print(f"| WebSocket client {c['client']}{err} | {c['small_hz']:.0f} | {100*c['small_delivered']:.1f} % | {c['small_min_channel_hz']:.0f} | {c['image_hz']:.1f} | {c['view_hz']:.1f} | "
              f"{f(c['small_p50_us'])} / {f(c['small_p99_us'])} | {f(c['image_p50_us'])} / {f(c['image_p99_us'])} | {f(c['view_p50_us'])} / {f(c['view_p99_us'])} |")
print("\n| publish() µs | without server | with server | ratio |")
print("|---|---|---|---|")
for k in ("small_p50_us", "small_p99_us", "image_p50_us", "image_p99_us"):
    r = with_[k] / base[k] if base[k] else float("nan")
    print(f"| {k[:-3]} | {base[k]} | {with_[k]} | {r:.2f} |")
print(f"\npublished: without {base['small_published']} small + {base['images_published']} images, with {with_['small_published']} + {with_['images_published']}; "
      f"publisher rounds late p50/p99: without {base['round_late_p50_ms']}/{base['round_late_p99_ms']} ms, with {with_['round_late_p50_ms']}/{with_['round_late_p99_ms']} ms")
per = stats.get("per_client", [])
if per:
    print("client queues at the end of the window (server --stats): " + "; ".join(
        f"{c['remote']}: {c['queued_bytes']/2**20:.1f} MiB, {c['queued_messages']} msgs, dropped {c['dropped']}" for c in per))
PY
