"""lcmx's Python API inside one process (and its shutdown in a child process)."""
import signal
import threading

import pytest

import lcmx
from conftest import python_script, wait_for
from lcmx_examples import header_t, pose_t


def pose(seq):
    m = pose_t()
    m.header.seq = seq
    m.header.frame_id = "py"
    m.position = [float(seq), 2.0, 3.0]
    m.orientation = [0.0, 0.0, 0.0, 1.0]
    return m


def test_typed_roundtrip_in_process(lcmx_env):
    got = []
    done = threading.Event()
    with lcmx.Runtime() as rt:
        node = rt.create_node("typed")
        pub = node.advertise("PY_POSE", pose_t)

        def cb(msg):
            got.append((msg.header.seq, msg.header.frame_id, tuple(msg.position)))
            if len(got) == 3:
                done.set()

        sub = node.subscribe("PY_POSE", pose_t, cb)
        assert pub.wait_for_subscribers(1, timeout=10)
        for i in range(3):
            pub.publish(pose(i))
        assert done.wait(10)
        assert got == [(i, "py", (float(i), 2.0, 3.0)) for i in range(3)]
        assert wait_for(lambda: sub.stats()["delivered"] == 3)  # counted after each callback
        s = sub.stats()
        assert s["callback_errors"] == 0
        assert [p["path"] for p in s["publishers"]] == ["intra"]
        assert pub.stats()["published"] == 3
        with pytest.raises(TypeError):
            pub.publish(header_t())
        # A callback that is not callable is a TypeError, as for services and actions.
        with pytest.raises(TypeError):
            node.subscribe("PY_NOT_CALLABLE", pose_t, 42)
        with pytest.raises(TypeError):
            node.subscribe_raw("PY_NOT_CALLABLE", "not a function")
        with pytest.raises(TypeError):
            rt.on_event(None)


def test_keep_last_n_late_subscriber_gets_the_last_messages_once(lcmx_env):
    got = []
    with lcmx.Runtime() as rt:
        node = rt.create_node("keep")
        pub = node.advertise("PY_KEEP", pose_t, history=3)
        for i in range(5):
            pub.publish(pose(i))
        node.subscribe("PY_KEEP", pose_t, lambda m: got.append(m.header.seq))
        assert wait_for(lambda: len(got) >= 3)
        for i in range(5, 7):
            pub.publish(pose(i))
        assert wait_for(lambda: len(got) >= 5)
        assert got == [2, 3, 4, 5, 6]


def test_raw_memoryview_released_after_callback(lcmx_env, capfd):
    views = []
    contents = []
    slices = []
    done = threading.Event()
    with lcmx.Runtime() as rt:
        node = rt.create_node("raw")
        pub = node.advertise_raw("PY_RAW")

        def cb(view):
            assert isinstance(view, memoryview) and view.readonly
            contents.append(bytes(view))
            views.append(view)
            if len(views) == 2:
                slices.append(view[1:3])  # a view of its own: cannot be revoked, is reported
                done.set()

        node.subscribe_raw("PY_RAW", cb)
        assert pub.wait_for_subscribers(1, timeout=10)
        pub.publish(b"hello lcmx")
        pub.publish(b"second")
        assert done.wait(10)
    assert contents == [b"hello lcmx", b"second"]
    with pytest.raises(ValueError):  # released: a view kept past its callback cannot read
        bytes(views[0])
    assert capfd.readouterr().out.count("was kept past its callback") == 1
    slices[0].release()


def test_raw_loan_zero_copy_publish(lcmx_env):
    got = []
    done = threading.Event()
    with lcmx.Runtime() as rt:
        node = rt.create_node("loaner")
        pub = node.advertise_raw("PY_LOAN")

        def cb(view):
            got.append(bytes(view))
            if len(got) == 2:
                done.set()

        node.subscribe_raw("PY_LOAN", cb)
        assert pub.wait_for_subscribers(1, timeout=10)
        with pub.loan(5) as buf:  # a writable view of the slot, published on leaving
            assert not buf.readonly and len(buf) == 5
            buf[:] = b"first"
        with pytest.raises(RuntimeError):
            with pub.loan(8) as buf:
                buf[:3] = b"bad"
                raise RuntimeError("dropped, never sent")
        loan = pub.loan(64)
        head = loan.view[:6]  # a slice: the slot cannot be published while it is alive
        head[:] = b"second"
        with pytest.raises(lcmx.Error):
            loan.publish()
        head.release()
        loan.publish(6)  # 6 of the 64 bytes
        with pytest.raises(lcmx.Error):
            loan.publish()  # once
        with pytest.raises(ValueError):
            head[0]  # released
        assert done.wait(10)
        assert got == [b"first", b"second"]
        with pytest.raises(TypeError):
            node.advertise("PY_LOAN_TYPED", pose_t).loan(10)  # typed publishers publish messages


def _python_thread_states():
    import ctypes
    api = ctypes.pythonapi
    api.PyInterpreterState_Head.restype = ctypes.c_void_p
    api.PyInterpreterState_ThreadHead.restype = ctypes.c_void_p
    api.PyInterpreterState_ThreadHead.argtypes = [ctypes.c_void_p]
    api.PyThreadState_Next.restype = ctypes.c_void_p
    api.PyThreadState_Next.argtypes = [ctypes.c_void_p]
    n, t = 0, api.PyInterpreterState_ThreadHead(api.PyInterpreterState_Head())
    while t:
        n, t = n + 1, api.PyThreadState_Next(t)
    return n


