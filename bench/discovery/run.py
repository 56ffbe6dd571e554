#!/usr/bin/env python3
"""bench/discovery driver (issue 33, docs/discovery.md "Benchmark").

Starts N copies of lcmx_bench_discovery_peer (10 publishers at 1 Hz, 10 subscribers of another
process's topics) within --spread seconds and measures, per run:
  match     time from the last start until each process had all its subscriptions matched
            (p50/p99/max over processes; "unmatched" = not within --timeout)
  cpu       steady-state CPU of all peers (utime+stime from /proc over --window s), % of one core
  group     bytes on the host-local group over the window (lcm-logger's log, which records
            everything on the group, as a stock user's recorder would)
  churn     CPU (ms) of all the other peers while one peer is SIGKILLed and one started
  restart   (--host-restart, --hosts > 1) every peer of host 0 SIGKILLed, then all started again
            within --spread: CPU (ms) of each peer of the other hosts from the kill until the
            restarted ones matched again and 3 s more (idle subtracted), and the time from the
            last restart until every restarted peer matched
Everything runs inside network namespaces this script creates (lo only, or a bridge between
emulated hosts with --hosts): no packet leaves them. They are removed at exit, even on failure.
Usage (root): run.py --peer build/bench/discovery/lcmx_bench_discovery_peer --n 50 --runs 3
              run.py ... --hosts 8 --n 50 --cross 0.2    (8 emulated hosts x 50 processes)
"""
import argparse, os, random, signal, statistics, subprocess, sys, tempfile, time, json, glob, shutil

TICK = os.sysconf("SC_CLK_TCK")


