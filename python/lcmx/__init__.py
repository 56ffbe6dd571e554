"""lcmx for Python: the same runtime as C++ (intra-process, shared memory, UDP, bridges).

    import lcmx
    from lcmx_examples import pose_t          # lcm-gen --python types

    with lcmx.Runtime() as rt:
        node = rt.create_node("planner")
        pub = node.advertise("POSE", pose_t)
        sub = node.subscribe("POSE", pose_t, lambda msg: print(msg.position))
        pub.wait_for_subscribers(1, timeout=5)
        pub.publish(pose_t())

Threads: a node's callbacks run on its executor thread (one per node by default), holding
the GIL only during the call; with ``create_node(name, manual=True)`` they run inside
``node.spin_once(timeout)`` on the caller's thread instead. A callback that raises is logged
and counted (``stats()["callback_errors"]``); the executor goes on. Raw callbacks get a
read-only ``memoryview`` of the message (shared memory itself on that path, no copy), valid
only during the callback: copy what you keep (``bytes(view)``).

Errors are ``lcmx.Error`` (a ``RuntimeError``), with the C++ core's messages. A second
Runtime in one process raises it; ``lcmx.LCM`` shares the process's Runtime if one is open.

``lcmx.LCM`` is a drop-in for LCM's Python API: ``import lcmx as lcm; lc = lcm.LCM()``.
"""

import atexit as _atexit
import collections as _collections
import struct as _struct

from . import _lcmx
from ._lcmx import Error, LCMSubscription, Loan

__all__ = ["Runtime", "Node", "Publisher", "Loan", "Subscriber", "Service", "Client", "CallError",
           "ActionServer", "ActionGoal", "ActionClient", "ClientGoal", "GoalStatus", "GoalOutcome",
           "LCM", "LCMSubscription", "Error"]


class _Closing:
    """close() on leaving a with-block; subclasses define close()."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _type_info(msg_type):
    """(name, fingerprint) of an lcm-gen --python class, as C++'s getTypeName()/getHash()."""
    try:
        packed = msg_type._get_packed_fingerprint()
    except AttributeError:
        raise TypeError(f"{msg_type!r} is not an lcm-gen Python type") from None
    return msg_type.__name__, _struct.unpack(">q", packed)[0]


def _service_types(req_type, resp_type):
    (req, req_fp), (resp, resp_fp) = _type_info(req_type), _type_info(resp_type)
    return req, resp, req_fp, resp_fp


def _action_types(goal_type, feedback_type, result_type):
    names, fps = zip(*(_type_info(t) for t in (goal_type, feedback_type, result_type)))
    return names + fps


def _check_callable(fn, what):
    if not callable(fn):
        raise TypeError("%s is not callable: %r" % (what, fn))


def _encode(msg, msg_type, what):
    """msg.encode() if msg is a msg_type (None: msg as bytes-like, raw endpoints)."""
    if msg_type is None:
        return msg
    if not isinstance(msg, msg_type):
        raise TypeError("%s: expected %s, got %s" % (what, msg_type.__name__, type(msg).__name__))
    return msg.encode()


class Runtime(_Closing):
    """The participant: one per process. Use as a context manager, or call close().

    Options default to the environment (LCMX_DISCOVERY_URL, LCMX_VEHICLE_URL, LCMX_MIRROR,
    ...), as in C++ RuntimeOptions::from_env(); keyword arguments override them.
    """

    def __init__(self, discovery_url=None, vehicle_url=None, mirror=None,
                 beacon_period_ms=None, lease_ms=None):
        self._rt = _lcmx._Runtime(discovery_url, vehicle_url, mirror, beacon_period_ms, lease_ms)

    def create_node(self, name, manual=False, threads=1):
        """A node; manual=True: no executor thread, callbacks run in node.spin_once()."""
        return Node(self._rt.create_node(name, manual, threads))

    def on_event(self, callback):
        """callback(kind, channel, message) for type mismatches, matches, participants and
        errors; runs on the discovery thread (keep it short). Replaces the previous one."""
        _check_callable(callback, "callback")
        self._rt.on_event(callback)

    @property
    def participant_id(self):
        return self._rt.participant_id

    @property
    def host_id(self):
        return self._rt.host_id

    def close(self):
        """Says goodbye to the other participants, stops every node, removes shared memory."""
        self._rt.close()


