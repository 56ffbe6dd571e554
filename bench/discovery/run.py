#!/usr/bin/env python3
"""bench/discovery driver (issue 33, docs/discovery.md "Benchmark").

Starts N copies of lcmx_bench_discovery_peer (10 publishers at 1 Hz, 10 subscribers of another
process's topics) within --spread seconds and measures, per run:
  match     time from the last start until each process had all its subscriptions matched
            (p50/p99/max over the processes that matched; "matched" = how many did within --timeout)
  cpu       steady-state CPU of all peers (utime+stime from /proc/<pid>/stat) over the window
            between two snapshots, % of one core. A snapshot reads every pid's file at once and
            is time-stamped before and after: the window is between the snapshots' midpoints
            (cpu_window_s), cpu_snapshot_spread_ms the longest a snapshot took
  group     bytes on the host-local group over that window (lcm-logger's log, which records
            everything on the group, as a stock user's recorder would)
  LAN       (--hosts > 1) the bytes each emulated host sends on the vehicle LAN (veth counters),
            and the datagrams on the vehicle group heard on the emulated switch by listen.py,
            by sender and kind (classified by lcm fingerprint, lcmx_bench_fingerprints): from
            cold start to full match (lan_disc_bytes_to_match*) and per host in the steady state
            (lan_disc_Bps_per_host_max/_mean, _by_kind: {kind: {max, mean}} over hosts, over the
            listener's own window). "disc" is discovery proper; data markers (host_beacon_t
            KIND_MARK, marker_t) are data bookkeeping and are reported apart (lan_mark_*).
            (Before 2026-12-08 the lan_disc_* figures included the markers: old disc = disc + mark.)
            A listener that does not report within 5 s of SIGTERM is killed, and one whose socket
            dropped datagrams (SO_RXQ_OVFL) is incomplete: its figures are null (lan_listen says why).
  false expiry  every UNMATCHED line a peer printed for a publisher nobody killed (between the
            subscriber's start or its last REMATCHED of that topic and the line, no kill of the
            topic's publisher): false_expiry (whole run), false_expiry_by_phase ("launch": up to
            the end of the steady window, then "kill", "churn", "restart": from each one's start),
            false_expiry_launch (= by_phase["launch"], target 0), false_expiry_some (3 of them: who,
            which topic, when, how long until its REMATCHED)
  kill      (--kill; default on with --hosts > 1) after the steady window one peer whose topics
            have subscribers on its own host and on others (from the subscription map) is
            SIGKILLed; per subscriber of its topics, the time from the kill until it printed
            UNMATCHED for all of them (kill_local_ms, kill_remote_ms: p50, max, "k/m" unmatched
            within the wait; max null when one was not), next to the lease (LCMX_LEASE_MS, default
            1500) and the 100 ms target on its own host; kill_seen_by_poll: how many of those lines
            a peer's periodic check saw rather than one a match Event woke (late by up to
            --idle-poll-ms). It is then started again (kill_rematch_s: until every one of those
            subscribers printed REMATCHED)
            (The peers check their subscriptions every --poll-ms ms until MATCHED, then every
            --idle-poll-ms ms and at each publisher_(un)matched Event: peer.cpp says why.)
  churn     CPU (ms) of all the other peers while one peer is SIGKILLed and one started
  restart   (--host-restart, --hosts > 1) every peer of host 0 SIGKILLed, then all started again
            within --spread: CPU (ms) of each peer of the other hosts from the kill until the
            restarted ones matched again and 3 s more (idle subtracted; null when some did not
            match within --timeout), and the time from the last restart until every restarted peer
            matched (restart_rematched: how many did)
A restarted peer (kill, churn, restart) has the same subscriptions as the one it replaces
(before 2026-12-08 it drew new random cross-host ones). The driver and its listeners and logger
run at real-time priority (--rt-prio, SCHED_FIFO; 0: normal), so that a saturated machine does
not stretch their windows or starve their counts; the peers run at normal priority: they are
what is measured.
Each run prints one JSON line; then a SUMMARY line (appended to --json FILE) of the runs: the
configuration (hosts, n, topics, cross, runs, and whether kill, churn, host_restart ran), match
p50/p99/max over every process of every run, kill p50/max over every subscriber of every run,
false expiries summed, lan_listen_ok (runs whose listeners reported in full), and of the other
figures the median over the runs where it was measured (null: in none).
Everything runs inside network namespaces this script creates (lo only, or a bridge between
emulated hosts with --hosts): no packet leaves them. They are removed at exit, even on failure.
Usage (root): run.py --peer build/bench/discovery/lcmx_bench_discovery_peer --n 50 --runs 3
              run.py ... --hosts 8 --n 50 --cross 0.2    (8 emulated hosts x 50 processes)
              table.py FILE  (the issue's table from the --json summaries)
"""
import argparse, os, random, select, signal, statistics, subprocess, sys, tempfile, time, json, shutil

