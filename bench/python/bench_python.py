#!/usr/bin/python3
"""One-way latency of lcmx from Python (issue 14's benchmark), against C++ in the same run.

    bench/python/bench_python.py [--build build] [--sizes 1K,6M] [--messages N] [--rounds 3]
                                 [--pin none|same|split] [--methods ...] [--markdown FILE]

Methods (publisher -> subscriber, two processes on this host, shared memory):
  cpp-shm    C++ Publisher<bench_t> -> C++ Subscriber<bench_t>      (lcmx_bench_latency's roles)
  cpp-loan   C++ RawPublisher::loan, 16-byte header only -> C++ RawSubscriber (zero-copy both ends)
  py-py      Python advertise(bench_t).publish(msg) -> Python subscribe(bench_t) (encode/decode)
  py-cpp     Python advertise(bench_t).publish(msg) -> C++ Subscriber<bench_t>
  py-py-raw  Python advertise_raw().publish(bytearray) (one copy into the slot) -> Python
             subscribe_raw: memoryview of the slot, header read in place (no copy)
  py-cpp-raw Python advertise_raw().publish(bytearray) -> C++ RawSubscriber (header read in place)
  py-py-loan Python pub.loan(size), 16-byte header only written (as cpp-loan) -> Python raw
  py-cpp-loan  the same -> C++ RawSubscriber
Each is a ping-pong (next message after the subscriber's ack on a pipe, not timed), as
bench/latency (bench/README.md): the publisher stamps CLOCK_MONOTONIC just before it encodes or
copies, the subscriber reads it once it has the message (decoded for typed, the view for raw).
The C++ roles are lcmx_bench_latency's hidden --role children (same pipe protocol: report fd 3,
acks fd 4, end fd 5); the Python roles are this script's --role. Prints a Markdown table with
p50/p99 and the ratios to C++ of the same run, then issue 14's targets. Every method runs
--rounds times in rotated order, pooled. Needs no root. Exit 1 if a method failed.
"""
import argparse
import os
import select
import struct
import subprocess
import sys
import time

REPORT_FD, ACK_FD, CTL_FD = 3, 4, 5
MATCHED = -(1 << 63)
HERE = os.path.dirname(os.path.abspath(__file__))

METHODS = {  # name: (publisher role, subscriber role); lcmx-* roles are C++
    "cpp-shm": ("lcmx-shm-pub", "lcmx-shm-sub"),
    "cpp-loan": ("lcmx-loan-pub", "lcmx-loan-sub"),
    "py-py": ("py-pub", "py-sub"),
    "py-cpp": ("py-pub", "lcmx-shm-sub"),
    "py-py-raw": ("py-raw-pub", "py-raw-sub"),
    "py-cpp-raw": ("py-raw-pub", "lcmx-loan-sub"),
    "py-py-loan": ("py-loan-pub", "py-raw-sub"),
    "py-cpp-loan": ("py-loan-pub", "lcmx-loan-sub"),
}


def parse_size(text):
    t = text.strip().upper().rstrip("B")
    mult = {"K": 1024, "M": 1024 * 1024}.get(t[-1:], 1)
    return int(t[:-1] if mult > 1 else t) * mult


def size_label(n):
    return "%d MB" % (n >> 20) if n >= 1 << 20 else "%d KB" % (n >> 10) if n >= 1024 else "%d B" % n


# ------------------------------------------------------------------ Python roles (children)

def report(line):
    os.write(REPORT_FD, (line + "\n").encode())


def channel(name, what):
    return "LCMXBENCH_%s_%s" % (name, what)


def wait_fd(fd, timeout_s):
    return bool(select.select([fd], [], [], max(0.0, timeout_s))[0])


def wait_ack(seq, timeout_s):
    deadline = time.monotonic() + timeout_s
    while wait_fd(ACK_FD, deadline - time.monotonic()):
        data = os.read(ACK_FD, 8)
        if len(data) < 8:
            return False  # EOF
        if struct.unpack("=q", data)[0] == seq:
            return True
    return False


