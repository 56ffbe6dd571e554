"""Python <-> C++ over shared memory, with test/integration/peer.cpp's lcmx_test_peer."""
import os
import threading

import lcmx
from conftest import image_fields, pattern, summary
from lcmx_examples import pose_t

PEER = os.environ["LCMX_TEST_PEER"]


def test_cpp_to_python_pose_shm(lcmx_env, procs):
    got = []
    done = threading.Event()
    with lcmx.Runtime() as rt:
        node = rt.create_node("py_sub")

        def cb(msg):
            got.append(msg)
            if len(got) == 20:
                done.set()

        sub = node.subscribe("CPP_POSE", pose_t, cb, queue_depth=64)
        peer = procs([PEER, "pub", "--channel", "CPP_POSE", "--type", "pose", "--count", "20",
                      "--rate", "0", "--subscribers", "1", "--shm-slots", "64", "--id", "cpp",
                      "--hold", "--timeout-ms", "60000"])
        peer.expect("PUBLISHED 20", timeout=30)
        assert done.wait(20), len(got)
        assert [m.header.seq for m in got] == list(range(20))
        assert all(m.header.frame_id == "cpp" and m.position[0] == m.header.seq
                   and m.orientation[3] == 1.0 for m in got)
        s = sub.stats()
        assert [p["path"] for p in s["publishers"]] == ["shm"]
        assert s["drops"] == 0 and s["decode_errors"] == 0 and s["callback_errors"] == 0
        peer.send("quit")
        assert peer.wait(20) == 0


def test_python_to_cpp_pose_shm(lcmx_env, procs):
    with lcmx.Runtime() as rt:
        node = rt.create_node("py_pub")
        pub = node.advertise("PY_POSE_OUT", pose_t, shm_slots=64)
        peer = procs([PEER, "sub", "--channel", "PY_POSE_OUT", "--type", "pose", "--expect", "20",
                      "--publishers", "1", "--queue-depth", "64", "--timeout-ms", "60000"])
        peer.expect("READY")
        assert pub.wait_for_subscribers(1, timeout=20)
        for seq in range(20):
            m = pose_t()
            m.header.seq = seq
            m.header.frame_id = "py"
            m.position = [float(seq), 0.0, 0.0]
            m.orientation = [0.0, 0.0, 0.0, 1.0]
            pub.publish(m)
        s = summary(peer.expect("SUMMARY channel=PY_POSE_OUT", timeout=30))
        assert s["received"] == "20" and s["bad_content"] == "0" and s["out_of_order"] == "0", s
        assert s["decode_errors"] == "0" and s["paths"] == "shm", s
        assert peer.wait(20) == 0


def test_cpp_to_python_6mb_zero_copy(lcmx_env, procs):
    """Raw receive of 6 MB images from shared memory: a read-only memoryview of the slot."""
    width, height = 2048, 1024  # 6 MiB of rgb8
    checked = []
    done = threading.Event()
    with lcmx.Runtime() as rt:
        node = rt.create_node("py_images")

        def cb(view):
            seq, w, h, data = image_fields(view)  # data: a view, no copy
            checked.append((seq, view.readonly, w * h * 3 == len(data),
                            data == pattern(seq, len(data))))
            if len(checked) == 3:
                done.set()

        sub = node.subscribe_raw("CPP_IMAGE", cb)
        peer = procs([PEER, "pub", "--channel", "CPP_IMAGE", "--type", "image", "--count", "3",
                      "--width", str(width), "--height", str(height), "--rate", "0",
                      "--shm-slots", "4", "--subscribers", "1", "--hold", "--timeout-ms", "60000"])
        peer.expect("PUBLISHED 3", timeout=30)
        assert done.wait(20), checked
        assert checked == [(seq, True, True, True) for seq in range(3)]
        s = sub.stats()
        assert [p["path"] for p in s["publishers"]] == ["shm"] and s["drops"] == 0, s
        peer.send("quit")
        assert peer.wait(20) == 0