TICK = os.sysconf("SC_CLK_TCK")
HERE = os.path.dirname(os.path.abspath(__file__))


def sh(*cmd, check=True):
    return subprocess.run(cmd, check=check, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def rt(prio, cmd):
    """cmd run at SCHED_FIFO `prio` (chrt), or as is when prio is 0."""
    return (["chrt", "-f", str(prio)] + cmd) if prio > 0 else cmd


class Net:
    """hosts network namespaces; with more than one, a bridge namespace joins them by veths.
    An anchor process (sleep) in each host lets the driver read its eth0 counters from
    /proc/<anchor>/net/dev: no subprocess, which a saturated machine would starve."""

    def __init__(self, hosts, tag):
        self.tag = tag
        self.hosts = [f"ldb{tag}h{i}" for i in range(hosts)]
        self.sw = f"ldb{tag}sw" if hosts > 1 else None
        self.created = []
        self.anchors = []
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
                for h in self.hosts:
                    self.anchors.append(subprocess.Popen(["ip", "netns", "exec", h, "sleep", "infinity"],
                                                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                                         stderr=subprocess.DEVNULL))
                # `ip netns exec` enters the namespace, then execs sleep (same pid): wait for it
                deadline = time.monotonic() + 10
                for h, a in zip(self.hosts, self.anchors):
                    want = os.stat(f"/run/netns/{h}").st_ino
                    while os.stat(f"/proc/{a.pid}/ns/net").st_ino != want:
                        if time.monotonic() > deadline or a.poll() is not None:
                            raise RuntimeError(f"anchor of {h} did not enter it")
                        time.sleep(0.01)
            else:
                sh("ip", "-n", self.hosts[0], "route", "add", "224.0.0.0/4", "dev", "lo")
        except BaseException:  # a signal's SystemExit too (main)
            self.close()
            raise

    def host_of_addr(self, addr):
        """The host index of a vehicle LAN source address (10.77.0.<i+1>), or None."""
        if addr.startswith("10.77.0."):
            i = int(addr.rsplit(".", 1)[1]) - 1
            if 0 <= i < len(self.hosts):
                return i
        return None

    def tx_bytes(self, i):
        """Bytes host i sent on its eth0 so far (its veth counter)."""
        with open(f"/proc/{self.anchors[i].pid}/net/dev") as f:
            for line in f:
                name, _, rest = line.partition(":")
                if name.strip() == "eth0":
                    return int(rest.split()[8])
        raise RuntimeError(f"no eth0 in host {i}")

    def close(self):
        for a in self.anchors:
            a.kill()
            a.wait()
        self.anchors = []
        for h in self.created:
            # whatever this driver started in its namespaces and is still running (it started
            # every process there): killed by pid before the namespace goes
            out = subprocess.run(["ip", "netns", "pids", h], stdout=subprocess.PIPE, text=True).stdout
            for pid in out.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (OSError, ValueError):
                    pass
            sh("ip", "netns", "del", h, check=False)
        self.created = []


class Snap:
    """CPU ticks (utime + stime) of a set of pids, read as fast as possible: {pid: ticks} and
    the CLOCK_MONOTONIC time (s) of the reading's midpoint, and how long it took (spread, s).
    A pid whose file is gone (the process exited) is absent."""

    def __init__(self, pids):
        t0 = time.monotonic()
        self.ticks = {}
        for pid in pids:
            try:
                fd = os.open(f"/proc/{pid}/stat", os.O_RDONLY)
                try:
                    b = os.read(fd, 2048)
                finally:
                    os.close(fd)
                parts = b.rsplit(b")", 1)[1].split()
                self.ticks[pid] = int(parts[11]) + int(parts[12])
            except (OSError, IndexError, ValueError):
                pass
        t1 = time.monotonic()
        self.t, self.spread = (t0 + t1) / 2, t1 - t0


def delta_ticks(a, b):
    """Ticks between snapshots a and b over the pids in both, and how many pids were in a only."""
    both = [p for p in a.ticks if p in b.ticks]
    return sum(b.ticks[p] - a.ticks[p] for p in both), len(a.ticks) - len(both)


def pct(values, p):
    """The p-th percentile (nearest rank) of values; None when there are none."""
    if not values:
        return None
    v = sorted(values)
    k = min(len(v) - 1, max(0, int(round(p / 100.0 * len(v) + 0.5)) - 1))
    return v[k]


def rnd(x, d=3):
    return None if x is None else round(x, d)


def med(values, d=3):
    """Median of the values that were measured (not None); None when none was."""
    v = [x for x in values if x is not None]
    if not v:
        return None
    return round(statistics.median(v)) if d == 0 else round(statistics.median(v), d)


class Proc:
    """One peer process (an incarnation of index idx on host h) and what it printed."""

    def __init__(self, idx, h, popen, start_ns):
        self.idx, self.h, self.p, self.start_ns = idx, h, popen, start_ns
        self.ready_ns = self.ready_cpu_ms = self.matched_ns = None
        self.events = []  # (kind, ns, topic): UNMATCHED / REMATCHED, in the order printed
        self.how = {}     # event -> "event" or "poll": what the peer's check that saw it ran for
        self.buf = b""
        self.killed_ns = None

    @property
    def pid(self):
        return self.p.pid

    def alive(self):
        return self.killed_ns is None and self.p.poll() is None


class Lines:
    """Reads every peer's stdout as lines come (one poll over all pipes) into its Proc."""

    def __init__(self):
        self.poll = select.poll()
        self.by_fd = {}

    def add(self, proc):
        fd = proc.p.stdout.fileno()
        os.set_blocking(fd, False)
        self.by_fd[fd] = proc
        self.poll.register(fd, select.POLLIN)

    def pump(self, seconds, until=None):
        """Reads lines for `seconds` s, or until until() is true (checked after each batch)."""
        deadline = time.monotonic() + seconds
        while True:
            if until is not None and until():
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            for fd, _ in self.poll.poll(max(1, int(min(left, 0.5) * 1000))):
                self._read(fd)

    def _read(self, fd):
        proc = self.by_fd[fd]
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            return
        except OSError:
            chunk = b""
        if not chunk:  # EOF: the process is gone
            self.poll.unregister(fd)
            del self.by_fd[fd]
            return
        proc.buf += chunk
        *lines, proc.buf = proc.buf.split(b"\n")
        for line in lines:
            f = line.split()
            try:
                if f[0] == b"READY":
                    proc.ready_ns, proc.ready_cpu_ms = int(f[1]), int(f[2]) / 1000.0
                elif f[0] == b"MATCHED":
                    proc.matched_ns = proc.matched_ns or int(f[1])
                elif f[0] in (b"UNMATCHED", b"REMATCHED"):
                    proc.events.append((f[0].decode(), int(f[1]), f[2].decode()))
                    proc.how[(f[0].decode(), int(f[1]), f[2].decode())] = f[3].decode() if len(f) > 3 else "poll"
            except (IndexError, ValueError):
                pass


class Listener:
    """listen.py on the emulated switch: started at real-time priority; stop() returns its
    report, or None (with self.problem saying why) when it cannot be trusted."""

    def __init__(self, args, net, group, port, fingerprints, log):
        self.problem = None
        err = open(log, "ab")
        self.p = subprocess.Popen(["ip", "netns", "exec", net.sw] +
                                  rt(args.rt_prio, [sys.executable, os.path.join(HERE, "listen.py"), group, str(port),
                                                    "10.77.0.250", "3600", json.dumps(fingerprints)]),
                                  stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err)
        err.close()
        self.out = b""
        os.set_blocking(self.p.stdout.fileno(), False)

    def _read(self, seconds, until):
        deadline = time.monotonic() + seconds
        fd = self.p.stdout.fileno()
        while not until() and time.monotonic() < deadline:
            r, _, _ = select.select([fd], [], [], max(0.0, min(0.2, deadline - time.monotonic())))
            if r:
                try:
                    chunk = os.read(fd, 1 << 20)
                except BlockingIOError:
                    continue
                if not chunk:
                    return True  # EOF
                self.out += chunk
        return until()

    def wait_listening(self, seconds=5.0):
        """Waits (bounded) until it has joined the group; False if it did not in time."""
        return self._read(seconds, lambda: b"LISTENING" in self.out)

    def stop(self, seconds=5.0):
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
        reported = self._read(seconds, lambda: self.out.endswith(b"}\n"))
        try:
            self.p.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            self.p.kill()
            self.p.wait()
        if not reported:
            self.problem = f"no report within {seconds:g} s of SIGTERM (exit {self.p.returncode})"
            return None
        try:
            rep = json.loads(self.out.strip().splitlines()[-1])
        except ValueError:
            self.problem = "its report did not parse"
            return None
        if rep.get("dropped"):
            self.problem = f"its socket dropped {rep['dropped']} datagrams"
            return None
        return rep


_stopping = False


def on_signal(sig, _frame):
    """SIGTERM, SIGHUP (and SIGINT unless ignored): SystemExit once, so that every `finally`
    stops the processes and removes the namespaces; later ones are ignored while it does."""
    global _stopping
    if not _stopping:
        _stopping = True
        raise SystemExit(128 + sig)


def main():
    for sig in (signal.SIGTERM, signal.SIGHUP) + ((signal.SIGINT,) if signal.getsignal(signal.SIGINT) is signal.default_int_handler else ()):
        signal.signal(sig, on_signal)
    ap = argparse.ArgumentParser()
    ap.add_argument("--peer", required=True)
    ap.add_argument("--fingerprints", default="", help="lcmx_bench_fingerprints (default: beside --peer)")
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
    ap.add_argument("--kill", action=argparse.BooleanOptionalAction, default=None,
                    help="SIGKILL one peer after the steady window and time its unmatching (default: on with --hosts > 1)")
    ap.add_argument("--host-restart", action="store_true", help="kill and restart every peer of host 0 (--hosts > 1)")
    ap.add_argument("--poll-ms", type=int, default=10, help="the peers' subscription polling period until MATCHED")
    ap.add_argument("--idle-poll-ms", type=int, default=200, help="... after MATCHED (besides their match events)")
    ap.add_argument("--events", action=argparse.BooleanOptionalAction, default=True,
                    help="the peers check their subscriptions at each publisher_(un)matched Event too")
    ap.add_argument("--rt-prio", type=int, default=10, help="SCHED_FIFO priority of the driver, listeners, logger (0: none)")
    ap.add_argument("--logger", default=shutil.which("lcm-logger"))
    ap.add_argument("--label", default="")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    if args.kill is None:
        args.kill = args.hosts > 1
    args.lease_ms = int(os.environ.get("LCMX_LEASE_MS", "1500"))
    args.fp = None
    if args.hosts > 1:
        tool = args.fingerprints or os.path.join(os.path.dirname(os.path.abspath(args.peer)), "lcmx_bench_fingerprints")
        if not os.access(tool, os.X_OK):
            sys.exit(f"run.py: {tool} not found (cmake --build build --target lcmx_bench_fingerprints): "
                     "the LAN datagrams could not be classified")
        args.fp = json.loads(sh(tool).stdout)
    args.rt = None
    if args.rt_prio > 0:
        try:
            # the children (peers, ip) start at normal priority; listeners and logger ask (chrt)
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(args.rt_prio))
            args.rt = args.rt_prio
        except OSError as e:
            print(f"run.py: no real-time priority ({e}): the driver's windows may stretch", file=sys.stderr)
            args.rt_prio = 0
    results = []
    for run in range(args.runs):
        results.append(one_run(args, run))
        print(json.dumps({k: v for k, v in results[-1].items() if k != "match_s"}), flush=True)
    summary = summarize(args, results)
    print("SUMMARY " + json.dumps(summary), flush=True)
    if args.json:
        with open(args.json, "a") as f:
            f.write(json.dumps(summary) + "\n")