def run_py_sub(args, plan, raw):
    import lcmx
    from lcmx_examples import bench_t
    lat = {size: [] for size, _, _ in plan}
    now = time.monotonic_ns  # CLOCK_MONOTONIC, as the C++ roles' now_ns()
    ack = ACK_FD

    def record(size, seq, ns):
        if seq & 1 and size in lat:
            lat[size].append(ns)
        os.write(ack, struct.pack("=q", seq))

    with lcmx.Runtime(discovery_url=args.url) as rt:
        node = rt.create_node("bench_sub")
        if raw:
            def cb(view):
                t = now()
                seq, send_ns = struct.unpack_from("=qq", view, 0)  # in the slot: no copy
                record(len(view), seq, t - send_ns)
            sub = node.subscribe_raw(channel(args.name, "LOAN"), cb)
        else:
            def cb(m):
                record(m.size, m.seq, now() - m.send_ns)
            sub = node.subscribe(channel(args.name, "SHM"), bench_t, cb)
        report("ready")
        if not sub.wait_for_publishers(1, 15):
            report("error subscriber: wait_for_publishers(1, 15 s) timed out")
            return 1
        report("note %s: path at match: %s" % (args.role, ",".join(
            p["path"] for p in sub.stats()["publishers"])))
        os.write(ack, struct.pack("=q", MATCHED))
        wait_fd(CTL_FD, 600)
        sub.close()
    for size, _, _ in plan:
        report("lat %d %d %s" % (size, len(lat[size]), " ".join(map(str, lat[size]))))
    report("done")
    return 0