class Node(_Closing):
    """A named unit of a program; owns the executor that runs its subscribers' callbacks."""

    def __init__(self, impl):
        self._node = impl

    @property
    def name(self):
        return self._node.name

    def advertise(self, channel, msg_type, max_message_size=64 << 20, shm_slots=8, history=0):
        """A Publisher of lcm-gen type msg_type on channel. shm_slots: messages a subscriber
        of another process may lag by before it loses the oldest. history: keep last N, a
        subscriber that matches later gets the last `history` messages first, once (0: none)."""
        name, fingerprint = _type_info(msg_type)
        return Publisher(self._node.advertise_raw(channel, name, fingerprint, max_message_size,
                                                  shm_slots, history), msg_type)

    def advertise_raw(self, channel, max_message_size=64 << 20, shm_slots=8, history=0):
        """A Publisher of bytes (any bytes-like object) on channel; history as advertise()."""
        return Publisher(self._node.advertise_raw(channel, None, 0, max_message_size, shm_slots,
                                                  history), None)

    def subscribe(self, channel, msg_type, callback, queue_depth=16):
        """callback(msg) with each message decoded as msg_type (msg_type.decode)."""
        _check_callable(callback, "callback")
        name, fingerprint = _type_info(msg_type)
        return Subscriber(self._node.subscribe_raw(channel, callback, name, fingerprint,
                                                   msg_type.decode, queue_depth))

    def subscribe_raw(self, channel, callback, queue_depth=16):
        """callback(view): a read-only memoryview of the message, valid during the call."""
        _check_callable(callback, "callback")
        return Subscriber(self._node.subscribe_raw(channel, callback, None, 0, None, queue_depth))

    def create_service(self, name, req_type, resp_type, handler):
        """A server of service `name`: handler(request) -> response (lcm-gen objects), on this
        node's executor. The types' names and fingerprints are announced as a C++ typed
        service's are: a client of other types gets CallError("type_mismatch"), a request
        that does not decode "bad_request", and what the handler raises "handler_failed"."""
        _check_callable(handler, "handler")

        def raw(request):
            response = handler(request)
            if not isinstance(response, resp_type):
                raise TypeError("service '%s': the handler returned %s, not %s"
                                % (name, type(response).__name__, resp_type.__name__))
            return response.encode()
        return Service(self._node.create_service_raw(name, raw, _service_types(req_type, resp_type),
                                                     req_type.decode))

    def create_service_raw(self, name, handler):
        """handler(view: memoryview, valid during the call) -> bytes-like response. Matches
        clients of any type."""
        _check_callable(handler, "handler")
        return Service(self._node.create_service_raw(name, handler))

    def create_client(self, name, req_type, resp_type):
        """A Client of service `name`: call(request, timeout) -> response. Servers of other
        types answer CallError("type_mismatch")."""
        return Client(self._node.create_client_raw(name, _service_types(req_type, resp_type)),
                      req_type, resp_type)

    def create_client_raw(self, name):
        """A Client over bytes: call(bytes, timeout) -> bytes. Matches servers of any type."""
        return Client(self._node.create_client_raw(name), None, None)

    def create_action_server(self, name, goal_type, feedback_type, result_type, execute,
                             accept=None, max_goals=16, status_period=1.0, client_timeout=5.0,
                             result_retention=60.0):
        """An action server (C++ Node::create_action_server<G, F, R>, docs/actions.md).

        execute(goal: ActionGoal) runs on a thread of its own per accepted goal (the GIL taken
        for the call) and ends the goal with goal.succeed(result), goal.abort(result, message)
        or goal.canceled(result); if it returns without, the goal is aborted; what it raises
        aborts it with the text. accept(goal_msg) (None: accept all, up to max_goals at once)
        runs on this node's executor and returns True/False or a str ("" accepts, other text
        is the rejection's reason). Times in seconds. Closing the server (or the node or the
        runtime, or the interpreter's exit) cancels live goals and waits for their execute.
        The types are announced: clients of other types get CallError("type_mismatch")."""
        _check_callable(execute, "execute")
        if accept is not None:
            _check_callable(accept, "accept")
        types = _action_types(goal_type, feedback_type, result_type)

        def run(handle, goal):
            execute(ActionGoal(handle, goal, feedback_type, result_type))
        return ActionServer(self._node.create_action_server_raw(
            name, run, accept, types, goal_type.decode, max_goals, status_period, client_timeout,
            result_retention))

    def create_action_server_raw(self, name, execute, accept=None, max_goals=16,
                                 status_period=1.0, client_timeout=5.0, result_retention=60.0):
        """As create_action_server over bytes: goal.goal is bytes, feedback and results are
        bytes-like; accept(view) gets a memoryview valid during the call. Matches clients of
        any type."""
        _check_callable(execute, "execute")
        if accept is not None:
            _check_callable(accept, "accept")

        def run(handle, goal):
            execute(ActionGoal(handle, goal, None, None))
        return ActionServer(self._node.create_action_server_raw(
            name, run, accept, None, None, max_goals, status_period, client_timeout,
            result_retention))

    def create_action_client(self, name, goal_type, feedback_type, result_type):
        """An ActionClient of action `name` (C++ Node::create_action_client<G, F, R>)."""
        types = _action_types(goal_type, feedback_type, result_type)
        return ActionClient(self._node.create_action_client_raw(name, types), goal_type,
                            feedback_type, result_type)

    def create_action_client_raw(self, name):
        """An ActionClient over bytes; matches servers of any type."""
        return ActionClient(self._node.create_action_client_raw(name), None, None, None)

    def spin_once(self, timeout=None):
        """Manual nodes: waits up to timeout seconds (None: until a message) and runs the
        callbacks of what arrived; returns how many ran. Ctrl-C raises KeyboardInterrupt."""
        return self._node.spin_once(timeout)

    def spin(self):
        """Manual nodes: runs callbacks until Ctrl-C (KeyboardInterrupt) or close()."""
        while True:
            self._node.spin_once(None)

    def close(self):
        self._node.close()


