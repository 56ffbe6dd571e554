#!/usr/bin/env python3
"""The DDS gateway benchmark (issue 13; docs/dds.md "Benchmark"), one run, one host.

1. One-way latency p50/p99 (us) by size, 1 KB .. 2 MB, measured by the same DDS reader process
   (lcmx_bench_dds sink, envelope type):
     direct:  DDS writer process (lcmx_bench_dds dds-source) -> DDS reader
     gateway: lcmx publisher process (lcmx-source, shared memory) -> lcmx dds-gateway -> DDS reader
   --mode interleaved (default): one source process (lcmx_bench_dds both-source) sends on both
   paths in turn, message by message (the lcmx message at k/HZ, the DDS sample half a period
   later), and one sink process reads both topics, so both paths see the same moments of a
   shared machine. --mode blocks: one block per path, the two alternating per round (direct
   first in even rounds, gateway first in odd ones), as before 2026-11-25.
   Each of the --rounds rounds per size gives a ratio gateway p50 / direct p50 (p99 alike); the
   figure given is the median of those per-round ratios.
2. 6 MB throughput (Mbit/s at the reader): DDS writer -> reader, lcmx -> gateway -> reader, and
   ddsperf pub/sub (Cyclone's own tool, size 6 MB) on the same host.
Cyclone runs on loopback only (unicast to 127.0.0.1, no multicast); lcmx on a group of its own
pinned to lo. The DDS programs (source, sink, ddsperf) ask Cyclone for a socket receive buffer of
--rcvbuf (default 4MB, Cyclone's own default is 1 MiB) and take what the kernel allows
(net.core.rmem_max): with 1 MiB a 2 MB sample overruns the reader's buffer and stalls on
retransmission for ~50 ms in some runs, whichever path sent it. The gateway (a writer here) keeps
its own config.

usage: run.py BUILD_DIR [--mode interleaved|blocks] [--pin CPUS] [--quick] [--rounds N] [--csv FILE] [--sizes LIST]
              [--no-throughput]
              [--rcvbuf SIZE] [--spin-us US] [--slice-us US]
"""
import argparse, os, re, subprocess, sys, tempfile, time

p = argparse.ArgumentParser()
p.add_argument("build")
p.add_argument("--pin", default="", help="taskset CPU list for every process (e.g. 0), default none")
p.add_argument("--quick", action="store_true", help="fewer samples")
p.add_argument("--rounds", type=int, default=3, help="rounds per size (default 3)")
p.add_argument("--mode", choices=("interleaved", "blocks"), default="interleaved",
               help="interleaved: both paths message by message from one source (default); "
                    "blocks: one block per path per round")
p.add_argument("--csv", default="")
p.add_argument("--no-throughput", action="store_true", help="latency only (no 6 MB throughput part)")
p.add_argument("--sizes", default="",
               help="comma-separated message sizes in bytes, a subset of 1024,10240,102400,1048576,2097152 (default all)")
p.add_argument("--spin-us", type=int, default=None,
               help="the gateway's spin_us (default: the gateway's own default)")
p.add_argument("--slice-us", type=int, default=None,
               help="the gateway's slice_us (default: the gateway's own default; 0 = the kernel's default slice)")
p.add_argument("--rcvbuf", default="4MB",
               help="Cyclone SocketReceiveBufferSize max for the DDS programs, e.g. 4MB; '' = Cyclone's default (1 MiB)")
a = p.parse_args()
bench = os.path.join(a.build, "bench/dds/lcmx_bench_dds")
tool = os.path.join(a.build, "apps/lcmx")
domain = 1 + os.getpid() % 200
env = dict(os.environ)
env["CYCLONEDDS_URI"] = ("<General><Interfaces><NetworkInterface address=\"127.0.0.1\"/></Interfaces>"
                         "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto"
                         "</ParticipantIndex><MaxAutoParticipantIndex>60</MaxAutoParticipantIndex><Peers>"
                         "<Peer address=\"127.0.0.1\"/></Peers></Discovery>" +
                         ("<Internal><SocketReceiveBufferSize max=\"%s\"/></Internal>" % a.rcvbuf if a.rcvbuf else ""))