def summarize(args, results):
    match = [x for r in results for x in r["match_s"]]
    multi = args.hosts > 1

    def m(key, d=3):
        return med([r.get(key) for r in results], d) if multi else None

    def kill_stats(key):
        vals = [x for r in results for x in r.get(key) or []]  # None: not unmatched within the wait
        got = sorted(x for x in vals if x is not None)
        if not vals:
            return None, None, None
        p50 = pct([x if x is not None else float("inf") for x in vals], 50)
        return (rnd(p50, 1) if p50 != float("inf") else None,
                rnd(max(got), 1) if len(got) == len(vals) else None, f"{len(got)}/{len(vals)}")

    kinds = sorted({k for r in results for k in (r.get("lan_disc_Bps_per_host_by_kind") or {})})

    def by_kind(r, k, s):
        """A run's per-host B/s of kind k (s: "max" or "mean"): 0 when measured but not heard."""
        d = r.get("lan_disc_Bps_per_host_by_kind")
        return None if d is None else d.get(k, {}).get(s, 0.0)
    lp50, lmax, lk = kill_stats("kill_local_ms")
    rp50, rmax, rk = kill_stats("kill_remote_ms")
    return {
        "label": args.label, "hosts": args.hosts, "n": args.n, "topics": args.topics, "cross": args.cross,
        "runs": args.runs, "kill": args.kill, "churn": args.churn, "host_restart": args.host_restart and multi,
        "matched": f'{sum(r["matched"] for r in results)}/{sum(r["total"] for r in results)}',
        "match_p50_s": rnd(pct(match, 50)), "match_p99_s": rnd(pct(match, 99)),
        "match_max_s": rnd(max(match) if match else None),
        "cpu_pct_all": med([r["cpu_pct"] for r in results], 1),
        "cpu_pct_per_process": med([None if r["cpu_pct"] is None else r["cpu_pct"] / (args.n * args.hosts) for r in results]),
        "cpu_window_s": med([r["cpu_window_s"] for r in results]),
        "cpu_snapshot_spread_ms_max": max(r["cpu_snapshot_spread_ms"] for r in results),
        "group_bytes_per_s": med([r["group_Bps"] for r in results], 0),
        "lan_tx_bytes_per_s_per_host": m("lan_Bps_per_host", 0),
        "lan_bytes_to_match": m("lan_bytes_to_match", 0),
        "lan_disc_bytes_to_match": m("lan_disc_bytes_to_match", 0),
        "lan_mark_bytes_to_match": m("lan_mark_bytes_to_match", 0),
        "lan_disc_Bps_per_host_max": m("lan_disc_Bps_per_host_max", 0),
        "lan_disc_Bps_per_host_mean": m("lan_disc_Bps_per_host_mean", 0),
        "lan_disc_Bps_per_host_by_kind": {k: {s: med([by_kind(r, k, s) for r in results], 1) for s in ("max", "mean")}
                                          for k in kinds} if multi else None,
        "lan_mark_Bps_per_host_max": m("lan_mark_Bps_per_host_max", 0),
        "lan_mark_Bps_per_host_mean": m("lan_mark_Bps_per_host_mean", 0),
        "lan_listen_ok": (f'{sum(1 for r in results if r["lan_listen"]["cold"] is None)}/{len(results)} cold, '
                          f'{sum(1 for r in results if r["lan_listen"]["steady"] is None)}/{len(results)} steady')
                         if multi else None,
        "false_expiry": sum(r["false_expiry"] for r in results),
        "false_expiry_launch": sum(r["false_expiry_launch"] for r in results),
        "false_expiry_by_phase": {k: sum(r["false_expiry_by_phase"].get(k, 0) for r in results)
                                  for k in results[0]["false_expiry_by_phase"]},
        "lease_ms": args.lease_ms, "kill_local_target_ms": 100,  # targets: other hosts within the lease, its own 100 ms
        "kill_local_ms_p50": lp50, "kill_local_ms_max": lmax, "kill_local_unmatched": lk,
        "kill_remote_ms_p50": rp50, "kill_remote_ms_max": rmax, "kill_remote_unmatched": rk,
        "kill_rematch_s": [r.get("kill_rematch_s") for r in results] if args.kill else None,
        "churn_ms_per_other": results[0].get("churn_ms_per_other"),  # the first run's (null: not run or unmeasured)
        "restart_ms_per_other": [r.get("restart_ms_per_other") for r in results] if args.host_restart else None,
        "restart_rematch_s": [r.get("restart_rematch_s") for r in results] if args.host_restart else None,
        "last_ready_s": med([r["last_ready_s"] for r in results]),
        "kill_seen_by_poll": sum(r.get("kill_seen_by_poll") or 0 for r in results) if args.kill else None,
        "poll_ms": args.poll_ms, "idle_poll_ms": args.idle_poll_ms, "events": args.events, "driver_rt_prio": args.rt,
    }


