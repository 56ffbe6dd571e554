#!/usr/bin/env python3
"""Markdown table of run.py --json summaries (one JSON object per line).

Usage: table.py FILE          the issue's table (issue 33): one row per target configuration, from
                              the last summary in FILE that has it; a row FILE lacks is listed
                              below the table with the command that measures it
       table.py FILE --all    every summary in FILE, in order, with the same columns
An empty cell: the summary has no such figure (not measured by that run, or an older driver);
"null" in a summary (a figure that could not be measured) shows as "unmeasured".
"""
import json, statistics, sys

PEER = "build/bench/discovery/lcmx_bench_discovery_peer"
RUN = f"sudo python3 bench/discovery/run.py --peer {PEER} --runs 5 --json FILE"
# (row name, predicate over a summary, command that measures it)
ROWS = [
    ("1 host, N = 50", lambda r: r["hosts"] == 1 and r["n"] == 50, f"{RUN} --n 50 --churn"),
    ("1 host, N = 200", lambda r: r["hosts"] == 1 and r["n"] == 200, f"{RUN} --n 200 --churn"),
    ("1 host, N = 500", lambda r: r["hosts"] == 1 and r["n"] == 500, f"{RUN} --n 500 --churn"),
    ("8 hosts × 50, 20 % across", lambda r: r["hosts"] == 8 and r["n"] == 50 and r.get("topics", 10) == 10,
     f"{RUN} --hosts 8 --n 50 --cross 0.2 --churn"),
    ("small robot: 2 × 10, 3 topics", lambda r: r["hosts"] == 2 and r["n"] == 10 and r.get("topics", 10) == 3,
     f"{RUN} --hosts 2 --n 10 --topics 3 --cross 0.2"),
    ("host restart", lambda r: any(x is not None for x in r.get("restart_ms_per_other") or []),
     f"{RUN} --hosts 8 --n 50 --cross 0.2 --host-restart"),
]


def num(x, d=None):
    if x is None:
        return "unmeasured"
    if isinstance(x, float) and d is not None:
        x = round(x, d)
    return f"{x:,}" if isinstance(x, (int, float)) else str(x)


def kill(r, side):
    """max (p50) ms of the subscribers on that side, with their count when one did not unmatch."""
    if f"kill_{side}_unmatched" not in r:
        return ""
    k = r[f"kill_{side}_unmatched"]
    if k is None:
        return "—"
    if r.get("kill") is False:
        return ""
    cell = f'{num(r[f"kill_{side}_ms_max"])} ({num(r[f"kill_{side}_ms_p50"])})'
    got, all_ = k.split("/")
    return cell if got == all_ else f"{cell}, {k} unmatched"


def runs_list(v):
    """A per-run list: its median, and its max when there are several."""
    if v is None:
        return ""
    got = [x for x in v if x is not None]
    if not got:
        return "unmeasured"
    cell = num(round(statistics.median(got), 3))
    if len(v) > 1:
        cell += f" (max {num(max(got))})"
    return cell + ("" if len(got) == len(v) else f", {len(v) - len(got)} unmeasured")


def cell(r, key, d=None):
    return "" if key not in r else num(r[key], d)


COLS = [
    ("runs", lambda r: str(r.get("runs", ""))),
    ("matched", lambda r: str(r.get("matched", ""))),
    ("match p99 s (≤ 2)", lambda r: cell(r, "match_p99_s")),
    ("CPU %/proc (≤ 0.1)", lambda r: cell(r, "cpu_pct_per_process")),
    ("LAN disc. B/s/host max, mean (≤ 10,000)",
     lambda r: "" if r.get("hosts", 1) < 2 else
     cell(r, "lan_disc_Bps_per_host_max") + ("" if "lan_disc_Bps_per_host_mean" not in r else ", " + cell(r, "lan_disc_Bps_per_host_mean"))),
    ("LAN markers B/s/host max", lambda r: "" if r.get("hosts", 1) < 2 else cell(r, "lan_mark_Bps_per_host_max")),
    ("LAN disc. B to match (≤ 10,000)", lambda r: "" if r.get("hosts", 1) < 2 else cell(r, "lan_disc_bytes_to_match")),
    ("SIGKILL: own host ms max (p50) (≤ 100)", lambda r: kill(r, "local")),
    ("SIGKILL: other hosts ms max (p50) (≤ lease)",
     lambda r: "" if r.get("hosts", 1) < 2 else kill(r, "remote") + (f'; lease {r["lease_ms"]}' if kill(r, "remote") and "lease_ms" in r else "")),
    ("false expiry at launch (0)", lambda r: cell(r, "false_expiry_launch")),
    ("churn ms/other (≤ 2)", lambda r: "" if r.get("churn") is False else cell(r, "churn_ms_per_other")),
    ("host restart ms/other (≤ 5)", lambda r: runs_list(r.get("restart_ms_per_other"))),
]


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    rows = [json.loads(l) for l in open(sys.argv[1]) if l.strip()]
    out, missing = [], []
    if "--all" in sys.argv[2:]:
        out = [(r.get("label") or f'{r["hosts"]} × {r["n"]}', r) for r in rows]
    else:
        for name, pred, cmd in ROWS:
            hit = [r for r in rows if pred(r)]
            if hit:
                r = hit[-1]
                label = r.get("label") or ""
                if name == "host restart":  # of any configuration: say which
                    label = f'{r["hosts"]} × {r["n"]}' + (f", {label}" if label else "")
                out.append((name + (f" ({label})" if label and label.lower() not in name.lower() else ""), r))
            else:
                missing.append((name, cmd))
    print("| run | " + " | ".join(c[0] for c in COLS) + " |")
    print("|---|" + "---|" * len(COLS))
    for name, r in out:
        print(f"| {name} | " + " | ".join(f(r) for _, f in COLS) + " |")
    if missing:
        print()
        for name, cmd in missing:
            print(f"- {name}: not in {sys.argv[1]} (`{cmd}`)")


if __name__ == "__main__":
    main()
