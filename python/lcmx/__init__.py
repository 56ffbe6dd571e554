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
import struct as _struct

from . import _lcmx
from ._lcmx import Error, LCMSubscription

__all__ = ["Runtime", "Node", "Publisher", "Subscriber", "Service", "Client", "CallError", "LCM",
           "LCMSubscription", "Error"]


def _type_info(msg_type):
    """(name, fingerprint) of an lcm-gen --python class, as C++'s getTypeName()/getHash()."""
    try:
        packed = msg_type._get_packed_fingerprint()
    except AttributeError:
        raise TypeError(f"{msg_type!r} is not an lcm-gen Python type") from None
    return msg_type.__name__, _struct.unpack(">q", packed)[0]


class Runtime:
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

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class Node:
    """A named unit of a program; owns the executor that runs its subscribers' callbacks."""

    def __init__(self, impl):
        self._node = impl

    @property
    def name(self):
        return self._node.name

    def advertise(self, channel, msg_type, max_message_size=64 << 20, shm_slots=8):
        """A Publisher of lcm-gen type msg_type on channel. shm_slots: messages a subscriber
        of another process may lag by before it loses the oldest."""
        name, fingerprint = _type_info(msg_type)
        return Publisher(self._node.advertise_raw(channel, name, fingerprint, max_message_size,
                                                  shm_slots), msg_type)

    def advertise_raw(self, channel, max_message_size=64 << 20, shm_slots=8):
        """A Publisher of bytes (any bytes-like object) on channel."""
        return Publisher(self._node.advertise_raw(channel, None, 0, max_message_size, shm_slots),
                         None)

    def subscribe(self, channel, msg_type, callback, queue_depth=16):
        """callback(msg) with each message decoded as msg_type (msg_type.decode)."""
        name, fingerprint = _type_info(msg_type)
        return Subscriber(self._node.subscribe_raw(channel, callback, name, fingerprint,
                                                   msg_type.decode, queue_depth))

    def subscribe_raw(self, channel, callback, queue_depth=16):
        """callback(view): a read-only memoryview of the message, valid during the call."""
        return Subscriber(self._node.subscribe_raw(channel, callback, None, 0, None, queue_depth))

    def create_service(self, name, req_type, resp_type, handler):
        """A server of service `name`: handler(request) -> response (lcm-gen objects), on this
        node's executor. What it raises reaches the client as CallError("handler_failed").
        Over raw bytes on the wire: clients of any type find it (see Limits in README)."""
        def raw(view):
            response = handler(req_type.decode(view))
            if not isinstance(response, resp_type):
                raise TypeError("service '%s': the handler returned %s, not %s"
                                % (name, type(response).__name__, resp_type.__name__))
            return response.encode()
        return Service(self._node.create_service_raw(name, raw))

    def create_service_raw(self, name, handler):
        """handler(view: memoryview, valid during the call) -> bytes-like response."""
        return Service(self._node.create_service_raw(name, handler))

    def create_client(self, name, req_type, resp_type):
        """A Client of service `name`: call(request, timeout) -> response."""
        return Client(self._node.create_client_raw(name), req_type, resp_type)

    def create_client_raw(self, name):
        """A Client over bytes: call(bytes, timeout) -> bytes. Matches servers of any type."""
        return Client(self._node.create_client_raw(name), None, None)

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

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class Publisher:
    def __init__(self, impl, msg_type):
        self._pub = impl
        self._type = msg_type

    @property
    def channel(self):
        return self._pub.channel

    def publish(self, msg):
        """Typed: an instance of the advertised type. Raw: any bytes-like object."""
        if self._type is None:
            self._pub.publish(msg)
            return
        if not isinstance(msg, self._type):
            raise TypeError(f"publish on '{self.channel}': expected {self._type.__name__}, "
                            f"got {type(msg).__name__}")
        self._pub.publish(msg.encode())

    def subscriber_count(self):
        return self._pub.subscriber_count()

    def wait_for_subscribers(self, n=1, timeout=10.0):
        """True once at least n subscribers are matched, False after timeout seconds."""
        return self._pub.wait_for_subscribers(n, timeout)

    def stats(self):
        return self._pub.stats()

    def close(self):
        self._pub.close()


class Subscriber:
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


class Service:
    def __init__(self, impl):
        self._srv = impl

    @property
    def handler_errors(self):
        """Calls whose handler raised (each logged)."""
        return self._srv.handler_errors

    def close(self):
        self._srv.close()


class Client:
    def __init__(self, impl, req_type, resp_type):
        self._cli = impl
        self._req = req_type
        self._resp = resp_type

    def wait_for_service(self, timeout=10.0):
        """True once a server answered a probe (both paths work), False after timeout s."""
        return self._cli.wait_for_service(timeout)

    def call(self, request, timeout=1.0):
        """The response, or raises CallError. Blocks up to timeout seconds (Ctrl-C raises)."""
        if self._req is not None:
            if not isinstance(request, self._req):
                raise TypeError("call: expected %s, got %s"
                                % (self._req.__name__, type(request).__name__))
            request = request.encode()
        ok, data, code, message, _path = self._cli.call(request, timeout)
        if not ok:
            raise CallError(code.replace(" ", "_"), message)  # C++'s to_string has spaces
        return data if self._resp is None else self._resp.decode(data)

    def close(self):
        self._cli.close()


class LCM:
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

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


# Before the interpreter finalises: close every handle (callbacks in flight finish, executor
# threads stop), so no lcmx thread touches Python afterwards.
_atexit.register(_lcmx._close_all)
