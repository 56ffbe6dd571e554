"""Python <-> C++ across two emulated hosts (network namespaces, test/support's
lcmx_netns_holder) over the vehicle group (LCM UDP multicast on link "eth"). Needs root."""
import os
import signal
import sys

import pytest

from conftest import unique_url

PEER = os.environ["LCMX_TEST_PEER"]
HOLDER = os.environ["LCMX_NETNS_HOLDER"]
IP = os.environ["LCMX_IP"]

_PUB = r"""
import sys, lcmx
from lcmx_examples import pose_t
with lcmx.Runtime() as rt:
    pub = rt.create_node("py_udp_pub").advertise("PY_UDP", pose_t)
    assert pub.wait_for_subscribers(1, timeout=30)
    for seq in range(20):
        m = pose_t()
        m.header.seq = seq
        m.header.frame_id = "py"
        m.position = [float(seq), 0.0, 0.0]
        m.orientation = [0.0, 0.0, 0.0, 1.0]
        pub.publish(m)
    print("PUBLISHED 20", flush=True)
    sys.stdin.readline()  # "quit": the subscriber has them all
"""

_SUB = r"""
import threading, lcmx
from lcmx_examples import pose_t
got = []
done = threading.Event()
def cb(m):
    got.append(m.header.seq if m.position[0] == m.header.seq and m.orientation[3] == 1.0 else -1)
    if len(got) == 20:
        done.set()
with lcmx.Runtime() as rt:
    sub = rt.create_node("py_udp_sub").subscribe("CPP_UDP", pose_t, cb, queue_depth=64)
    print("READY", flush=True)
    ok = done.wait(30)
    paths = sorted(p["path"] for p in sub.stats()["publishers"])
    print("GOT", ok, got == list(range(20)), ",".join(paths), flush=True)
"""


@pytest.fixture
def hosts(procs):
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    holder = procs([HOLDER, "2"])
    fields = holder.expect("ready ").split()
    yield fields[1], fields[4]
    holder.p.send_signal(signal.SIGTERM)  # removes the namespaces
    assert holder.wait(20) == 0


def vehicle_env():
    env = dict(os.environ)
    env["LCMX_VEHICLE_URL"] = unique_url().replace("ttl=0&iface=lo", "ttl=1&iface=eth")
    return env


def test_python_to_cpp_udp_across_hosts(lcmx_env, hosts, procs):
    env = vehicle_env()
    sub = procs([IP, "netns", "exec", hosts[1], PEER, "sub", "--channel", "PY_UDP", "--type",
                 "pose", "--expect", "20", "--publishers", "1", "--queue-depth", "64",
                 "--timeout-ms", "60000"], env=env)
    sub.expect("READY")
    pub = procs([IP, "netns", "exec", hosts[0], sys.executable, "-c", _PUB], env=env)
    pub.expect("PUBLISHED 20", timeout=40)
    s = dict(kv.split("=", 1) for kv in sub.expect("SUMMARY channel=PY_UDP", timeout=30).split()[1:])
    assert s["received"] == "20" and s["bad_content"] == "0" and s["paths"] == "udp", s
    assert sub.wait(20) == 0
    pub.send("quit")
    assert pub.wait(20) == 0


def test_cpp_to_python_udp_across_hosts(lcmx_env, hosts, procs):
    env = vehicle_env()
    sub = procs([IP, "netns", "exec", hosts[1], sys.executable, "-c", _SUB], env=env)
    sub.expect("READY")
    pub = procs([IP, "netns", "exec", hosts[0], PEER, "pub", "--channel", "CPP_UDP", "--type",
                 "pose", "--count", "20", "--rate", "200", "--subscribers", "1", "--hold",
                 "--timeout-ms", "60000"], env=env)
    assert sub.expect("GOT", timeout=60) == "GOT True True udp"
    assert sub.wait(20) == 0
    pub.send("quit")
    assert pub.wait(20) == 0