def run_py_pub(args, plan, raw, loan):
    import lcmx
    from lcmx_examples import bench_t
    ok = False
    try:
        with lcmx.Runtime(discovery_url=args.url) as rt:
            node = rt.create_node("bench_pub")
            biggest = max(size for size, _, _ in plan) + 4096
            if raw:
                pub = node.advertise_raw(channel(args.name, "LOAN"), max_message_size=max(biggest, 64 << 20))
            else:
                pub = node.advertise(channel(args.name, "SHM"), bench_t, max_message_size=max(biggest, 64 << 20))
            if not pub.wait_for_subscribers(1, 15) or not wait_ack(MATCHED, 15):
                report("error publisher: no subscriber matched within 15 s")
                return 1
            now = time.monotonic_ns
            k = 0
            timeout = args.timeout_ms / 1000.0
            for size, warmup, messages in plan:
                payload = bytes((i * 31) & 0xFF for i in range(256)) * (size // 256 + 1)
                if raw:
                    buf = bytearray(payload[:size])
                else:
                    msg = bench_t()
                    msg.size = size
                    msg.data = payload[:size]
                lost = 0
                for i in range(warmup + messages):
                    seq = (k << 1) | (1 if i >= warmup else 0)
                    k += 1
                    if loan:  # as cpp-loan: stamp, loan, write the header only, publish
                        t = now()
                        with pub.loan(size) as slot:
                            struct.pack_into("=qq", slot, 0, seq, t)
                    elif raw:
                        struct.pack_into("=qq", buf, 0, seq, now())
                        pub.publish(buf)
                    else:
                        msg.seq = seq
                        msg.send_ns = now()
                        pub.publish(msg)
                    if not wait_ack(seq, timeout):
                        lost += 1
                report("sent %d %d %d" % (size, messages, lost))
            ok = True
    finally:
        os.write(CTL_FD, b"E")
        report("done")
    return 0 if ok else 1


# ------------------------------------------------------------------ orchestrator

def spawn(argv, fds, cpu):
    """argv with fds[i] as fd 3 + i (posix_spawn's dup2 clears close-on-exec there)."""
    if cpu >= 0:
        argv = ["taskset", "-c", str(cpu)] + argv
    actions = [(os.POSIX_SPAWN_DUP2, fd, REPORT_FD + i) for i, fd in enumerate(fds)]
    exe = argv[0] if "/" in argv[0] else subprocess.check_output(["which", argv[0]], text=True).strip()
    return os.posix_spawn(exe, argv, os.environ, file_actions=actions)


class Reader:
    def __init__(self, fd):
        self.fd, self.buf, self.lines, self.eof = fd, b"", [], False

    def pump(self):
        data = os.read(self.fd, 1 << 20)
        if not data:
            self.eof = True
        self.buf += data
        *done, self.buf = self.buf.split(b"\n")
        self.lines += [d.decode() for d in done]

    def has(self, prefix):
        return any(l.startswith(prefix) for l in self.lines)


def pump_until(readers, until, timeout_s):
    deadline = time.monotonic() + timeout_s
    while not until():
        live = [r for r in readers if not r.eof]
        if not live:
            return until()
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        for fd in select.select([r.fd for r in live], [], [], left)[0]:
            next(r for r in live if r.fd == fd).pump()
    return True


def role_argv(args, role, plan_text, name):
    if role.startswith("py-"):
        base = [sys.executable, os.path.abspath(__file__), "--build", args.build]
    else:
        base = [args.bench_exe]
    return base + ["--role", role, "--plan", plan_text, "--name", name, "--url", args.url,
                   "--timeout-ms", str(args.timeout_ms)]


def run_method(args, method, plan, pub_cpu, sub_cpu):
    """Latencies {size: [ns]} and notes, or raises RuntimeError with the children's errors."""
    pub_role, sub_role = METHODS[method]
    name = "py%d_%s" % (os.getpid(), method.replace("-", ""))
    plan_text = ",".join("%d:%d:%d" % p for p in plan)
    rep_sub, rep_pub, ack, ctl = os.pipe(), os.pipe(), os.pipe(), os.pipe()
    pids = []
    try:
        pids.append(spawn(role_argv(args, sub_role, plan_text, name), [rep_sub[1], ack[1], ctl[0]], sub_cpu))
        sub = Reader(rep_sub[0])
        os.close(rep_sub[1])
        if not pump_until([sub], lambda: sub.has("ready") or sub.has("error"), 30) or sub.has("error"):
            raise RuntimeError("subscriber not ready: %s" % sub.lines)
        pids.append(spawn(role_argv(args, pub_role, plan_text, name), [rep_pub[1], ack[0], ctl[1]], pub_cpu))
        pub = Reader(rep_pub[0])
        for fd in (rep_pub[1], ack[0], ack[1], ctl[0], ctl[1]):
            os.close(fd)
        deadline = 60 + sum(w + m for _, w, m in plan) * (args.timeout_ms / 1000.0 + 0.05)
        if not pump_until([sub, pub], lambda: sub.eof and pub.eof, deadline):
            for pid in pids:
                os.kill(pid, 9)
            raise RuntimeError("no end within %.0f s: %s" % (deadline, (sub.lines + pub.lines)[-5:]))
        errors = [l for l in sub.lines + pub.lines if l.startswith("error")]
        lat = {}
        for l in sub.lines:
            if l.startswith("lat "):
                f = l.split()
                lat[int(f[1])] = sorted(int(v) for v in f[3:])
        lost = {}
        for l in pub.lines:
            if l.startswith("sent "):
                f = l.split()
                lost[int(f[1])] = int(f[3])
        notes = [l[5:] for l in sub.lines + pub.lines if l.startswith("note ")]
        if errors or not lat:
            raise RuntimeError("; ".join(errors) or "no latencies reported")
        return lat, lost, notes
    finally:
        for pid in pids:  # they closed their reports (ended), or were killed above
            if sys.exc_info()[0] is not None and not isinstance(sys.exc_info()[1], RuntimeError):
                os.kill(pid, 9)  # Ctrl-C, or a fault of ours
            os.waitpid(pid, 0)
        for fd in (rep_sub[0], rep_pub[0]):
            try:
                os.close(fd)
            except OSError:
                pass


def pct(sorted_ns, p):
    if not sorted_ns:
        return None
    rank = max(1, -(-p * len(sorted_ns) // 100))  # nearest rank
    return sorted_ns[rank - 1] / 1000.0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--build", default=os.path.join(HERE, "..", "..", "build"),
                    help="the CMake build tree (build/python, build/bench/lcmx_bench_latency)")
    ap.add_argument("--sizes", default="1K,6M")
    ap.add_argument("--messages", type=int, default=0, help="measured per size (default 200 <= 100 KB, else 50)")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--rounds", type=int, default=3, help="runs of every method, rotated, pooled")
    ap.add_argument("--pin", default="none", choices=["none", "same", "split"])
    ap.add_argument("--timeout-ms", type=int, default=1000)
    ap.add_argument("--url", default="udpm://239.255.77.203:17703?ttl=0&iface=lo")
    ap.add_argument("--markdown", help="also write the table to this file")
    ap.add_argument("--role", help=argparse.SUPPRESS)
    ap.add_argument("--plan", help=argparse.SUPPRESS)
    ap.add_argument("--name", help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.build = os.path.abspath(args.build)
    sys.path.insert(0, os.path.join(args.build, "python"))
    if args.role:
        plan = [tuple(int(v) for v in p.split(":")) for p in args.plan.split(",")]
        raw = "raw" in args.role or "loan" in args.role
        if args.role.endswith("sub"):
            return run_py_sub(args, plan, raw)
        return run_py_pub(args, plan, raw, "loan" in args.role)

    args.bench_exe = os.path.join(args.build, "bench", "lcmx_bench_latency")
    if not os.access(args.bench_exe, os.X_OK):
        sys.exit("%s: not built (cmake --build %s --target lcmx_bench_latency lcmx_python)"
                 % (args.bench_exe, args.build))
    os.environ["PYTHONPATH"] = os.path.join(args.build, "python")
    plan = []
    for s in args.sizes.split(","):
        n = parse_size(s)
        plan.append((n, 20 if n <= 100 << 10 else 5, args.messages or (200 if n <= 100 << 10 else 50)))
    pub_cpu, sub_cpu = {"none": (-1, -1), "same": (0, 0), "split": (0, 1)}[args.pin]
    results, failed = {}, []
    methods = args.methods.split(",")
    for m in methods:
        if m not in METHODS:
            sys.exit("unknown method %r (known: %s)" % (m, ", ".join(METHODS)))
    # Rounds in rotated order, pooled per method: a drift of the shared machine (or a flip
    # of the wake-up between vCPUs) hits every method alike.
    for r in range(args.rounds):
        for method in methods[r % len(methods):] + methods[:r % len(methods)]:
            if any(m == method for m, _ in failed):
                continue
            print("bench_python: round %d: %s ..." % (r + 1, method), file=sys.stderr, flush=True)
            try:
                lat, lost, notes = run_method(args, method, plan, pub_cpu, sub_cpu)
            except RuntimeError as e:
                failed.append((method, str(e)))
                continue
            if method not in results:
                results[method] = ({n: [] for n in lat}, {n: 0 for n in lat}, [])
            for n in lat:
                results[method][0].setdefault(n, []).extend(lat[n])
                results[method][1][n] = results[method][1].get(n, 0) + lost.get(n, 0)
            results[method][2].extend(notes)
    for lat, _, _ in results.values():
        for v in lat.values():
            v.sort()
    md = ["## Python latency (one-way µs, p50 / p99), %s, pin %s, %d rounds of %s" % (
        time.strftime("%Y-%m-%d %H:%M"), args.pin, args.rounds,
        ", ".join("%s %d+%d" % (size_label(n), w, m) for n, w, m in plan)),
        "",
        "| method | size | p50 | p99 | lost | p50 vs cpp-shm | p50 vs cpp-loan |",
        "|---|---|---|---|---|---|---|"]
    for method, (lat, lost, _notes) in results.items():
        for n, _, _ in plan:
            p50, p99 = pct(lat.get(n, []), 50), pct(lat.get(n, []), 99)
            ratios = []
            for ref in ("cpp-shm", "cpp-loan"):
                r = results.get(ref)
                r50 = pct(r[0].get(n, []), 50) if r else None
                ratios.append("%.2fx" % (p50 / r50) if p50 and r50 else "-")
            md.append("| %s | %s | %s | %s | %d | %s | %s |" % (
                method, size_label(n), "%.1f" % p50 if p50 else "-", "%.1f" % p99 if p99 else "-",
                lost.get(n, 0), *ratios))
    # Issue 14's targets, on p50: at 1 KB <= 3x C++ (typed Python against typed C++), at 6 MB
    # raw <= 1.2x C++ (Python raw against C++'s shm path; Python loan against C++ loan).
    targets = [("1 KB", "py-py", "cpp-shm", 3.0), ("1 KB", "py-cpp", "cpp-shm", 3.0),
               ("6 MB", "py-py-raw", "cpp-shm", 1.2), ("6 MB", "py-cpp-raw", "cpp-shm", 1.2),
               ("6 MB", "py-py-loan", "cpp-loan", 1.2), ("6 MB", "py-cpp-loan", "cpp-loan", 1.2)]
    md += ["", "Targets (p50):"]
    for label, method, ref, limit in targets:
        n = next((n for n, _, _ in plan if size_label(n) == label), None)
        a = pct(results[method][0].get(n, []), 50) if method in results and n else None
        b = pct(results[ref][0].get(n, []), 50) if ref in results and n else None
        if a is None or b is None:
            md.append("- %s %s <= %.1fx %s: not measured" % (label, method, limit, ref))
        else:
            md.append("- %s %s <= %.1fx %s: %s (%.2fx)" % (label, method, limit, ref,
                                                         "holds" if a <= limit * b else "FAILS", a / b))
    for method, text in failed:
        md.append("")
        md.append("FAILED %s: %s" % (method, text))
    notes = sorted({n for _, (_, _, ns) in results.items() for n in ns})
    if notes:
        md += [""] + ["- " + n for n in notes]
    out = "\n".join(md) + "\n"
    sys.stdout.write(out)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(out)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