def lan_figures(rep, net, hosts):
    """Per-host discovery figures of a listener report (None: unmeasured)."""
    if rep is None:
        return None
    w = (rep["t1_ns"] - rep["t0_ns"]) / 1e9
    per = [{"disc": 0, "mark": 0, "kinds": {}} for _ in range(hosts)]
    for src, v in rep["sources"].items():
        h = net.host_of_addr(src)
        if h is None:
            continue
        per[h]["disc"] += v["disc"]
        per[h]["mark"] += v["mark"]
        for k, b in v["kinds"].items():
            per[h]["kinds"][k] = per[h]["kinds"].get(k, 0) + b
    kinds = sorted({k for p in per for k in p["kinds"]} - {"mark"})  # markers: apart (lan_mark_*)
    return {"window_s": w, "per": per, "kinds": kinds,
            "total": {k: sum(p["kinds"].get(k, 0) for p in per) for k in kinds}}


def false_expiries(procs, kills, phases):
    """UNMATCHED lines not explained by a kill: (count, {phase: count}, a few of them). A line is
    explained when the topic's publisher (index) was killed after the subscriber's previous event
    on that topic (its start, or its REMATCHED) and not after the line. phases: [(name, start ns)]
    in time order; a line counts in the last phase begun before it."""
    n = 0
    by_phase = {name: 0 for name, _ in phases}
    some = []
    for pr in procs:
        last = {}
        for kind, ns, topic in pr.events:
            prev = last.get(topic, pr.start_ns)
            last[topic] = ns
            if kind != "UNMATCHED":
                continue
            pub = int(topic.split("_")[1])
            if any(prev < tk <= ns for tk in kills.get(pub, [])):
                continue
            n += 1
            phase = [name for name, t in phases if t <= ns][-1:] or [phases[0][0]]
            by_phase[phase[0]] += 1
            if len(some) < 3:
                back = [t for k, t, tp in pr.events if k == "REMATCHED" and tp == topic and t > ns]
                some.append({"subscriber": pr.idx, "topic": topic, "phase": phase[0],
                             "at_s_after_start": round((ns - pr.start_ns) / 1e9, 3),
                             "rematched_after_ms": round((back[0] - ns) / 1e6, 1) if back else None})
    return n, by_phase, some


