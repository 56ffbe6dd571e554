#!/usr/bin/env python3
"""Before/after tables (Markdown) from the files bench/before_after.sh writes (issue 15).

Reads OUTDIR/latency-{before,after}-<round>.md, udp-{before,after}.md and
bridge-{before,after}.md, and, when present, tput-<version>-<round>.md: unshaped-link
throughput runs of lcmx_bench_bridge (`--only throughput --link-rate "" --markdown ...`), one
file per version and round, versions in the order given by --versions. Prints the tables on
stdout; a file that is missing or has no table is named on stderr and its cells left empty.

  sudo bench/before_after.sh BEFORE_BUILD AFTER_BUILD /tmp/b15 2
  bench/tools/before_after_tables.py /tmp/b15 [--versions before,item1,now]
"""
import argparse
import os
import re
import sys


def rows(path):
    """The table rows of a Markdown file (header rows included, separator rows left out)."""
    if not os.path.exists(path):
        print(f"before_after_tables: {path}: missing", file=sys.stderr)
        return []
    out = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.startswith("|") and not line.startswith("|---"):
                out.append([c.strip() for c in line.strip().strip("|").split("|")])
    if not out:
        print(f"before_after_tables: {path}: no table", file=sys.stderr)
    return out


def tables(rs):
    """Splits rows into (header, body) pairs: a row whose first cell is 'size' or 'method'
    starts a table."""
    out = []
    for r in rs:
        if r[0] in ("size", "method", "scenario"):
            out.append((r, []))
        elif out:
            out[-1][1].append(r)
    return out


def latency(d, rounds, sizes, methods):
    data = {}
    for w in ("before", "after"):
        for r in rounds:
            for hdr, body in tables(rows(f"{d}/latency-{w}-{r}.md"))[:1]:
                for row in body:
                    data[(w, r, row[0])] = dict(zip(hdr, row))
    cols = [(w, r) for r in rounds for w in ("before", "after")]
    print("### Latency, one host (`lcmx_bench_latency`, defaults), p50 / p99 µs\n")
    print("| size | method | " + " | ".join(f"{w} r{r}" for w, r in cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for size in sizes:
        for m in methods:
            cells = [data.get((w, r, size), {}).get(m, "") for w, r in cols]
            print(f"| {size} | {m} | " + " | ".join(cells) + " |")


def udp(d):
    print("\n### UDP across two emulated hosts (`lcmx_bench_udp`, defaults): p50 / p99 µs (lost/sent)\n")
    print("| size or scenario | before: liblcm | before: lcmx | ratio | after: liblcm | after: lcmx | ratio |")
    print("|---|---|---|---|---|---|---|")
    before = [r for h, b in tables(rows(f"{d}/udp-before.md")) for r in b]
    after = [r for h, b in tables(rows(f"{d}/udp-after.md")) for r in b]
    for b, a in zip(before, after):
        cell = lambda r, i: r[i] if len(r) > i else ""
        print(f"| {b[0]} | {cell(b, 1)} | {cell(b, 2)} | {cell(b, 3)} | {cell(a, 1)} | {cell(a, 2)} | {cell(a, 3)} |")


def bridge(d):
    print("\n### Bridge (`lcmx_bench_bridge`, defaults: 2 subscribers on B, 2 Gbit/s link)\n")
    print("| figure | size | method | before | after |")
    print("|---|---|---|---|---|")
    tb = tables(rows(f"{d}/bridge-before.md"))
    ta = tables(rows(f"{d}/bridge-after.md"))
    for (hdr, body_b), (_, body_a) in zip(tb, ta):
        col = {name: i for i, name in enumerate(hdr)}
        for b, a in zip(body_b, body_a):
            if "x payload" in col:  # experiment 2
                f = lambda r: f"{r[col['p50 µs']]} / {r[col['p99 µs']]}, {r[col['x payload']]}"
                print(f"| exp. 2 latency p50 / p99 µs, link bytes x payload | {b[0]} | {b[1]} | {f(b)} | {f(a)} |")
            elif "messages" in col and hdr[0] == "size":  # experiment 3
                f = lambda r: f"{r[col['p50 µs']]} / {r[col['p99 µs']]}"
                print(f"| exp. 3 callback-time difference p50 / p99 µs | {b[0]} | {b[1]} | {f(b)} | {f(a)} |")
            elif "Gbit/s" in col:  # throughput
                cpu = [k for k in col if k.startswith("bridge CPU")]
                f = lambda r: r[col["Gbit/s"]] + (f" ({r[col[cpu[0]]]})" if cpu and len(r) > col[cpu[0]] else "")
                print(f"| throughput Gbit/s (bridge CPU s per GB) | 6 MB | {b[0]} | {f(b)} | {f(a)} |")


def throughput(d, versions):
    found = [(v, r) for r in range(1, 21) for v in versions if os.path.exists(f"{d}/tput-{v}-{r}.md")]
    if not found:
        return
    print("\n### Bridge throughput on the unshaped link (`--only throughput --link-rate \"\"`)\n")
    print("| round | version | bridge Gbit/s | iperf3 Gbit/s | bridge / iperf3 | sending bridge CPU s per GB (user) | receiving bridge CPU s per GB |")
    print("|---|---|---|---|---|---|---|")
    cpu_re = re.compile(r"A ([\d.]+) \(user ([\d.]+)\), B ([\d.]+)")
    for v, r in found:
        body = [row for _, b in tables(rows(f"{d}/tput-{v}-{r}.md")) for row in b]
        br = next((row for row in body if row[0] == "lcmx bridge"), None)
        ip = next((row for row in body if row[0].startswith("iperf3")), None)
        if br is None or ip is None:
            print(f"before_after_tables: tput-{v}-{r}.md: no bridge or iperf3 row", file=sys.stderr)
            continue
        ratio = f"{100 * float(br[1]) / float(ip[1]):.0f} %" if float(ip[1]) > 0 else "—"
        m = cpu_re.match(br[5]) if len(br) > 5 else None
        cpu = (f"{m.group(1)} ({m.group(2)})", m.group(3)) if m else ("—", "—")
        print(f"| {r} | {v} | {br[1]} | {ip[1]} | {ratio} | {cpu[0]} | {cpu[1]} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("outdir", help="the OUTDIR of bench/before_after.sh")
    ap.add_argument("--rounds", type=int, default=2, help="latency rounds (default 2)")
    ap.add_argument("--sizes", default="1 KB,100 KB,1 MB,6 MB", help="latency sizes shown")
    ap.add_argument("--methods", default="floor,liblcm,lcmx-intra,lcmx-shm,lcmx-loan", help="latency methods shown")
    ap.add_argument("--versions", default="before,item1,now", help="tput-<version>-<round>.md versions, in order")
    a = ap.parse_args()
    if not os.path.isdir(a.outdir):
        print(f"before_after_tables: {a.outdir}: not a directory", file=sys.stderr)
        return 2
    latency(a.outdir, range(1, a.rounds + 1), a.sizes.split(","), a.methods.split(","))
    udp(a.outdir)
    bridge(a.outdir)
    throughput(a.outdir, a.versions.split(","))
    return 0


if __name__ == "__main__":
    sys.exit(main())