env["BENCH_DDS_DOMAIN"] = str(domain)
g = os.getpid()
env["LCMX_DISCOVERY_URL"] = "udpm://239.255.%d.%d:%d?ttl=0&iface=lo" % (1 + g // 250 % 250, 1 + g % 250, 30000 + g % 20000)
env["SPDLOG_LEVEL"] = "warn"
pin = ["taskset", "-c", a.pin] if a.pin else []
procs = []


def start(argv, stdin=subprocess.DEVNULL):
    pr = subprocess.Popen(pin + argv, env=env, stdin=stdin, stdout=subprocess.PIPE, text=True)
    procs.append(pr)
    return pr


def expect(pr, prefix, timeout=60):
    deadline = time.time() + timeout
    while time.time() < deadline:
        line = pr.stdout.readline()
        if not line:
            break
        if line.startswith(prefix):
            return line.strip()
    raise SystemExit("no '%s' from %s" % (prefix, pr.args))


def cpu_seconds(pid):
    """User + system CPU time of a process so far (/proc/PID/stat), in seconds."""
    with open("/proc/%d/stat" % pid) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def result(line):
    return {k: float(v) for k, v in re.findall(r"(\w+)=([\d.]+)", line)}


sizes = [1024, 10240, 102400, 1048576, 2097152]
plan = {1024: (400, 200), 10240: (400, 200), 102400: (300, 100), 1048576: (150, 30), 2097152: (100, 20)}
if a.quick:
    plan = {s: (max(50, n // 4), hz) for s, (n, hz) in plan.items()}
if a.sizes:
    try:
        sizes = [int(x) for x in a.sizes.split(",")]
    except ValueError:
        raise SystemExit("--sizes: a comma-separated list of byte counts, e.g. 1024,102400")
    bad = [x for x in sizes if x not in plan]
    if bad:
        raise SystemExit("--sizes: %s not among %s" % (bad, ",".join(str(x) for x in plan)))
tmp = tempfile.mkdtemp(prefix="lcmx_bench_dds_")
cfg = os.path.join(tmp, "gw.toml")
with open(cfg, "w") as f:
    f.write('name = "bench"\ndomain = %d\ninterface = "127.0.0.1"\nallow_multicast = false\npeers = ["127.0.0.1"]\n' % domain)
    if a.spin_us is not None:
        f.write('spin_us = %d\n' % a.spin_us)
    if a.slice_us is not None:
        f.write('slice_us = %d\n' % a.slice_us)
    for s in sizes + [6000000]:
        f.write('[[map]]\nchannel = "BENCH_%d"\ndirection = "to_dds"\ntopic = "G_%d"\n' % (s, s))
rows = []
thr = {}  # 6 MB throughput per path (empty with --no-throughput)
try:
    gw = start([tool, "dds-gateway", "--config", cfg])
    expect(gw, "dds-gateway bench: ready")
    gw_cpu0, wall0 = cpu_seconds(gw.pid), time.time()
    for s in sizes:
        n, hz = plan[s]
        rounds = []  # [{"direct": result, "gateway": result}] per round
        for r in range(max(1, a.rounds)):
            res = {}
            if a.mode == "interleaved":
                sink = start([bench, "sink", "D_%d,G_%d" % (s, s), str(n)])
                expect(sink, "ready")
                src = start([bench, "both-source", "BENCH_%d" % s, "D_%d" % s, str(n), str(s), str(hz)],
                            stdin=subprocess.PIPE)
                res["direct"] = result(expect(sink, "result i=0", 180))
                res["gateway"] = result(expect(sink, "result i=1", 30))
                src.stdin.close()
                src.wait(30)
                sink.wait(30)
            for path in () if a.mode == "interleaved" else (("direct", "gateway") if r % 2 == 0 else ("gateway", "direct")):
                sink = start([bench, "sink", ("D_%d" if path == "direct" else "G_%d") % s, str(n)])
                expect(sink, "ready")
                if path == "direct":
                    src = start([bench, "dds-source", "D_%d" % s, str(n), str(s), str(hz)])
                else:
                    src = start([bench, "lcmx-source", "BENCH_%d" % s, str(n), str(s), str(hz)], stdin=subprocess.PIPE)
                res[path] = result(expect(sink, "result", 180))
                if src.stdin:
                    src.stdin.close()
                src.wait(30)
                sink.wait(30)
            rounds.append(res)
            print("size %7d round %d  direct p50 %8.1f p99 %8.1f | gateway p50 %8.1f p99 %8.1f | ratio p50 %.2f p99 %.2f" % (
                s, r + 1, res["direct"]["p50_us"], res["direct"]["p99_us"], res["gateway"]["p50_us"],
                res["gateway"]["p99_us"], res["gateway"]["p50_us"] / res["direct"]["p50_us"],
                res["gateway"]["p99_us"] / res["direct"]["p99_us"]), flush=True)
        rows.append((s, rounds))
    gw_cpu = (cpu_seconds(gw.pid) - gw_cpu0) / max(time.time() - wall0, 1e-9)
    # 6 MB throughput.
    n6 = 15 if a.quick else 40
    if not a.no_throughput:
        sink = start([bench, "sink", "D_6000000", str(n6)]); expect(sink, "ready")
        src = start([bench, "dds-source", "D_6000000", str(n6), "6000000", "0"])
        thr["direct"] = result(expect(sink, "result", 300)); src.wait(60); sink.wait(30)
        sink = start([bench, "sink", "G_6000000", str(n6)]); expect(sink, "ready")
        # lcmx as fast as it publishes: what the gateway does not keep up with is lost (counted).
        src = start([bench, "lcmx-source", "BENCH_6000000", str(n6), "6000000", "0"], stdin=subprocess.PIPE)
        thr["gateway"] = result(expect(sink, "result", 300)); src.stdin.close(); src.wait(30); sink.wait(30)
        # ddsperf: sub and pub processes, 6 MB samples, 8 s; the sub's per-second "Mb/s" lines.
        dsub = start(["ddsperf", "-i", str(domain), "-D", "10", "sub"])
        dpub = start(["ddsperf", "-i", str(domain), "-D", "8", "pub", "size", "6MB"])
        out = dsub.communicate(timeout=60)[0]
        dpub.wait(30)
        rates = [float(x) for x in re.findall(r"([\d.]+) Mb/s", out)]
        rates = [r for r in rates if r > 0]
        thr["ddsperf"] = {"mbps": sorted(rates)[len(rates) // 2] if rates else 0.0}
    gw.terminate(); gw.wait(10)
finally:
    for pr in procs:
        if pr.poll() is None:
            pr.kill()
            pr.wait()
    import shutil
    shutil.rmtree(tmp, ignore_errors=True)

try:
    rmem_max = open("/proc/sys/net/core/rmem_max").read().strip()
except OSError:
    rmem_max = "?"
print("\n### One-way latency, us (%s; %s; DDS programs' receive buffer %s, rmem_max %s)\n" % (
    "pinned to CPU " + a.pin if a.pin else "unpinned", time.strftime("%Y-%m-%d %H:%M"),
    a.rcvbuf or "Cyclone's default", rmem_max))


def median(xs):
    xs = sorted(xs)
    m = len(xs) // 2
    return xs[m] if len(xs) % 2 else (xs[m - 1] + xs[m]) / 2


def summary(rounds):
    """Medians over the rounds: each path's p50/p99, and the per-round ratios' median."""
    out = {}
    for q in ("p50_us", "p99_us"):
        out["direct_" + q] = median([r["direct"][q] for r in rounds])
        out["gateway_" + q] = median([r["gateway"][q] for r in rounds])
        out["ratios_" + q] = [r["gateway"][q] / r["direct"][q] for r in rounds]
        out["ratio_" + q] = median(out["ratios_" + q])
    return out


print("mode %s, %d rounds per size; each figure is the median over the rounds, the ratio the median of the "
      "per-round ratios (gateway / direct).\n" % (a.mode, max(1, a.rounds)))
print("| size | direct p50 | direct p99 | gateway p50 | gateway p99 | ratio p50 (per round) | ratio p99 |")
print("|---:|---:|---:|---:|---:|---:|---:|")
for s, rounds in rows:
    m = summary(rounds)
    print("| %d | %.1f | %.1f | %.1f | %.1f | %.2f (%s) | %.2f |" % (
        s, m["direct_p50_us"], m["direct_p99_us"], m["gateway_p50_us"], m["gateway_p99_us"], m["ratio_p50_us"],
        ", ".join("%.2f" % x for x in m["ratios_p50_us"]), m["ratio_p99_us"]))
print("\nThe gateway's CPU use during the latency runs: %.0f %% of one CPU (spin_us %s, slice_us %s).\n" % (
    100 * gw_cpu, a.spin_us if a.spin_us is not None else "default",
    a.slice_us if a.slice_us is not None else "default"))
print("\n### Targets (issue 13): p50 gateway / direct, median of the rounds\n")
for s, rounds in rows:
    limit = 1.5 if s <= 1024 else (1.2 if s >= 102400 else None)
    if limit is None:
        continue
    r = summary(rounds)["ratio_p50_us"]
    print("- %d bytes: <= %.1fx: %s (%.2fx)" % (s, limit, "**holds**" if r <= limit else "**not met**", r))
if thr:
    print("\n### 6 MB throughput at the reader, Mbit/s\n")
    print("| DDS writer -> reader (reliable, KEEP_LAST 16 as the gateway) | lcmx -> gateway -> reader | ddsperf pub/sub (median of 1 s lines) |")
    print("|---:|---:|---:|")
    print("| %.0f (%d of %d received) | %.0f (%d of %d received) | %.0f |" % (
        thr["direct"]["mbps"], thr["direct"]["n"], n6, thr["gateway"]["mbps"], thr["gateway"]["n"], n6, thr["ddsperf"]["mbps"]))
    print("\nratio gateway/direct 6 MB throughput: %.2f; gateway/ddsperf: %.2f" % (
        thr["gateway"]["mbps"] / max(thr["direct"]["mbps"], 1e-9), thr["gateway"]["mbps"] / max(thr["ddsperf"]["mbps"], 1e-9)))
if a.csv:
    with open(a.csv, "w") as f:
        f.write("size,round,direct_p50_us,direct_p99_us,gateway_p50_us,gateway_p99_us\n")
        for s, rounds in rows:
            for i, r in enumerate(rounds):
                d, gg = r["direct"], r["gateway"]
                f.write("%d,%d,%.1f,%.1f,%.1f,%.1f\n" % (s, i + 1, d["p50_us"], d["p99_us"], gg["p50_us"], gg["p99_us"]))