def one_run(args, run):
    tag = f"{os.getpid() % 10000}r{run}"
    net = None
    procs = []   # every incarnation started, in order
    live = {}    # index -> its current Proc
    aux = []     # logger and listeners
    lines = Lines()
    tmp = tempfile.mkdtemp(prefix="lcmx_bench_disc_")
    try:
        net = Net(args.hosts, tag)
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
        logf = os.path.join(tmp, "group.lcmlog")
        if args.logger:
            lenv = dict(env)
            lenv["LCM_DEFAULT_URL"] = local
            aux.append(subprocess.Popen(["ip", "netns", "exec", net.hosts[0]] + rt(args.rt_prio, [args.logger, "-q", "-f", logf]),
                                        env=lenv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        vg, vp = f"239.255.{salt}.68", 18000 + salt
        listen_log = os.path.join(tmp, "listen.err")

        def listener():
            if args.hosts < 2:
                return None
            lst = Listener(args, net, vg, vp, args.fp, listen_log)
            aux.append(lst.p)
            lst.wait_listening()
            return lst

        total = args.n * args.hosts
        rng = random.Random(run)
        # the subscription map: index -> [(publisher index, topic k)], drawn once per run in
        # launch order (the draws of earlier versions of this driver); a restart keeps it
        subs = {}
        for h in range(args.hosts):
            for i in range(args.n):
                s = []
                for k in range(args.topics):
                    if args.hosts > 1 and rng.random() < args.cross:
                        oh = (h + 1 + rng.randrange(args.hosts - 1)) % args.hosts
                        s.append((oh * args.n + rng.randrange(args.n), k))
                    else:
                        s.append((h * args.n + (i + 1) % args.n, k))
                subs[h * args.n + i] = s
        host_of = {idx: idx // args.n for idx in subs}
        kills = {}  # publisher index -> [kill ns]

        def start(h, i):
            idx = h * args.n + i
            sub_args = [a for pub, k in subs[idx] for a in ("--sub", f"{pub}:{k}")]
            p = subprocess.Popen(["ip", "netns", "exec", net.hosts[h], args.peer, "--index", str(idx), "--n", str(total),
                                  "--topics", str(args.topics), "--prefix", f"T{tag}", "--poll-ms", str(args.poll_ms),
                                  "--idle-poll-ms", str(args.idle_poll_ms), "--events", str(int(args.events))] + sub_args,
                                 env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
            pr = Proc(idx, h, p, time.monotonic_ns())
            procs.append(pr)
            live[idx] = pr
            lines.add(pr)
            return pr

        def launch(pairs):
            """Starts a peer per (host, index), evenly over --spread s; returns them."""
            out, t0 = [], time.monotonic()
            for k, (h, i) in enumerate(pairs):
                d = t0 + args.spread * k / max(1, len(pairs) - 1) - time.monotonic()
                if d > 0:
                    lines.pump(d)
                out.append(start(h, i))
            return out

        def kill(pr):
            pr.killed_ns = time.monotonic_ns()
            kills.setdefault(pr.idx, []).append(pr.killed_ns)
            pr.p.send_signal(signal.SIGKILL)
            return pr.killed_ns

        def cpu_ms_beyond_idle(s0, s1, cpu_pct, n_steady):
            """CPU (ms) each process of s0 spent between the snapshots beyond its idle share
            (the steady state's `cpu_pct` of n_steady processes over the same time)."""
            d, _ = delta_ticks(s0, s1)
            n = max(1, len(s0.ticks))
            idle = (cpu_pct / 100.0) * (s1.t - s0.t) * TICK * n / n_steady
            return round(max(0.0, d - idle) / TICK * 1000 / n, 3)

        cold = listener()
        lan0 = [net.tx_bytes(h) for h in range(args.hosts)] if args.hosts > 1 else []
        order = [(h, i) for h in range(args.hosts) for i in range(args.n)]
        first = launch(order)
        last_start = max(pr.start_ns for pr in first)
        lines.pump(args.timeout, until=lambda: all(pr.matched_ns for pr in first))
        lan_to_match = sum(net.tx_bytes(h) - lan0[h] for h in range(args.hosts)) if args.hosts > 1 else None
        cold_rep = cold.stop() if cold else None
        if cold_rep is not None and cold_rep["t0_ns"] > first[0].start_ns:
            cold.problem, cold_rep = "it joined the group after the first peer started", None
        match_s = [max(0, pr.matched_ns - last_start) / 1e9 for pr in first if pr.matched_ns]
        ready = [pr.ready_ns for pr in first if pr.ready_ns]
        # when the last process had its endpoints (start-up: exec, runtime, shm segments)
        ready_s = (max(ready) - last_start) / 1e9 if ready else None
        lines.pump(args.settle)
        steady = listener()
        pids = [pr.pid for pr in first]  # the peer is the child of `ip netns exec`, which execs: same pid
        g0 = os.path.getsize(logf) if os.path.exists(logf) else 0
        l0 = [net.tx_bytes(h) for h in range(args.hosts)] if args.hosts > 1 else []
        s0 = Snap(pids)
        lines.pump(args.window)
        s1 = Snap(pids)
        g1 = os.path.getsize(logf) if os.path.exists(logf) else 0
        l1 = [net.tx_bytes(h) for h in range(args.hosts)] if args.hosts > 1 else []
        phases = [("launch", 0)]  # the launch, the settle time and the steady window
        steady_rep = steady.stop() if steady else None
        w = s1.t - s0.t
        dt, gone = delta_ticks(s0, s1)
        res = {"run": run, "total": len(first), "matched": len(match_s), "match_s": match_s, "last_ready_s": rnd(ready_s),
               "startup_cpu_ms_p50": pct([pr.ready_cpu_ms for pr in first if pr.ready_cpu_ms is not None], 50),
               "startup_cpu_ms_max": max((pr.ready_cpu_ms for pr in first if pr.ready_cpu_ms is not None), default=None),
               # a process that exited during the window takes its ticks with it: unmeasured
               "cpu_pct": 100.0 * dt / TICK / w if not gone else None, "cpu_window_s": round(w, 3),
               "cpu_snapshot_spread_ms": round(1000 * max(s0.spread, s1.spread), 2), "cpu_pids_gone": gone,
               "group_Bps": (g1 - g0) / w if args.logger else None}
        if args.hosts > 1:
            cold_f = lan_figures(cold_rep, net, args.hosts)
            st_f = lan_figures(steady_rep, net, args.hosts)
            res.update({
                "lan_Bps_per_host": (sum(l1) - sum(l0)) / w / args.hosts,
                "lan_bytes_to_match": lan_to_match,
                # discovery datagrams (LCMX_BEACON on the vehicle group, markers apart), heard on the switch
                "lan_disc_bytes_to_match": sum(p["disc"] for p in cold_f["per"]) if cold_f else None,
                "lan_mark_bytes_to_match": sum(p["mark"] for p in cold_f["per"]) if cold_f else None,
                "lan_disc_bytes_to_match_by_kind": cold_f["total"] if cold_f else None,
                "lan_disc_datagrams_to_match": sum(v["disc_datagrams"] for v in cold_rep["sources"].values()) if cold_rep else None,
                "lan_disc_Bps_per_host_max": max(p["disc"] for p in st_f["per"]) / st_f["window_s"] if st_f else None,
                "lan_disc_Bps_per_host_mean": sum(p["disc"] for p in st_f["per"]) / args.hosts / st_f["window_s"] if st_f else None,
                "lan_disc_Bps_per_host_by_kind": {k: {"max": round(max(p["kinds"].get(k, 0) for p in st_f["per"]) / st_f["window_s"], 1),
                                                      "mean": round(st_f["total"][k] / args.hosts / st_f["window_s"], 1)}
                                                  for k in st_f["kinds"]} if st_f else None,
                "lan_mark_Bps_per_host_max": max(p["mark"] for p in st_f["per"]) / st_f["window_s"] if st_f else None,
                "lan_mark_Bps_per_host_mean": sum(p["mark"] for p in st_f["per"]) / args.hosts / st_f["window_s"] if st_f else None,
                "lan_disc_Bps_steady_by_kind": {k: round(v / st_f["window_s"], 1) for k, v in st_f["total"].items()} if st_f else None,
                "lan_data_Bps_total": sum(v["data"] for v in steady_rep["sources"].values()) / st_f["window_s"] if st_f else None,
                "lan_listen": {"cold": cold.problem if cold_rep is None else None,
                               "steady": steady.problem if steady_rep is None else None,
                               "steady_window_s": round(st_f["window_s"], 3) if st_f else None},
            })
        if args.kill and not any(subs.values()):
            res["kill_victim"] = None  # no process has a subscriber: nothing to time
        elif args.kill:
            # the victim: the process whose topics have subscribers on its own host and on
            # others (most of the fewer side, then most in all); on one host, the most subscribers
            subscribers = {}  # publisher index -> {subscriber index: {topics}}
            for s_idx, lst in subs.items():
                for pub, k in lst:
                    subscribers.setdefault(pub, {}).setdefault(s_idx, set()).add(f"T{tag}_{pub}_{k}")

            def score(pub):
                ss = subscribers.get(pub, {})
                loc = sum(1 for s in ss if host_of[s] == host_of[pub])
                return (min(loc, len(ss) - loc) if args.hosts > 1 else loc, len(ss), -pub)

            phases.append(("kill", time.monotonic_ns()))
            vidx = max(subscribers, key=score)
            victim = live[vidx]
            watch = {s: topics for s, topics in subscribers[vidx].items() if s != vidx and live[s].alive()}
            tk = kill(victim)
            victim.p.wait()
            wait_s = 2 * args.lease_ms / 1000 + 3

            def unmatched_lines(s, topics):
                """{topic: the first UNMATCHED event since tk} of subscriber s."""
                t = {}
                for ev in live[s].events:
                    if ev[0] == "UNMATCHED" and ev[2] in topics and ev[1] >= tk:
                        t.setdefault(ev[2], ev)
                return t

            def unmatched_at(s, topics):
                """ns when subscriber s had printed UNMATCHED for every one of topics since tk, or None."""
                t = unmatched_lines(s, topics)
                return max(ev[1] for ev in t.values()) if len(t) == len(topics) else None

            lines.pump(wait_s, until=lambda: all(unmatched_at(s, t) is not None for s, t in watch.items()))
            loc, rem = [], []
            for s, t in watch.items():
                at = unmatched_at(s, t)
                (loc if host_of[s] == host_of[vidx] else rem).append(None if at is None else round((at - tk) / 1e6, 2))
            res.update({"kill_victim": vidx, "kill_local_ms": loc, "kill_remote_ms": rem,
                        "kill_local_ms_max": (round(max(loc), 1) if loc and None not in loc else None),
                        "kill_remote_ms_max": (round(max(rem), 1) if rem and None not in rem else None),
                        "kill_unmatched": f"{sum(x is not None for x in loc + rem)}/{len(loc) + len(rem)} within {wait_s:g} s",
                        # lines of a check that ran for its poll period, not for a match Event: late by up to it
                        "kill_seen_by_poll": sum(live[s].how[ev] == "poll" for s, t in watch.items()
                                                 for ev in unmatched_lines(s, t).values())})
            # started again: the following phases begin from every pair matched
            h, i = order[vidx]
            again = start(h, i)

            def rematched():
                for s, topics in watch.items():
                    got = {topic for kind, ns, topic in live[s].events if kind == "REMATCHED" and ns >= again.start_ns}
                    if not topics <= got:
                        return False
                return again.matched_ns is not None

            ok = lines.pump(args.timeout, until=rematched)
            res["kill_rematch_s"] = (round((max([ns for s in watch for kind, ns, topic in live[s].events
                                                 if kind == "REMATCHED" and ns >= again.start_ns] + [again.matched_ns])
                                            - again.start_ns) / 1e9, 3) if ok else None)
        if args.churn:
            phases.append(("churn", time.monotonic_ns()))
            victim = live[len(order) // 2]  # index k is order[k]
            others = [pr.pid for pr in live.values() if pr is not victim and pr.alive()]
            c0 = Snap(others)
            kill(victim)
            victim.p.wait()
            lines.pump(2.0)
            h, i = order[len(order) // 2]
            start(h, i)
            lines.pump(3.0)
            c1 = Snap(others)
            # the same window without churn, from the steady state above, is subtracted
            res["churn_ms_per_other"] = (cpu_ms_beyond_idle(c0, c1, res["cpu_pct"], len(pids))
                                         if res["cpu_pct"] is not None else None)
        if args.host_restart and args.hosts > 1:
            # The whole of host 0 restarts (its software stack; /dev/shm stays, as after a
            # restart of the stack, not a reboot): every peer killed, then all started again.
            phases.append(("restart", time.monotonic_ns()))
            victims = [pr for pr in live.values() if pr.h == 0 and pr.alive()]
            others = [pr.pid for pr in live.values() if pr.h != 0 and pr.alive()]
            c0 = Snap(others)
            for pr in victims:
                kill(pr)
            for pr in victims:
                pr.p.wait()
            fresh = launch([order[pr.idx] for pr in victims])
            last = time.monotonic_ns()
            lines.pump(args.timeout, until=lambda: all(pr.matched_ns for pr in fresh))
            lines.pump(3.0)
            c1 = Snap(others)
            done = [pr.matched_ns for pr in fresh if pr.matched_ns]
            # "until the restarted ones matched again": undefined when some did not (null)
            res["restart_ms_per_other"] = (cpu_ms_beyond_idle(c0, c1, res["cpu_pct"], len(order))
                                           if res["cpu_pct"] is not None and len(done) == len(fresh) else None)
            res["restart_rematch_s"] = (round(max(0, max(done) - last) / 1e9, 3) if len(done) == len(fresh) else None)
            res["restart_rematched"] = f"{len(done)}/{len(fresh)}"
        lines.pump(0.1)  # the last lines
        n, by_phase, some = false_expiries(procs, kills, phases)
        res.update({"false_expiry": n, "false_expiry_launch": by_phase["launch"], "false_expiry_by_phase": by_phase,
                    "false_expiry_some": some})
        return res
    finally:
        for pr in procs:
            try:
                pr.p.stdin.close()
            except Exception:
                pass
        for pr in procs:
            try:
                pr.p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pr.p.kill()
                pr.p.wait()
        for p in aux:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        if net is not None:
            net.close()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
