#!/usr/bin/env python3
"""Markdown table of run.py --json summaries (one JSON object per line). Usage: table.py FILE"""
import json, sys

rows = [json.loads(l) for l in open(sys.argv[1]) if l.strip()]
cols = [("label", "run"), ("matched", "matched"), ("match_p50_s", "match p50 s"), ("match_p99_s", "match p99 s"),
        ("last_ready_s", "last ready s"), ("cpu_pct_all", "CPU % all"), ("cpu_pct_per_process", "CPU %/proc"),
        ("group_bytes_per_s", "host group B/s (lcm-logger)"), ("lan_disc_Bps_per_host_max", "LAN disc. B/s/host max"),
        ("lan_disc_bytes_to_match", "LAN disc. B to match"), ("churn_ms_per_other", "churn ms/other")]
print("| " + " | ".join(c[1] for c in cols) + " |")
print("|" + "---|" * len(cols))
for r in rows:
    print("| " + " | ".join("" if r.get(k) is None else str(r.get(k)) for k, _ in cols) + " |")
