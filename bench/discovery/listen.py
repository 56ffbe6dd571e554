#!/usr/bin/env python3
"""Counts LCM udpm bytes on a multicast group for a while, by sender address, and the datagrams
on LCMX_BEACON by their type: the 8-byte lcm fingerprint that starts every message.
Run inside the namespace whose interface is given (run.py runs it at real-time priority).

Usage: listen.py GROUP PORT IFACE_ADDR SECONDS FINGERPRINTS
  FINGERPRINTS: the JSON object lcmx_bench_fingerprints prints ({"beacon_t": "<16 hex>", ...,
  "marker_t": null when the build has no such type}).
Prints "LISTENING <monotonic ns>" once it has joined the group, then, at the end or on SIGTERM,
one JSON line:
  {"t0_ns": ..., "t1_ns": ...,       CLOCK_MONOTONIC: when it started and stopped listening
   "dropped": n,                     datagrams the kernel dropped at this socket (SO_RXQ_OVFL): the
                                     counts below miss them (the driver reports them as unmeasured)
   "sources": {src: {"disc": bytes, "mark": bytes, "data": bytes, "kinds": {kind: bytes},
                     "disc_datagrams": n, "mark_datagrams": n}}}
Bytes include the IP and UDP headers (+28). On LCMX_BEACON, by fingerprint:
  "record"     beacon_t (one record or goodbye), records_t, records_z_t (a speaker's batches)
  "heartbeat", "index", "request", "request_nonspeaker" (a request from a participant that
               speaks for nobody: count 0), "other": host_beacon_t by its kind field
  "mark"       data markers: host_beacon_t KIND_MARK and marker_t. Data bookkeeping, not
               discovery: counted in "mark", not in "disc" (and in kinds, to be seen)
  "unknown"    a fingerprint none of the above has (counted in "disc")
Other channels are "data". An LC03 message (fragments) is classified by its fragment 0; a
fragment whose fragment 0 was not heard is "data".
"""
import json, signal, socket, struct, sys, time

SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
HB_KINDS = {1: "heartbeat", 2: "index", 3: "request", 4: "mark"}  # host_beacon_t.KIND_*

stop = False


def on_term(*_):
    global stop
    stop = True


signal.signal(signal.SIGTERM, on_term)

group, port, iface, secs = sys.argv[1], int(sys.argv[2]), sys.argv[3], float(sys.argv[4])
fps = json.loads(sys.argv[5])
by_fp = {}
for name, kind in (("beacon_t", "record"), ("records_t", "record"), ("records_z_t", "record"),
                   ("host_beacon_t", "host_beacon"), ("marker_t", "mark")):
    if fps.get(name):
        by_fp[bytes.fromhex(fps[name])] = kind


def beacon_kind(body):
    """The kind of one LCMX_BEACON message (its lcm encoding, fingerprint first)."""
    k = by_fp.get(body[:8], "unknown")
    if k != "host_beacon":
        return k
    if len(body) < 13:
        return "other"
    sub = HB_KINDS.get(body[12], "other")  # fingerprint 8, version 4, then kind
    # host_beacon_t.count (after scope, host_id, registry_id, speaker, sequence, lease_ms, digest)
    if sub == "request" and len(body) >= 62 and struct.unpack(">i", body[58:62])[0] == 0:
        sub = "request_nonspeaker"
    return sub


s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
try:
    s.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 64 << 20)  # root: beyond rmem_max
except OSError:
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 << 20)
s.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
s.bind(("", port))
s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(group) + socket.inet_aton(iface))
s.settimeout(0.1)
t0 = time.monotonic_ns()
print(f"LISTENING {t0}", flush=True)
out, frag, dropped = {}, {}, 0
end = time.monotonic() + secs
while time.monotonic() < end and not stop:
    try:
        data, anc, _, (src, _) = s.recvmsg(65536, socket.CMSG_SPACE(4))
    except socket.timeout:
        continue
    except InterruptedError:
        continue
    for level, typ, val in anc:
        if level == socket.SOL_SOCKET and typ == SO_RXQ_OVFL and len(val) >= 4:
            dropped = struct.unpack("=I", val[:4])[0]  # cumulative since the socket opened
    kind, sub = "data", None
    try:
        if data[:4] == b"LC02":
            nul = data.index(b"\0", 8)
            if data[8:nul] == b"LCMX_BEACON":
                sub = beacon_kind(data[nul + 1:])
        elif data[:4] == b"LC03" and len(data) >= 20:
            seq = struct.unpack(">I", data[4:8])[0]
            fragno = struct.unpack(">H", data[16:18])[0]
            if fragno == 0:
                nul = data.index(b"\0", 20)
                frag[(src, seq)] = beacon_kind(data[nul + 1:]) if data[20:nul] == b"LCMX_BEACON" else None
                if len(frag) > 4096:
                    frag.pop(next(iter(frag)))
            sub = frag.get((src, seq))
    except ValueError:  # no NUL after the channel: not lcm's format
        sub = None
    if sub is not None:
        kind = "mark" if sub == "mark" else "disc"
    d = out.setdefault(src, {"disc": 0, "mark": 0, "data": 0, "kinds": {}, "disc_datagrams": 0, "mark_datagrams": 0})
    d[kind] += len(data) + 28
    if sub is not None:
        d["kinds"][sub] = d["kinds"].get(sub, 0) + len(data) + 28
        d[kind + "_datagrams"] += 1  # a discovery datagram wakes every process of every other host that hears it
print(json.dumps({"t0_ns": t0, "t1_ns": time.monotonic_ns(), "dropped": dropped, "sources": out}), flush=True)
