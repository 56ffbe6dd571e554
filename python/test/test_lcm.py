"""lcmx.LCM, the drop-in for LCM's Python API."""
import os
import select
import time

import lcmx
from conftest import python_script
from lcmx_examples import pose_t

# Written in LCM's documented Python style (the LCM tutorial's listener), with
# `import lcmx as lcm`: it acknowledges three messages on ACK and exits.
_LISTENER = r'''
import lcmx as lcm
from lcmx_examples import pose_t

received = []

def my_handler(channel, data):
    msg = pose_t.decode(data)
    print("Received message on channel \"%s\"" % channel)
    print("   position    = %s" % str(msg.position))
    print("   frame_id    = '%s'" % msg.header.frame_id)
    if msg.header.seq not in received:
        received.append(msg.header.seq)
    lc.publish("ACK", data)

lc = lcm.LCM()
subscription = lc.subscribe("EXAMPLE", my_handler)
print("READY", flush=True)
try:
    while len(received) < 3:
        lc.handle()
except KeyboardInterrupt:
    pass
lc.unsubscribe(subscription)
print("DONE %s" % received, flush=True)
'''


def test_lcm_style_script(lcmx_env, procs, monkeypatch):
    monkeypatch.setenv("LCM_DEFAULT_URL", lcmx_env)
    listener = procs(python_script(_LISTENER))
    listener.expect("READY")
    acked = set()
    lc = lcmx.LCM()  # LCM_DEFAULT_URL, as the listener's
    lc.subscribe("ACK", lambda channel, data: acked.add(pose_t.decode(data).header.seq))
    deadline = time.monotonic() + 30
    seq = 0
    # An LCM publisher does not know its subscribers: send each message until acknowledged.
    while seq < 3:
        assert time.monotonic() < deadline, ("no acknowledgement", listener.seen)
        msg = pose_t()
        msg.header.seq = seq
        msg.header.frame_id = "lcm-style"
        msg.position = [float(seq), 0.0, 0.0]
        lc.publish("EXAMPLE", msg.encode())
        lc.handle_timeout(100)
        if seq in acked:
            seq += 1
    listener.expect("DONE [0, 1, 2]")
    assert listener.wait(20) == 0
    assert 'Received message on channel "EXAMPLE"' in listener.seen
    lc.close()


def test_lcm_fileno_select(lcmx_env):
    with lcmx.Runtime() as rt:
        lc = lcmx.LCM()  # shares the open Runtime
        got = []
        sub = lc.subscribe("PY_LCM_.*", lambda channel, data: got.append((channel, data)))
        assert lc.handle_timeout(0) == 0
        assert select.select([lc], [], [], 0)[0] == []
        deadline = time.monotonic() + 10
        # The channel subscription appears with the channel's first publisher: send until heard.
        while not select.select([lc], [], [], 0.05)[0]:
            assert time.monotonic() < deadline
            lc.publish("PY_LCM_A", b"payload")
        assert lc.handle_timeout(1000) == 1
        assert got[0] == ("PY_LCM_A", b"payload")
        lc.unsubscribe(sub)
        lc.close()
