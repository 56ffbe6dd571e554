"""Actions from Python: server and client in one process, and with test/integration's C++
lcmx_service_peer (action-server / action-client roles: goal pose_t, feedback pose_t, result
bench_t) over shared memory; Ctrl-C and interpreter exit with a goal in flight."""
import os
import re
import signal
import sys

import pytest

import lcmx
from lcmx_examples import bench_t, pose_t

PEER = os.environ["LCMX_SERVICE_PEER"]


def goal_of(x):
    g = pose_t()
    g.position = [float(x), 0.0, 0.0]
    return g


def result_of(x):
    r = bench_t()
    r.seq = x
    r.data = b""  # lcm-gen's Python default for a byte array is a str
    return r


def test_python_action_server_and_client(lcmx_env):
    kept = []

    def accept(goal):
        return "too far" if goal.position[0] == 99 else True

    def execute(g):
        x = int(g.goal.position[0])
        kept.append(g)
        if x == 13:
            raise RuntimeError("unlucky goal")
        if x < 0:
            assert g.wait_for_cancel(20)
            g.canceled(result_of(x))
            return
        for i in range(1, x + 1):
            g.publish_feedback(goal_of(i))
        with pytest.raises(TypeError):
            g.succeed(pose_t())  # not the result type: nothing sent
        g.succeed(result_of(x))

    with lcmx.Runtime() as rt:
        srv = rt.create_node("act_srv").create_action_server(
            "py_drive", pose_t, pose_t, bench_t, execute, accept=accept)
        cli = rt.create_node("act_cli").create_action_client("py_drive", pose_t, pose_t, bench_t)
        assert cli.wait_for_server(10)

        feedback = []
        goal = cli.send_goal(goal_of(3), timeout=5, on_feedback=lambda f: feedback.append(f.position[0]))
        assert goal.accepted and len(goal.id) == 32
        out = goal.wait(10)
        assert out.status.state == "succeeded" and out.result.seq == 3
        assert feedback == [1.0, 2.0, 3.0]  # every feedback before wait() returned

        rejected = cli.send_goal(goal_of(99), timeout=5)
        assert not rejected.accepted and rejected.message == "too far"
        assert rejected.wait(5).status.state == "rejected"

        failed = cli.send_goal(goal_of(13), timeout=5).wait(10)
        assert failed.status.state == "aborted" and "unlucky goal" in failed.status.message
        assert srv.execute_errors == 1

        live = cli.send_goal(goal_of(-1), timeout=5)
        assert cli.status(live.id).state in ("accepted", "executing")
        assert live.cancel(5).state in ("canceling", "canceled")
        out = live.wait(10)
        assert out.status.state == "canceled" and out.result.seq == -1
        assert cli.goal(live.id).status().state == "canceled"

        wrong = rt.create_node("act_wrong").create_action_client("py_drive", bench_t, pose_t, bench_t)
        with pytest.raises(lcmx.CallError) as err:
            wrong.send_goal(result_of(1), timeout=2)
        assert err.value.code == "type_mismatch" and "pose_t" in str(err.value)
        with pytest.raises(TypeError):
            cli.send_goal(result_of(1))  # not the goal type
        with pytest.raises(TypeError):
            rt.create_node("act_bad").create_action_server("py_bad", pose_t, pose_t, bench_t, 42)
        s = srv.stats()
        assert (s["accepted"], s["succeeded"], s["aborted"], s["canceled"]) == (3, 1, 1, 1), s
        srv.close()  # every execute has returned: their handles are dead
        assert len(kept) == 3
        with pytest.raises(lcmx.Error):
            kept[0].publish_feedback(goal_of(0))


def test_cpp_client_of_python_action_server(lcmx_env, procs):
    def execute(g):
        x = int(g.goal.position[0])
        for i in range(1, x + 1):
            g.publish_feedback(goal_of(i))
        g.succeed(result_of(x))

    with lcmx.Runtime() as rt:
        srv = rt.create_node("py_act_srv").create_action_server(
            "py_served", pose_t, pose_t, bench_t, execute)
        client = procs([PEER, "action-client", "--name", "py_served", "--x", "4",
                        "--timeout-ms", "60000"])
        client.expect("ACCEPTED")
        assert client.expect("OUTCOME", timeout=30) == "OUTCOME state=succeeded seq=4 feedback=4"
        assert client.wait(20) == 0
        assert srv.stats()["succeeded"] == 1