def test_executor_thread_states_freed_with_their_threads(lcmx_env):
    """Executor threads keep their Python thread state between callbacks; it goes when the
    thread ends (closed nodes), so making and closing nodes does not accumulate them."""
    before = _python_thread_states()
    with lcmx.Runtime() as rt:
        pub = rt.create_node("ts_pub").advertise_raw("PY_TS")
        for i in range(5):
            got = threading.Event()
            node = rt.create_node("ts_%d" % i)
            sub = node.subscribe_raw("PY_TS", lambda view: got.set())
            assert pub.wait_for_subscribers(1, timeout=10)
            pub.publish(b"x")
            assert got.wait(10)
            sub.close()
            node.close()
        # An executor thread ends within its 1 s wait once its node is gone.
        assert wait_for(lambda: _python_thread_states() == before, timeout=10), \
            (before, _python_thread_states())


def test_raising_callback_is_counted_and_executor_lives_on(lcmx_env, capfd):
    first = threading.Event()
    second = threading.Event()
    with lcmx.Runtime() as rt:
        node = rt.create_node("raises")
        pub = node.advertise("PY_RAISE", pose_t)

        def cb(msg):
            if msg.header.seq == 0:
                first.set()
                raise RuntimeError("boom from a callback")
            second.set()

        sub = node.subscribe("PY_RAISE", pose_t, cb)
        assert pub.wait_for_subscribers(1, timeout=10)
        pub.publish(pose(0))
        assert first.wait(10)
        pub.publish(pose(1))
        assert second.wait(10)
        # `delivered` counts a callback once it returned: wait for the second one's.
        assert wait_for(lambda: sub.stats()["delivered"] == 2)
        assert sub.stats()["callback_errors"] == 1
    logged = capfd.readouterr()
    assert "boom from a callback" in logged.out + logged.err


def test_callback_that_publishes(lcmx_env):
    """A callback publishes to a subscriber of the same node (one executor thread), 200 rounds."""
    done = threading.Event()
    with lcmx.Runtime() as rt:
        node = rt.create_node("pingpong")
        ping = node.advertise("PY_PING", pose_t)
        pong = node.advertise("PY_PONG", pose_t)

        def on_ping(msg):
            pong.publish(msg)

        def on_pong(msg):
            if msg.header.seq == 199:
                done.set()
            else:
                ping.publish(pose(msg.header.seq + 1))

        node.subscribe("PY_PING", pose_t, on_ping)
        node.subscribe("PY_PONG", pose_t, on_pong)
        assert ping.wait_for_subscribers(1, timeout=10)
        assert pong.wait_for_subscribers(1, timeout=10)
        ping.publish(pose(0))
        assert done.wait(20)


def test_manual_spin_once(lcmx_env):
    threads = []
    with lcmx.Runtime() as rt:
        node = rt.create_node("manual", manual=True)
        pub = node.advertise("PY_MANUAL", pose_t)
        node.subscribe("PY_MANUAL", pose_t, lambda msg: threads.append(threading.get_ident()))
        assert pub.wait_for_subscribers(1, timeout=10)
        assert node.spin_once(0.0) == 0
        pub.publish(pose(0))
        assert node.spin_once(10.0) == 1
    assert threads == [threading.get_ident()]


def test_second_runtime_is_an_error(lcmx_env):
    with lcmx.Runtime():
        with pytest.raises(lcmx.Error):
            lcmx.Runtime()
    with lcmx.Runtime():  # the first one is gone
        pass


def test_type_mismatch_is_reported(lcmx_env):
    mismatch = threading.Event()
    events = []
    with lcmx.Runtime() as rt:
        def on_event(kind, channel, message):
            if kind == "type_mismatch" and channel == "PY_MISMATCH":
                events.append(message)
                mismatch.set()

        rt.on_event(on_event)
        node = rt.create_node("mismatch")
        pub = node.advertise("PY_MISMATCH", pose_t)
        sub = node.subscribe("PY_MISMATCH", header_t, lambda msg: None)
        assert mismatch.wait(10)
        assert "pose_t" in events[0] and "header_t" in events[0]
        assert pub.subscriber_count() == 0
        assert any("header_t" in e for e in sub.stats()["errors"])


_IN_FLIGHT = r"""
import threading, lcmx
from lcmx_examples import pose_t
rt = lcmx.Runtime()
node = rt.create_node("busy")
pub = node.advertise("PY_BUSY", pose_t)
first = threading.Event()
calls = [0]
def cb(msg):
    calls[0] += 1
    first.set()
    sum(range(200000))  # Python work while the main thread exits
sub = node.subscribe("PY_BUSY", pose_t, cb, queue_depth=1000)
assert pub.wait_for_subscribers(1, timeout=10)
for i in range(200):
    pub.publish(pose_t())
assert first.wait(10)
print("EXITING", calls[0], flush=True)
# no close(): the interpreter ends with callbacks queued and one running
"""


def test_shutdown_with_callbacks_in_flight(lcmx_env, procs):
    p = procs(python_script(_IN_FLIGHT))
    p.expect("EXITING")
    assert p.wait(30) == 0, p.seen


_SPIN = r"""
import lcmx
from lcmx_examples import pose_t
with lcmx.Runtime() as rt:
    node = rt.create_node("spinner", manual=True)
    node.subscribe("PY_SPIN", pose_t, lambda msg: None)
    try:  # READY inside: Ctrl-C may come as soon as it is printed
        print("READY", flush=True)
        node.spin()
    except KeyboardInterrupt:
        print("INTERRUPTED", flush=True)
print("CLOSED", flush=True)
"""


def test_ctrl_c_in_spin(lcmx_env, procs):
    p = procs(python_script(_SPIN))
    p.expect("READY")
    p.p.send_signal(signal.SIGINT)
    p.expect("INTERRUPTED", timeout=10)
    p.expect("CLOSED", timeout=10)
    assert p.wait(10) == 0
