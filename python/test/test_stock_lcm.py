"""lcmx.LCM with stock liblcm programs (test/multihost's lcmx_mh_lcm_peer), both ways, on LCM's
default URL inside an emulated host of the test's own (liblcm cannot be pinned to lo), with
scripts in LCM's documented Python style. Needs root."""
import os
import signal
import sys

import pytest

LCM_PEER = os.environ.get("LCMX_LCM_PEER", "")
HOLDER = os.environ["LCMX_NETNS_HOLDER"]
IP = os.environ["LCMX_IP"]
URL = "udpm://239.255.76.67:7667?ttl=0"

_LISTENER = r'''
import lcmx as lcm
from lcmx_examples import bench_t

seqs = []
good = []

def my_handler(channel, data):
    msg = bench_t.decode(data)
    seqs.append(msg.seq)
    good.append(msg.size == len(msg.data) and
                all(msg.data[i] == (i * 131 + msg.seq * 7) & 0xFF for i in range(8, msg.size)))

lc = lcm.LCM("%s")
subscription = lc.subscribe("STOCK_.*", my_handler)
print("READY", flush=True)
try:
    while len(seqs) < 20:
        if lc.handle_timeout(30000) == 0:
            break
except KeyboardInterrupt:
    pass
lc.unsubscribe(subscription)
print("GOT", seqs == list(range(20)), all(good), flush=True)
''' % URL

_SENDER = r'''
import sys
import lcmx as lcm
from lcmx_examples import bench_t

lc = lcm.LCM("%s")
for seq in range(20):
    msg = bench_t()
    msg.seq = seq
    msg.size = 256
    msg.data = bytes(b"py" + bytes(6)) + bytes((i * 131 + seq * 7) & 0xFF for i in range(8, 256))
    lc.publish("PY_TO_STOCK", msg.encode())
print("SENT", flush=True)
sys.stdin.readline()  # "quit"
''' % URL


@pytest.fixture
def host(procs):
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if not LCM_PEER:
        pytest.skip("built without test/multihost's stock LCM peer")
    holder = procs([HOLDER, "1"])
    ns = holder.expect("ready ").split()[1]
    yield ns
    holder.p.send_signal(signal.SIGTERM)
    assert holder.wait(20) == 0


def test_stock_lcm_publisher_to_python_lcm(lcmx_env, host, procs):
    listener = procs([IP, "netns", "exec", host, sys.executable, "-c", _LISTENER])
    listener.expect("READY")
    pub = procs([IP, "netns", "exec", host, LCM_PEER, "pub", URL, "STOCK_BENCH", "20", "200",
                 "256", "stock"])
    pub.expect("done 20", timeout=30)
    assert listener.expect("GOT", timeout=30) == "GOT True True"
    assert listener.wait(20) == 0


def test_python_lcm_to_stock_lcm_subscriber(lcmx_env, host, procs):
    sub = procs([IP, "netns", "exec", host, LCM_PEER, "sub", URL, "PY_TO_STOCK", "20", "30000"])
    sub.expect("ready")
    sender = procs([IP, "netns", "exec", host, sys.executable, "-c", _SENDER])
    sender.expect("SENT")
    line = sub.expect("SUMMARY", timeout=30)
    s = dict(kv.split("=", 1) for kv in line.split()[1:])
    assert s["received"] == "20" and s["bad_content"] == "0" and s["duplicates"] == "0", s
    assert sub.wait(20) == 0
    sender.send("quit")
    assert sender.wait(20) == 0
