#!/usr/bin/env bash
# lcmx foxglove under load (issue 36): 100 channels x 100 Hz pose_t + a 6.2 MB image at 10 Hz,
# in two runs of the same publisher process: without the server, then with `lcmx foxglove`,
# two reading clients subscribed to everything and one client that stops reading.
# Reports: server CPU (% of one core), each reading client's delivered rate and latency
# (server receive -> client receipt; pose_t has no utime), the stuck client's bound (server
# RSS), and the publishers' publish() latency with vs without the server (same run).
# Usage: bench/foxglove/run.sh [BUILD_DIR] [SECONDS]   (loopback only; a private discovery group)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
build=${1:-$root/build}
secs=${2:-15}
lcmx=$build/apps/lcmx
pub=$build/bench/foxglove/lcmx_bench_foxglove_pub
client=$root/test/foxglove/client/fg_client.js
tmp=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; rm -rf "$tmp"; }
trap cleanup EXIT
export LCMX_DISCOVERY_URL="udpm://239.255.$((RANDOM % 200 + 20)).$((RANDOM % 250 + 1)):$((20000 + RANDOM % 20000))?ttl=0&iface=lo"
export SPDLOG_LEVEL=warn

cpu_ticks() { awk '{print $14 + $15}' "/proc/$1/stat"; }

echo "== without the server ($secs s)"
"$pub" --seconds "$secs" > "$tmp/pub0.txt"
base=$(tail -1 "$tmp/pub0.txt")

echo "== with lcmx foxglove, 2 reading clients + 1 stuck client ($secs s)"
"$lcmx" foxglove --port 0 --json --types "$root/lcmtypes" > "$tmp/server.txt" 2>&1 &
srv=$!; pids+=("$srv")
for _ in $(seq 100); do grep -q '"ready":true' "$tmp/server.txt" 2>/dev/null && break; sleep 0.1; done
port=$(head -1 "$tmp/server.txt" | sed 's/.*"port":\([0-9]*\).*/\1/')
"$pub" --seconds $((secs + 8)) > "$tmp/pub1.txt" &
pp=$!; pids+=("$pp")
sleep 3  # the channels are advertised (discovery), publishing has begun
for i in 1 2; do
  echo "{\"url\":\"ws://127.0.0.1:$port\",\"timeout_ms\":$(((secs + 20) * 1000)),\"subscribe_all\":true,\"count_only\":true,\"expect_topics\":[\"FGB_CAMERA\",\"FGB_POSE_99\"],\"run_ms\":$((secs * 1000)),\"stats_every_ms\":$((secs * 1000))}" > "$tmp/c$i.json"
  node "$client" "$tmp/c$i.json" > "$tmp/c$i.out" &
  pids+=("$!")
done
echo "{\"url\":\"ws://127.0.0.1:$port\",\"timeout_ms\":$(((secs + 20) * 1000)),\"subscribe_all\":true,\"slow\":true,\"expect_topics\":[\"FGB_CAMERA\"],\"run_ms\":$((secs * 1000))}" > "$tmp/slow.json"
node "$client" "$tmp/slow.json" > "$tmp/slow.out" &
pids+=("$!")
sleep 2
t0=$(cpu_ticks "$srv"); s0=$(date +%s.%N)
sleep "$secs"
t1=$(cpu_ticks "$srv"); s1=$(date +%s.%N)
rss=$(awk '/VmHWM/ {print $2}' "/proc/$srv/status")
wait "$pp"
with=$(tail -1 "$tmp/pub1.txt")
hz=$(getconf CLK_TCK)
cpu=$(python3 -c "print(round(100*($t1-$t0)/$hz/($s1-$s0),1))")
python3 - "$tmp" "$cpu" "$rss" "$base" "$with" <<'PY'
import json, sys
tmp, cpu, rss, base, with_ = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), json.loads(sys.argv[4]), json.loads(sys.argv[5])
print(f"\nserver CPU: {cpu} % of one core; server peak RSS (VmHWM): {rss/1024:.0f} MiB (per-client queue bound 64 MiB)")
print("\n| client | pose channels delivered (Hz, sum of 100) | image (Hz) | pose p50/p99 ms | image p50/p99 ms |")
print("|---|---|---|---|---|")
for i in (1, 2):
    stats = [json.loads(l) for l in open(f"{tmp}/c{i}.out") if '"stats"' in l]
    if not stats:
        print(f"| reading {i} | (no stats) | | | |"); continue
    t = stats[-1]["topics"]
    poses = [v for k, v in t.items() if k.startswith("FGB_POSE_") and "/" not in k]
    cam = t.get("FGB_CAMERA", {})
    p50 = sorted(v["p50_ms"] for v in poses if v["p50_ms"] is not None)
    p99 = sorted(v["p99_ms"] for v in poses if v["p99_ms"] is not None)
    med = lambda a: a[len(a)//2] if a else float("nan")
    print(f"| reading {i} | {sum(v['rate'] for v in poses):.0f} | {cam.get('rate', 0):.1f} | {med(p50):.2f} / {max(p99) if p99 else float('nan'):.2f} | {cam.get('p50_ms') or float('nan'):.1f} / {cam.get('p99_ms') or float('nan'):.1f} |")
print("\n| publish() latency (µs) | without server | with server | ratio |")
print("|---|---|---|---|")
for k in ("small_p50_us", "small_p99_us", "image_p50_us", "image_p99_us"):
    r = with_[k] / base[k] if base[k] else float("nan")
    print(f"| {k} | {base[k]} | {with_[k]} | {r:.2f} |")
PY
