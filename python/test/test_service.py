"""Services from Python: in process, and a Python client of a C++ server in another process."""
import os

import pytest

import lcmx
from conftest import pattern
from lcmx_examples import bench_t, pose_t

PEER = os.environ["LCMX_SERVICE_PEER"]


def test_python_service_and_client(lcmx_env):
    with lcmx.Runtime() as rt:
        node = rt.create_node("srv")

        def plan(goal):
            if goal.position[0] < 0:
                raise ValueError("negative goal")
            answer = bench_t()
            answer.seq = int(goal.position[0])
            answer.data = b""  # lcm-gen's Python default for a byte array is a str
            return answer

        srv = node.create_service("py_plan", pose_t, bench_t, plan)
        cli = rt.create_node("cli").create_client("py_plan", pose_t, bench_t)
        assert cli.wait_for_service(10)
        goal = pose_t()
        goal.position = [7.0, 0.0, 0.0]
        assert cli.call(goal, timeout=5).seq == 7
        goal.position = [-1.0, 0.0, 0.0]
        with pytest.raises(lcmx.CallError) as err:
            cli.call(goal, timeout=5)
        assert err.value.code == "handler_failed" and "negative goal" in str(err.value)
        assert srv.handler_errors == 1
        goal.position = [8.0, 0.0, 0.0]  # the server lives on
        assert cli.call(goal, timeout=5).seq == 8
        with pytest.raises(lcmx.CallError) as err:
            rt.create_node("lost").create_client_raw("py_nobody").call(b"x", timeout=0.2)
        assert err.value.code in ("no_server", "timeout")


def test_python_client_of_cpp_server(lcmx_env, procs):
    server = procs([PEER, "server", "--name", "cpp_plan", "--timeout-ms", "60000"])
    server.expect("READY")
    with lcmx.Runtime() as rt:
        cli = rt.create_node("py_cli").create_client("cpp_plan", pose_t, bench_t)
        assert cli.wait_for_service(20)
        for x in range(5):
            goal = pose_t()
            goal.position = [float(x), 1000.0, 0.0]
            answer = cli.call(goal, timeout=5)
            assert answer.seq == x and bytes(answer.data) == pattern(x, 1000)
    server.send("quit")
    server.expect("SERVED 5")
    assert server.wait(20) == 0


def test_cpp_client_of_python_server(lcmx_env, procs):
    def serve(goal):
        x, n = int(goal.position[0]), int(goal.position[1])
        answer = bench_t()
        answer.seq = x
        answer.size = n
        answer.data = pattern(x, n)
        return answer

    with lcmx.Runtime() as rt:
        srv = rt.create_node("py_srv").create_service("py_served", pose_t, bench_t, serve)
        client = procs([PEER, "client", "--name", "py_served", "--calls", "5", "--size", "3000",
                        "--timeout-ms", "60000"])
        line = client.expect("CALLS", timeout=30)
        assert line.startswith("CALLS ok=5 failed=0 wrong=0 path=shm"), line
        assert client.wait(20) == 0
        assert srv.handler_errors == 0


def test_typed_service_types_on_the_wire(lcmx_env):
    """Python <-> Python: a client of other types gets type_mismatch, not handler_failed; a
    raw client still matches, and a request that does not decode is bad_request."""
    calls = []

    def plan(goal):
        calls.append(goal)
        answer = bench_t()
        answer.seq = int(goal.position[0])
        answer.data = b""
        return answer

    with lcmx.Runtime() as rt:
        srv = rt.create_node("srv").create_service("py_typed", pose_t, bench_t, plan)
        wrong = rt.create_node("wrong").create_client("py_typed", bench_t, bench_t)
        request = bench_t()
        request.data = b""
        with pytest.raises(lcmx.CallError) as err:
            wrong.call(request, timeout=1.0)
        assert err.value.code == "type_mismatch", err.value
        assert "pose_t" in str(err.value) and "bench_t" in str(err.value)
        raw = rt.create_node("raw").create_client_raw("py_typed")
        assert raw.wait_for_service(10)
        goal = pose_t()
        goal.position = [5.0, 0.0, 0.0]
        assert bench_t.decode(raw.call(goal.encode(), timeout=5)).seq == 5
        with pytest.raises(lcmx.CallError) as err:
            raw.call(b"\x01\x02not a pose", timeout=5)
        assert err.value.code == "bad_request" and "pose_t" in str(err.value), err.value
        assert len(calls) == 1 and srv.handler_errors == 0
        with pytest.raises(TypeError):
            rt.create_node("bad").create_service("py_bad", pose_t, bench_t, 42)  # not callable


def test_typed_service_type_mismatch_with_cpp(lcmx_env, procs):
    """Python client of a C++ server of other types, and the C++ client of a Python server of
    other types: type_mismatch both ways."""
    server = procs([PEER, "server", "--name", "cpp_typed", "--timeout-ms", "60000"])
    server.expect("READY")
    with lcmx.Runtime() as rt:
        node = rt.create_node("py")
        wrong = node.create_client("cpp_typed", bench_t, bench_t)
        request = bench_t()
        request.data = b""
        with pytest.raises(lcmx.CallError) as err:
            wrong.call(request, timeout=1.0)
        assert err.value.code == "type_mismatch" and "pose_t" in str(err.value), err.value

        def serve(req):
            return req

        srv = node.create_service("py_typed_other", bench_t, bench_t, serve)
        client = procs([PEER, "client", "--name", "py_typed_other", "--calls", "1", "--no-wait",
                        "--call-timeout-ms", "1000", "--timeout-ms", "60000"])
        line = client.expect("CALLS", timeout=30)
        assert line.startswith("CALLS ok=0 failed=1 wrong=0 path=- server=0 error=type mismatch: "), line
        assert "bench_t" in line and "pose_t" in line, line
        assert client.wait(20) == 0
        assert srv.handler_errors == 0
    server.send("quit")
    assert server.expect("SERVED") == "SERVED 0"
    assert server.wait(20) == 0