class Publisher(_Closing):
    def __init__(self, impl, msg_type):
        self._pub = impl
        self._type = msg_type
        if msg_type is None:
            self.loan = impl.loan  # raw: straight to C++ (on the path of every loaned message)

    @property
    def channel(self):
        return self._pub.channel

    def publish(self, msg):
        """Typed: an instance of the advertised type. Raw: any bytes-like object."""
        self._pub.publish(_encode(msg, self._type, "publish on '%s'" % self.channel))

    def loan(self, size):
        """Raw publishers: a Loan of a shared-memory slot of size bytes to write in place
        (zero-copy publish, C++ RawPublisher::loan):

            with pub.loan(len(frame)) as buf:   # buf: a writable memoryview of the slot
                buf[:] = frame                   # or numpy.frombuffer(buf, ...) ... del array
            # published on leaving the block; dropped (nothing sent) if it raised

        A Loan has .view (that memoryview), .size, publish(size=None) (size: the bytes to send,
        at most the loan's) and drop(); both release the view first and raise lcmx.Error while
        a slice, cast or array of it is still alive (the slot is then reused). One loan per
        publisher at a time; publish() and loan() of the same publisher raise lcmx.Error on
        this thread while it is out."""
        if self._type is not None:
            raise TypeError("loan: only raw publishers (advertise_raw) loan slots")
        return self._pub.loan(size)

    def subscriber_count(self):
        return self._pub.subscriber_count()

    def wait_for_subscribers(self, n=1, timeout=10.0):
        """True once at least n subscribers are matched, False after timeout seconds."""
        return self._pub.wait_for_subscribers(n, timeout)

    def stats(self):
        return self._pub.stats()

    def close(self):
        self._pub.close()


class Subscriber(_Closing):
    def __init__(self, impl):
        self._sub = impl

    @property
    def channel(self):
        return self._sub.channel

    def publisher_count(self):
        return self._sub.publisher_count()

    def wait_for_publishers(self, n=1, timeout=10.0):
        """True once at least n publishers are matched, False after timeout seconds."""
        return self._sub.wait_for_publishers(n, timeout)

    def stats(self):
        """delivered, drops, decode_errors, callback_errors, errors (type mismatches...),
        publishers (per pair: participant, endpoint, path, received, drops)."""
        return self._sub.stats()

    def close(self):
        """Unsubscribes; waits for a running callback of it (unless called from inside it)."""
        self._sub.close()


class CallError(Error):
    """A failed service call: .code is one of timeout, no_server, server_gone, type_mismatch,
    handler_failed, bad_request, shutdown (C++ lcmx::CallErrc); str() is the message."""

    def __init__(self, code, message):
        super().__init__("%s: %s" % (code, message))
        self.code = code


def _call_error(code, message):
    return CallError(code.replace(" ", "_"), message)  # C++'s to_string has spaces


def _decode_reply(msg_type, data, what):
    """msg_type.decode(data); a payload that does not decode is C++'s type_mismatch."""
    try:
        return msg_type.decode(data)
    except Exception as e:  # lcm-gen raises ValueError, struct.error, ...
        raise CallError("type_mismatch", "the %s did not decode as %s: %s"
                        % (what, msg_type.__name__, e)) from None


