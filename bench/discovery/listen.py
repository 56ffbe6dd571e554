#!/usr/bin/env python3
"""Counts LCM udpm bytes on a multicast group for a while, by sender address and by whether the
channel is LCMX_BEACON (discovery) or not. Run inside the namespace whose interface is given.
Usage: listen.py GROUP PORT IFACE_ADDR SECONDS  -> one JSON line {src: {"disc": bytes, "data": bytes,
"kinds": {kind: bytes}, "disc_datagrams": n}} at the end or on SIGTERM; kinds split the discovery bytes: "record" (a
participant's beacon_t, or a speaker's batch of them: records_t), "heartbeat", "index", "request", "mark" (host_beacon_t), "other";
"request_nonspeaker": a request from a participant that speaks for nobody (its count is 0), not its host's speaker.
"""
import json, signal, socket, struct, sys, time

stop = False
def on_term(*_):
    global stop
    stop = True
signal.signal(signal.SIGTERM, on_term)

group, port, iface, secs = sys.argv[1], int(sys.argv[2]), sys.argv[3], float(sys.argv[4])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("", port))
s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(group) + socket.inet_aton(iface))
s.settimeout(0.2)
out, frag = {}, {}
end = time.monotonic() + secs
while time.monotonic() < end and not stop:
    try:
        data, (src, _) = s.recvfrom(65536)
    except socket.timeout:
        continue
    kind, sub = "data", "other"
    if data[:4] == b"LC02":
        nul = data.index(b"\0", 8)
        ch = data[8:nul]
        kind = "disc" if ch == b"LCMX_BEACON" else "data"
        body = data[nul + 1:]
        if kind == "disc" and len(body) >= 13:
            version = struct.unpack(">i", body[8:12])[0]
            if version == 1:  # host_beacon_t (kHostBeaconVersion); beacon_t and records_t are version 6
                sub = {1: "heartbeat", 2: "index", 3: "request", 4: "mark"}.get(body[12], "other")
                if sub == "request" and len(body) >= 62 and struct.unpack(">i", body[58:62])[0] == 0:
                    sub = "request_nonspeaker"  # host_beacon_t.count: a speaker's counts what it speaks for
            else:
                sub = "record"
    elif data[:4] == b"LC03":
        seq = struct.unpack(">I", data[4:8])[0]
        fragno = struct.unpack(">H", data[16:18])[0]
        if fragno == 0:
            ch = data[20:data.index(b"\0", 20)]
            frag[(src, seq)] = "disc" if ch == b"LCMX_BEACON" else "data"
        kind = frag.get((src, seq), "data")
    d = out.setdefault(src, {"disc": 0, "data": 0, "kinds": {}, "disc_datagrams": 0})
    d[kind] += len(data) + 28  # + IP and UDP headers
    if kind == "disc":
        d["kinds"][sub] = d["kinds"].get(sub, 0) + len(data) + 28
        d["disc_datagrams"] += 1  # each one wakes every process of every other host
print(json.dumps(out), flush=True)
