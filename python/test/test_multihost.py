"""Python <-> C++ across two emulated hosts (network namespaces, test/support's
lcmx_netns_holder): over the vehicle group (LCM UDP multicast on link "eth"), and 6 MB images
through the Message Bridges (`lcmx bridge` on each host). Needs root."""
import os
import signal
import subprocess
import sys

import pytest

from conftest import summary, unique_url

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
    procs.close_all(keep=(holder,))  # stopped cleanly while their hosts still exist
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
    s = summary(sub.expect("SUMMARY channel=PY_UDP", timeout=30))
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


# ---- through the Message Bridges: 6 MB images, a large topic ----

_IMAGE_SUB = r"""
import threading, lcmx
from conftest import image_fields, pattern
ok = []
done = threading.Event()
def cb(view):  # image_t's encoding, read in place
    seq, w, h, data = image_fields(view)
    ok.append(len(data) == w * h * 3 and data == pattern(seq, len(data)))
    if len(ok) == 3:
        done.set()
with lcmx.Runtime() as rt:
    sub = rt.create_node("py_img_sub").subscribe_raw("CPP_BIG", cb)
    print("READY", flush=True)
    got = done.wait(40)
    paths = sorted(set(p["path"] for p in sub.stats()["publishers"]))
    print("GOT", got, all(ok[:3]), ",".join(paths), flush=True)
"""

_IMAGE_PUB = r"""
import select, sys, lcmx
from lcmx_examples import image_t
from conftest import pattern
with lcmx.Runtime() as rt:
    pub = rt.create_node("py_img_pub").advertise("PY_BIG", image_t)
    assert pub.wait_for_subscribers(1, timeout=30)  # the local bridge, on demand of host B
    seq = 0
    # Until the subscriber has its images ("quit"): the first may go before host B's bridge
    # republishes the topic.
    while not select.select([sys.stdin], [], [], 0.05)[0]:
        m = image_t()
        m.header.seq = seq
        m.header.frame_id = "py"
        m.width, m.height = 2048, 1024
        m.stride = m.width * 3
        m.encoding = "rgb8"
        m.size = m.stride * m.height
        m.data = pattern(seq, m.size)
        pub.publish(m)
        seq += 1
"""


def _bridges(tmp_path, hosts, env, procs):
    tool = os.environ.get("LCMX_TOOL")
    if not tool:
        pytest.skip("built without the lcmx tool (LCMX_BUILD_APPS=OFF)")
    names = ["chipA", "chipB"]
    addrs = []
    for ns in hosts:
        out = subprocess.run([IP, "-n", ns, "-4", "-o", "addr", "show", "dev", "eth"],
                             capture_output=True, text=True, check=True).stdout
        addrs.append(out.split()[3].split("/")[0])
    bridges = []
    for i, ns in enumerate(hosts):
        peer = 1 - i
        cfg = tmp_path / (names[i] + ".toml")
        cfg.write_text(
            'name = "%s"\nlisten = ["%s"]\ncontrol_port = 7700\nheartbeat_ms = 100\n'
            'link_timeout_ms = 600\nstatus_period_ms = 200\n'
            '[[peer]]\nname = "%s"\nendpoints = [{ link = "eth", address = "%s" }]\n'
            % (names[i], addrs[i], names[peer], addrs[peer]))
        b = procs([IP, "netns", "exec", ns, tool, "bridge", "--config", str(cfg)], env=env)
        b.expect("bridge %s: ready" % names[i])
        bridges.append(b)
    return bridges


def test_cpp_to_python_images_through_bridges(lcmx_env, hosts, procs, tmp_path):
    env = vehicle_env()
    _bridges(tmp_path, hosts, env, procs)
    sub = procs([IP, "netns", "exec", hosts[1], sys.executable, "-c", _IMAGE_SUB], env=env)
    sub.expect("READY")
    pub = procs([IP, "netns", "exec", hosts[0], PEER, "pub", "--channel", "CPP_BIG", "--type",
                 "image", "--width", "2048", "--height", "1024", "--count", "0", "--rate", "10",
                 "--subscribers", "1", "--timeout-ms", "60000"], env=env)
    assert sub.expect("GOT", timeout=60) == "GOT True True bridge"
    assert sub.wait(20) == 0
    pub.send("quit")
    assert pub.wait(20) == 0


def test_python_to_cpp_images_through_bridges(lcmx_env, hosts, procs, tmp_path):
    env = vehicle_env()
    _bridges(tmp_path, hosts, env, procs)
    sub = procs([IP, "netns", "exec", hosts[1], PEER, "sub", "--channel", "PY_BIG", "--type",
                 "image", "--expect", "3", "--timeout-ms", "60000"], env=env)
    sub.expect("READY")
    pub = procs([IP, "netns", "exec", hosts[0], sys.executable, "-c", _IMAGE_PUB], env=env)
    s = summary(sub.expect("SUMMARY channel=PY_BIG", timeout=60))
    assert int(s["received"]) >= 3 and s["bad_content"] == "0" and s["paths"] == "bridge", s
    assert s["decode_errors"] == "0", s
    assert sub.wait(20) == 0
    pub.send("quit")
    assert pub.wait(20) == 0