class Service(_Closing):
    def __init__(self, impl):
        self._srv = impl

    @property
    def handler_errors(self):
        """Calls whose handler raised (each logged)."""
        return self._srv.handler_errors

    def close(self):
        self._srv.close()


class Client(_Closing):
    def __init__(self, impl, req_type, resp_type):
        self._cli = impl
        self._req = req_type
        self._resp = resp_type

    def wait_for_service(self, timeout=10.0):
        """True once a server answered a probe (both paths work), False after timeout s."""
        return self._cli.wait_for_service(timeout)

    def call(self, request, timeout=1.0):
        """The response, or raises CallError. Blocks up to timeout seconds (Ctrl-C raises)."""
        ok, data, code, message, _path = self._cli.call(_encode(request, self._req, "call"),
                                                        timeout)
        if not ok:
            raise _call_error(code, message)
        return data if self._resp is None else _decode_reply(self._resp, data, "response")

    def close(self):
        self._cli.close()


# ---- actions (C++ action.hpp, docs/actions.md) ----

GoalStatus = _collections.namedtuple("GoalStatus", "goal_id state message")
GoalStatus.__doc__ = """A goal's status: goal_id (32 hex digits), state (unknown, accepted,
executing, canceling, succeeded, aborted, canceled, rejected, or lost: the server went away
before the goal ended) and message (why it was rejected/aborted, who canceled it)."""

GoalOutcome = _collections.namedtuple("GoalOutcome", "status result")
GoalOutcome.__doc__ = """How a goal ended: its final GoalStatus, and the result execute gave
(None if it gave none, or it did not decode as the result type)."""

TERMINAL_STATES = frozenset(("succeeded", "aborted", "canceled", "rejected", "lost"))


class ActionGoal:
    """A goal on the server, given to execute(); valid until execute returns (then its
    methods raise lcmx.Error). Methods may be called from any thread."""

    def __init__(self, impl, goal, feedback_type, result_type):
        self._h = impl
        self._goal = goal
        self._feedback = feedback_type
        self._result = result_type

    @property
    def id(self):
        return self._h.id

    @property
    def goal(self):
        """The goal (an instance of the goal type; bytes for a raw server)."""
        return self._goal

    def cancel_requested(self):
        return self._h.cancel_requested()

    def wait_for_cancel(self, timeout=None):
        """Waits up to timeout seconds (None: until one comes) for a cancel request, without
        the GIL; True if one came. Use it instead of sleeping."""
        return self._h.wait_for_cancel(timeout)

    def publish_feedback(self, feedback):
        self._h.publish_feedback(_encode(feedback, self._feedback, "publish_feedback"))

    def _finish(self, state, result, message):
        data = b"" if result is None else _encode(result, self._result, state)
        self._h.finish(state, data, message)

    def succeed(self, result):
        self._finish("succeeded", result, "")

    def abort(self, result=None, message=""):
        self._finish("aborted", result, message)

    def canceled(self, result=None):
        """Acknowledges a cancel request: the goal ends canceled."""
        self._finish("canceled", result, "")

    def finished(self):
        return self._h.finished()


class ActionServer(_Closing):
    def __init__(self, impl):
        self._srv = impl

    @property
    def name(self):
        return self._srv.name

    @property
    def execute_errors(self):
        """Goals whose execute raised (each logged, the goal aborted)."""
        return self._srv.execute_errors

    def stats(self):
        """accepted, rejected, succeeded, aborted, canceled, cancel_requests,
        client_gone_cancels, executing."""
        return self._srv.stats()

    def goals(self):
        """GoalStatus of live goals, then of retained ended ones."""
        return [GoalStatus(*g) for g in self._srv.goals()]

    def close(self):
        """Cancels live goals and waits for their execute to return."""
        self._srv.close()


class ClientGoal:
    """A goal sent by an ActionClient (or named by id with client.goal(id))."""

    def __init__(self, impl, result_type):
        self._g = impl
        self._result = result_type

    @property
    def id(self):
        return self._g.id

    @property
    def accepted(self):
        """False for a goal the server rejected (message says why)."""
        return self._g.accepted

    @property
    def message(self):
        return self._g.message

    def status(self):
        """The last GoalStatus heard of this goal."""
        return GoalStatus(*self._g.status())

    def wait(self, timeout=None):
        """Waits for the goal's end (None: no limit; Ctrl-C raises KeyboardInterrupt) and
        returns a GoalOutcome; raises CallError (timeout: still live; no_server, server_gone).
        Every feedback of the goal was delivered before it returns (see docs/actions.md)."""
        r = self._g.wait(timeout)
        if not r[0]:
            raise _call_error(r[1], r[2])
        status, data = GoalStatus(*r[1]), r[2]
        result = data
        if data is not None and self._result is not None:
            try:
                result = self._result.decode(data)
            except Exception:  # as C++ GoalOutcome: no result when it does not decode
                result = None
        return GoalOutcome(status, result)

    def cancel(self, timeout=1.0):
        """Asks the server to cancel the goal; returns its GoalStatus then (canceling, or the
        end state if it had ended) or raises CallError."""
        r = self._g.cancel(timeout)
        if not r[0]:
            raise _call_error(r[1], r[2])
        return GoalStatus(*r[1])


