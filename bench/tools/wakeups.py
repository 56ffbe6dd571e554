#!/usr/bin/env python3
"""Wake-up placement and delay between the processes of one benchmark (issue 15 item 3).

Reads `perf script -F comm,tid,cpu,time,event,trace` of a `perf sched record` on stdin and,
for every sched_waking of a task whose name starts with --comm by a task with that prefix,
finds when the wakee was switched in. Prints, per placement (the wakee ran on the waker's CPU
or on the other one), the count and the waking -> running delay p50/p99 in microseconds.

  perf sched record -o /tmp/s.data -- build/bench/lcmx_bench_latency --methods lcmx-loan --sizes 1K
  perf script -i /tmp/s.data -F comm,tid,cpu,time,event,trace | bench/tools/wakeups.py
"""
import argparse
import re
import sys

LINE = re.compile(r"\s*(\S+)\s+(\d+)\s+\[(\d+)\]\s+([\d.]+):\s+sched:(\w+):\s+(.*)")
WAKING = re.compile(r"comm=(\S+) pid=(\d+) .*target_cpu=(\d+)")
SWITCH = re.compile(r"next_comm=(\S+) next_pid=(\d+)")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--comm", default="lcmx_bench", help="task name prefix (perf truncates names to 15 characters)")
    args = ap.parse_args()
    pending = {}  # wakee tid -> (time, waker cpu)
    delays = {"same CPU": [], "other CPU": []}
    for line in sys.stdin:
        m = LINE.match(line)
        if not m:
            continue
        comm, _tid, cpu, t, event, trace = m.groups()
        cpu, t = int(cpu), float(t)
        if event == "sched_waking" and comm.startswith(args.comm):
            w = WAKING.search(trace)
            if w and w.group(1).startswith(args.comm):
                pending[int(w.group(2))] = (t, cpu)
        elif event == "sched_switch":
            s = SWITCH.search(trace)
            if s and int(s.group(2)) in pending:
                t0, waker_cpu = pending.pop(int(s.group(2)))
                delays["same CPU" if waker_cpu == cpu else "other CPU"].append((t - t0) * 1e6)
    total = sum(len(v) for v in delays.values())
    if total == 0:
        print("no wake-ups between tasks named %s*" % args.comm)
        return 1
    print("| wakee ran on | wake-ups | share | waking -> running p50 µs | p99 µs |")
    print("|---|---:|---:|---:|---:|")
    for k, v in delays.items():
        v.sort()
        pct = lambda q: v[min(len(v) - 1, int(q * len(v)))] if v else float("nan")
        print("| %s | %d | %.0f %% | %.1f | %.1f |" % (k, len(v), 100.0 * len(v) / total, pct(0.5), pct(0.99)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