def sh(*cmd, check=True):
    return subprocess.run(cmd, check=check, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


class Net:
    """hosts network namespaces; with more than one, a bridge namespace joins them by veths."""

    def __init__(self, hosts, tag):
        self.tag = tag
        self.hosts = [f"ldb{tag}h{i}" for i in range(hosts)]
        self.sw = f"ldb{tag}sw" if hosts > 1 else None
        self.created = []
        try:
            for h in self.hosts + ([self.sw] if self.sw else []):
                sh("ip", "netns", "add", h)
                self.created.append(h)
                sh("ip", "-n", h, "link", "set", "lo", "up")
                sh("ip", "-n", h, "link", "set", "lo", "multicast", "on")
            if self.sw:
                sh("ip", "-n", self.sw, "link", "add", "br0", "type", "bridge", "mcast_snooping", "0")
                sh("ip", "-n", self.sw, "link", "set", "br0", "up")
                # the listener (listen.py) hears every host's datagrams on the bridge itself
                sh("ip", "-n", self.sw, "addr", "add", "10.77.0.250/24", "dev", "br0")
                sh("ip", "-n", self.sw, "route", "add", "224.0.0.0/4", "dev", "br0")
                for i, h in enumerate(self.hosts):
                    sh("ip", "link", "add", f"ldb{tag}v{i}", "netns", h, "type", "veth", "peer", "name", f"p{i}", "netns", self.sw)
                    sh("ip", "-n", h, "link", "set", f"ldb{tag}v{i}", "name", "eth0")
                    sh("ip", "-n", h, "addr", "add", f"10.77.0.{i + 1}/24", "dev", "eth0")
                    sh("ip", "-n", h, "link", "set", "eth0", "up")
                    sh("ip", "-n", self.sw, "link", "set", f"p{i}", "master", "br0")
                    sh("ip", "-n", self.sw, "link", "set", f"p{i}", "up")
                    sh("ip", "-n", h, "route", "add", "224.0.0.0/4", "dev", "eth0")
                    # count what each host sends on the LAN (discovery only: channel filter below)
            else:
                sh("ip", "-n", self.hosts[0], "route", "add", "224.0.0.0/4", "dev", "lo")
        except Exception:
            self.close()
            raise

    def tx_bytes(self, i):
        out = sh("ip", "-n", self.hosts[i], "-s", "-j", "link", "show", "eth0").stdout
        return json.loads(out)[0]["stats64"]["tx"]["bytes"]

    def close(self):
        for h in self.created:
            subprocess.run(["ip", "netns", "pids", h], stdout=subprocess.PIPE)
            sh("ip", "netns", "del", h, check=False)
        self.created = []


def cpu_ticks(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            parts = f.read().rsplit(")", 1)[1].split()
        return int(parts[11]) + int(parts[12])
    except OSError:
        return 0


def pct(values, p):
    if not values:
        return float("nan")
    v = sorted(values)
    k = min(len(v) - 1, max(0, int(round(p / 100.0 * len(v) + 0.5)) - 1))
    return v[k]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--peer", required=True)
    ap.add_argument("--n", type=int, default=50, help="processes per host")
    ap.add_argument("--hosts", type=int, default=1)
    ap.add_argument("--cross", type=float, default=0.0, help="fraction of subscriptions to another host's topics")
    ap.add_argument("--topics", type=int, default=10)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--spread", type=float, default=2.0)
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--window", type=float, default=10.0)
    ap.add_argument("--settle", type=float, default=3.0)
    ap.add_argument("--churn", action="store_true")
    ap.add_argument("--host-restart", action="store_true", help="kill and restart every peer of host 0 (--hosts > 1)")
    ap.add_argument("--logger", default=shutil.which("lcm-logger"))
    ap.add_argument("--label", default="")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    results = []
    for run in range(args.runs):
        results.append(one_run(args, run))
        print(json.dumps({k: v for k, v in results[-1].items() if k != "match_s"}), flush=True)
    match = [x for r in results for x in r["match_s"]]
    summary = {
        "label": args.label, "hosts": args.hosts, "n": args.n, "runs": args.runs,
        "matched": f'{sum(r["matched"] for r in results)}/{sum(r["total"] for r in results)}',
        "match_p50_s": round(pct(match, 50), 3), "match_p99_s": round(pct(match, 99), 3),
        "match_max_s": round(max(match) if match else float("nan"), 3),
        "cpu_pct_all": round(statistics.median(r["cpu_pct"] for r in results), 1),
        "cpu_pct_per_process": round(statistics.median(r["cpu_pct"] for r in results) / (args.n * args.hosts), 3),
        "group_bytes_per_s": round(statistics.median(r["group_Bps"] for r in results)),
        "lan_tx_bytes_per_s_per_host": round(statistics.median(r["lan_Bps_per_host"] for r in results)) if args.hosts > 1 else None,
        "lan_bytes_to_match": round(statistics.median(r["lan_bytes_to_match"] for r in results)) if args.hosts > 1 else None,
        "lan_disc_bytes_to_match": round(statistics.median(r["lan_disc_bytes_to_match"] for r in results)) if args.hosts > 1 else None,
        "lan_disc_Bps_per_host_max": round(statistics.median(r["lan_disc_Bps_per_host_max"] for r in results)) if args.hosts > 1 else None,
        "churn_ms_per_other": results[0].get("churn_ms_per_other"),
        "restart_ms_per_other": [r.get("restart_ms_per_other") for r in results] if args.host_restart else None,
        "restart_rematch_s": [r.get("restart_rematch_s") for r in results] if args.host_restart else None,
        "last_ready_s": round(statistics.median(r["last_ready_s"] for r in results), 3),
    }
    print("SUMMARY " + json.dumps(summary), flush=True)
    if args.json:
        with open(args.json, "a") as f:
            f.write(json.dumps(summary) + "\n")


def by_kind(listened_bytes):
    """Discovery bytes of every host summed by kind (listen.py's "kinds")."""
    kinds = sorted({k for v in listened_bytes.values() for k in v.get("kinds", {})})
    return {k: sum(v.get("kinds", {}).get(k, 0) for v in listened_bytes.values()) for k in kinds}


def extra_ms_per(others, c0, since, cpu_pct, n_steady):
    """CPU (ms) each of `others` (pids) spent since `since` beyond its idle share: their ticks
    since c0, less the steady state's `cpu_pct` (of n_steady processes) over the same time."""
    c1 = sum(cpu_ticks(x) for x in others)
    idle = (cpu_pct / 100.0) * (time.monotonic() - since) * TICK * len(others) / n_steady
    return round(max(0.0, (c1 - c0) - idle) / TICK * 1000 / len(others), 3)


def wait_matched(procs, timeout):
    """Reads the peers' stdout until each printed MATCHED or `timeout` s passed: returns
    {index: MATCHED ns}, {index: READY ns}, {index: CPU ms at READY}."""
    matched, ready, ready_cpu = {}, {}, {}
    for p in procs:
        os.set_blocking(p.stdout.fileno(), False)
    deadline = time.monotonic() + timeout
    bufs = [b""] * len(procs)
    while len(matched) < len(procs) and time.monotonic() < deadline:
        for k, p in enumerate(procs):
            if k in matched:
                continue
            try:
                chunk = p.stdout.read()
            except (BlockingIOError, TypeError):
                chunk = None
            if chunk:
                bufs[k] += chunk
                for line in bufs[k].split(b"\n"):
                    if line.startswith(b"MATCHED "):
                        matched[k] = int(line.split()[1])
                    elif line.startswith(b"READY "):
                        ready[k] = int(line.split()[1])
                        ready_cpu[k] = int(line.split()[2]) / 1000.0
        time.sleep(0.02)
    return matched, ready, ready_cpu


def one_run(args, run):
    tag = f"{os.getpid() % 10000}r{run}"
    net = Net(args.hosts, tag)
    procs = []
    logger = None
    tmp = tempfile.mkdtemp(prefix="lcmx_bench_disc_")
    try:
        salt = (os.getpid() * 7 + run) % 250 + 1
        local = f"udpm://239.255.{salt}.67:{17000 + salt}?ttl=0"
        vehicle = f"udpm://239.255.{salt}.68:{18000 + salt}?ttl=1&iface=eth0"
        env = dict(os.environ)
        env["LCMX_DISCOVERY_URL"] = local
        env.pop("LCMX_VEHICLE_URL", None)
        if args.hosts > 1:
            env["LCMX_VEHICLE_URL"] = vehicle
        env["LCMX_LOG_LEVEL"] = env.get("LCMX_LOG_LEVEL", "warn")
        env["SPDLOG_LEVEL"] = env.get("SPDLOG_LEVEL", "warn")
        if args.logger:
            logf = os.path.join(tmp, "group.lcmlog")
            lenv = dict(env)
            lenv["LCM_DEFAULT_URL"] = local
            logger = subprocess.Popen(["ip", "netns", "exec", net.hosts[0], args.logger, "-q", "-f", logf],
                                      env=lenv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        listen = os.path.join(os.path.dirname(os.path.abspath(__file__)), "listen.py")
        vg, vp = f"239.255.{salt}.68", 18000 + salt

        def listener():
            if args.hosts < 2:
                return None
            return subprocess.Popen(["ip", "netns", "exec", net.sw, sys.executable, listen, vg, str(vp), "10.77.0.250", "3600"],
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)

        def listened(p):
            if p is None:
                return {}
            p.send_signal(signal.SIGTERM)
            out = p.communicate(timeout=10)[0]
            try:
                return json.loads(out.strip().splitlines()[-1])
            except Exception:
                return {}

        cold = listener()
        time.sleep(0.3 if cold else 0)
        total = args.n * args.hosts
        rng = random.Random(run)
        starts = {}
        lan0 = [net.tx_bytes(h) for h in range(args.hosts)] if args.hosts > 1 else []

        def subs_of(h, i):
            out = []
            for k in range(args.topics):
                if args.hosts > 1 and rng.random() < args.cross:
                    oh = (h + 1 + rng.randrange(args.hosts - 1)) % args.hosts
                    out += ["--sub", f"{oh * args.n + rng.randrange(args.n)}:{k}"]
                else:
                    out += ["--sub", f"{h * args.n + (i + 1) % args.n}:{k}"]
            return out

        host_of = {}

        def launch(pairs):
            """Starts a peer per (host, index), evenly over --spread s; returns them."""
            out, t0 = [], time.monotonic()
            for k, (h, i) in enumerate(pairs):
                d = t0 + args.spread * k / max(1, len(pairs) - 1) - time.monotonic()
                if d > 0:
                    time.sleep(d)
                out.append(start(h, i))
            return out

        def start(h, i):
            idx = h * args.n + i
            p = subprocess.Popen(["ip", "netns", "exec", net.hosts[h], args.peer, "--index", str(idx), "--n", str(total),
                                  "--topics", str(args.topics), "--prefix", f"T{tag}"] + subs_of(h, i),
                                 env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
            starts[idx] = time.monotonic_ns()
            host_of[p.pid] = h
            return p

        order = [(h, i) for h in range(args.hosts) for i in range(args.n)]
        procs.extend(launch(order))
        last_start = max(starts.values())
        matched, ready, ready_cpu = wait_matched(procs, args.timeout)
        lan_to_match = sum(net.tx_bytes(h) - lan0[h] for h in range(args.hosts)) if args.hosts > 1 else 0
        cold_bytes = listened(cold)
        match_s = [max(0, t - last_start) / 1e9 for t in matched.values()]
        # when the last process had its endpoints (start-up: exec, runtime, shm segments)
        ready_s = (max(ready.values()) - last_start) / 1e9 if ready else float("nan")
        time.sleep(args.settle)
        pids = [p.pid for p in procs]
        # the peer is the child of `ip netns exec` (which execs: same pid)
        c0 = sum(cpu_ticks(x) for x in pids)
        g0 = os.path.getsize(logf) if args.logger and os.path.exists(logf) else 0
        l0 = [net.tx_bytes(h) for h in range(args.hosts)] if args.hosts > 1 else []
        steady = listener()
        w0 = time.monotonic()
        time.sleep(args.window)
        w = time.monotonic() - w0
        steady_bytes = listened(steady)
        c1 = sum(cpu_ticks(x) for x in pids)
        g1 = os.path.getsize(logf) if args.logger and os.path.exists(logf) else 0
        l1 = [net.tx_bytes(h) for h in range(args.hosts)] if args.hosts > 1 else []
        res = {"run": run, "total": len(procs), "matched": len(matched), "match_s": match_s, "last_ready_s": ready_s,
               "startup_cpu_ms_p50": pct(list(ready_cpu.values()), 50), "startup_cpu_ms_max": max(ready_cpu.values(), default=0),
               "cpu_pct": 100.0 * (c1 - c0) / TICK / w, "group_Bps": (g1 - g0) / w,
               "lan_Bps_per_host": (sum(l1) - sum(l0)) / w / max(1, args.hosts),
               "lan_bytes_to_match": lan_to_match,
               # discovery datagrams only (LCMX_BEACON on the vehicle group), heard on the switch
               "lan_disc_bytes_to_match": sum(v["disc"] for v in cold_bytes.values()),
               "lan_disc_bytes_to_match_by_kind": by_kind(cold_bytes),
               "lan_disc_datagrams_to_match": sum(v.get("disc_datagrams", 0) for v in cold_bytes.values()),
               "lan_disc_Bps_per_host_max": max([v["disc"] / w for v in steady_bytes.values()], default=0),
               "lan_disc_Bps_steady_by_kind": {k: round(v / w, 1) for k, v in by_kind(steady_bytes).items()},
               "lan_data_Bps_total": sum(v["data"] for v in steady_bytes.values()) / w}
        if args.churn:
            victim = procs[len(procs) // 2]
            others = [p.pid for p in procs if p is not victim]
            c0 = sum(cpu_ticks(x) for x in others)
            w0 = time.monotonic()
            victim.send_signal(signal.SIGKILL)
            victim.wait()
            time.sleep(2.0)
            h, i = order[len(procs) // 2]
            newp = start(h, i)
            procs.append(newp)
            time.sleep(3.0)
            # the same window without churn, from the steady state above, is subtracted
            res["churn_ms_per_other"] = extra_ms_per(others, c0, w0, res["cpu_pct"], len(pids))  # the steady window measured len(pids) processes
        if args.host_restart and args.hosts > 1:
            # The whole of host 0 restarts (its software stack; /dev/shm stays, as after a
            # restart of the stack, not a reboot): every peer killed, then all started again.
            victims = [k for k, (h, i) in enumerate(order) if h == 0 and procs[k].poll() is None]
            others = [p.pid for p in procs if host_of[p.pid] != 0 and p.poll() is None]
            c0 = sum(cpu_ticks(x) for x in others)
            w0 = time.monotonic()
            for k in victims:
                procs[k].send_signal(signal.SIGKILL)
            for k in victims:
                procs[k].wait()
            fresh = launch([order[k] for k in victims])
            last = time.monotonic_ns()
            procs.extend(fresh)
            done, _, _ = wait_matched(fresh, args.timeout)
            time.sleep(3.0)
            res["restart_ms_per_other"] = extra_ms_per(others, c0, w0, res["cpu_pct"], len(order))
            res["restart_rematch_s"] = (round(max(0, max(done.values()) - last) / 1e9, 3)
                                        if len(done) == len(fresh) else None)
            res["restart_rematched"] = f"{len(done)}/{len(fresh)}"
        return res
    finally:
        for p in procs:
            try:
                p.stdin.close()
            except Exception:
                pass
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if logger:
            logger.terminate()
            try:
                logger.wait(timeout=5)
            except subprocess.TimeoutExpired:
                logger.kill()
        net.close()
        shutil.rmtree(tmp, ignore_errors=True)
        for f in glob.glob(f"/dev/shm/lcmxreg_*") + glob.glob("/dev/shm/lcmx_*"):
            pass  # the peers remove theirs; leftovers of killed peers are reclaimed by the next runtime


if __name__ == "__main__":
    main()