class ActionClient(_Closing):
    def __init__(self, impl, goal_type, feedback_type, result_type):
        self._cli = impl
        self._goal = goal_type
        self._feedback = feedback_type
        self._result = result_type

    @property
    def name(self):
        return self._cli.name

    def wait_for_server(self, timeout=10.0):
        """True once a server answered (goal, cancel and result paths work), False after
        timeout seconds."""
        return self._cli.wait_for_server(timeout)

    def send_goal(self, goal, timeout=10.0, on_feedback=None):
        """Sends goal and blocks (without the GIL) until the server accepted or rejected it:
        returns a ClientGoal (check .accepted), or raises CallError (no_server, timeout,
        type_mismatch, bad_request). on_feedback(feedback) runs on the client's own thread
        for each feedback of this goal (keep it short; never call wait() from it)."""
        if on_feedback is not None:
            _check_callable(on_feedback, "on_feedback")
        decode = self._feedback.decode if self._feedback is not None else None
        r = self._cli.send_goal(_encode(goal, self._goal, "send_goal"), timeout, on_feedback,
                                decode)
        if not r[0]:
            raise _call_error(r[1], r[2])
        return ClientGoal(r[1], self._result)

    def goal(self, goal_id):
        """The goal goal_id (sent by any client) as a ClientGoal: wait(), cancel(), status()."""
        return ClientGoal(self._cli.goal(goal_id), self._result)

    def status(self, goal_id):
        return GoalStatus(*self._cli.status(goal_id))

    def cancel(self, goal_id, timeout=1.0):
        return self.goal(goal_id).cancel(timeout)

    def goals(self):
        """GoalStatus of the goals this client sent or heard of."""
        return [GoalStatus(*g) for g in self._cli.goals()]

    def close(self):
        """Stops the client; its goals go on at the server (canceled after its
        client_timeout)."""
        self._cli.close()


class LCM(_Closing):
    """Drop-in for LCM's Python ``lcm.LCM``: publish(channel, data), subscribe(channel_regex,
    handler) -> subscription, unsubscribe(subscription), handle(), handle_timeout(ms),
    fileno(). Handlers run inside handle()/handle_timeout() on the caller's thread, as handler(
    channel, data: bytes).

    url: LCM's provider URL (``udpm://239.255.76.67:7667?ttl=0``) becomes the host-local
    group; small messages are also sent there (mirror), so stock LCM programs hear them. With
    no url (and LCM_DEFAULT_URL unset) the process's lcmx.Runtime is shared if one is open.
    """

    def __init__(self, url=None):
        import os
        if url is None:
            url = os.environ.get("LCM_DEFAULT_URL") or None
        rt = _lcmx._current_runtime() if url is None else None
        self._own = rt is None
        if rt is None:
            rt = _lcmx._Runtime(url, None, True, None, None)
        self._rt = rt
        self._lcm = _lcmx._LCM(rt)

    def publish(self, channel, data):
        self._lcm.publish(channel, data)

    def subscribe(self, channel, handler):
        """channel: a regular expression matched against the whole channel name."""
        return self._lcm.subscribe(channel, handler)

    def unsubscribe(self, subscription):
        self._lcm.unsubscribe(subscription)

    def handle(self):
        """Waits for one message and calls its handler. Returns 0."""
        self._lcm.handle(None)
        return 0

    def handle_timeout(self, timeout_millis):
        """Handles one message if one comes within timeout_millis: returns 1, else 0."""
        if timeout_millis < 0:
            raise ValueError("invalid timeout")
        return 1 if self._lcm.handle(timeout_millis / 1000.0) else 0

    def fileno(self):
        """A file descriptor readable while a message waits for handle() (select/poll)."""
        return self._lcm.fileno()

    def close(self):
        self._lcm.close()
        if self._own:
            self._rt.close()


# Before the interpreter finalises: close every handle (callbacks in flight finish, executor
# threads stop), so no lcmx thread touches Python afterwards.
_atexit.register(_lcmx._close_all)