def test_python_client_of_cpp_action_server(lcmx_env, procs):
    server = procs([PEER, "action-server", "--name", "cpp_drive", "--timeout-ms", "60000"])
    server.expect("READY")
    with lcmx.Runtime() as rt:
        node = rt.create_node("py_act_cli")
        cli = node.create_action_client("cpp_drive", pose_t, pose_t, bench_t)
        assert cli.wait_for_server(20)
        feedback = []
        out = cli.send_goal(goal_of(3), 10, lambda f: feedback.append(f.position[0])).wait(20)
        assert out.status.state == "succeeded" and out.result.seq == 3 and feedback == [1.0, 2.0, 3.0]

        live = cli.send_goal(goal_of(-5), 10)
        assert server.expect("EXECUTING") == "EXECUTING " + live.id
        live.cancel(5)
        assert server.expect("CANCELED") == "CANCELED " + live.id
        out = live.wait(20)
        assert out.status.state == "canceled" and out.result.seq == -5

        wrong = node.create_action_client("cpp_drive", bench_t, pose_t, bench_t)
        with pytest.raises(lcmx.CallError) as err:
            wrong.send_goal(result_of(1), timeout=2)
        assert err.value.code == "type_mismatch"
    server.send("quit")
    assert server.expect("ACTIONS") == "ACTIONS accepted=2 succeeded=1 canceled=1 client_gone=0"
    assert server.wait(20) == 0


_CLIENT = r"""
import lcmx
from lcmx_examples import pose_t, bench_t
rt = lcmx.Runtime()  # no with-block: the interpreter's exit closes it
cli = rt.create_node("py_act_cli").create_action_client("cpp_long", pose_t, pose_t, bench_t)
assert cli.wait_for_server(20)
g = pose_t()
g.position = [-1.0, 0.0, 0.0]
try:
    goal = cli.send_goal(g, 10)
    print("ACCEPTED", goal.id, flush=True)
    goal.wait()  # no timeout: only Ctrl-C ends it
except KeyboardInterrupt:
    print("INTERRUPTED", goal.status().state, flush=True)
"""


def test_ctrl_c_python_client_with_goal_in_flight(lcmx_env, procs):
    server = procs([PEER, "action-server", "--name", "cpp_long", "--client-timeout-ms", "300",
                    "--timeout-ms", "60000"])
    server.expect("READY")
    client = procs([sys.executable, "-c", _CLIENT])
    goal_id = client.expect("ACCEPTED").split()[1]
    assert server.expect("EXECUTING") == "EXECUTING " + goal_id
    client.p.send_signal(signal.SIGINT)
    # Its last status heard: the server's "executing" may not have reached it yet.
    assert client.expect("INTERRUPTED") in ("INTERRUPTED accepted", "INTERRUPTED executing")
    assert client.wait(20) == 0
    # The client is gone: the server cancels its goal after client_timeout.
    assert server.expect("CANCELED", timeout=20) == "CANCELED " + goal_id
    server.send("quit")
    # The peer prints CANCELED just before it ends the goal: "canceled" may not count it yet.
    assert re.fullmatch(r"ACTIONS accepted=1 succeeded=0 canceled=[01] client_gone=1",
                        server.expect("ACTIONS")), server.seen[-1]
    assert server.wait(20) == 0


_SERVER = r"""
import threading, lcmx
from lcmx_examples import pose_t, bench_t
def execute(g):
    print("EXECUTING", g.id, flush=True)
    while not g.wait_for_cancel(0.02):  # Python runs between the waits
        g.publish_feedback(pose_t())
    r = bench_t()
    r.seq = int(g.goal.position[0])
    r.data = b""
    g.canceled(r)
    print("ENDED", g.id, flush=True)
rt = lcmx.Runtime()  # no with-block: the interpreter's exit closes it (atexit)
srv = rt.create_node("py_act_srv").create_action_server("py_long", pose_t, pose_t, bench_t, execute)
print("READY", flush=True)
try:
    threading.Event().wait()  # until Ctrl-C
except KeyboardInterrupt:
    print("INTERRUPTED", [g.state for g in srv.goals()], flush=True)
"""


def test_ctrl_c_python_server_with_goal_in_flight(lcmx_env, procs):
    server = procs([sys.executable, "-c", _SERVER])
    server.expect("READY")
    client = procs([PEER, "action-client", "--name", "py_long", "--x", "-7",
                    "--timeout-ms", "60000"])
    goal_id = client.expect("ACCEPTED").split()[1]
    assert server.expect("EXECUTING") == "EXECUTING " + goal_id
    server.p.send_signal(signal.SIGINT)
    assert server.expect("INTERRUPTED") == "INTERRUPTED ['executing']"
    # Exit closes the server: the goal is canceled, execute returns, the process ends.
    assert server.expect("ENDED") == "ENDED " + goal_id
    assert server.wait(20) == 0
    # The client hears the end (canceled, in the server's final status; its result if the
    # server was still there to give it) or that the server went away first (lost), as C++
    # action_test's "destroying the server" allows; never a hang.
    outcome = client.expect("OUTCOME", timeout=30)
    assert re.fullmatch(r"OUTCOME state=(canceled seq=(-7|-)|lost seq=-) feedback=\d+", outcome), outcome
    assert client.wait(20) == 0
