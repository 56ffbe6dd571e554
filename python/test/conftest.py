"""Shared fixtures of the Python tests (run by CTest: python/test/CMakeLists.txt).

Each test gets a discovery group of its own on loopback (as test/core/core_support.hpp's
test_options()): LCMX_DISCOVERY_URL is set for this process and inherited by the peers it
starts, with short beacons and lease.
"""
import os
import queue
import struct
import subprocess
import sys
import threading
import time

import pytest

_counter = [0]


def unique_url():
    ident = os.getpid() * 8 + _counter[0]
    _counter[0] += 1
    return "udpm://239.254.%d.%d:%d?ttl=0&iface=lo" % ((ident >> 8) & 0xFF, ident & 0xFF,
                                                       20000 + ident % 40000)


@pytest.fixture
def lcmx_env(monkeypatch):
    url = unique_url()
    monkeypatch.setenv("LCMX_DISCOVERY_URL", url)
    monkeypatch.setenv("LCMX_BEACON_PERIOD_MS", "100")
    monkeypatch.setenv("LCMX_LEASE_MS", "600")
    return url


def wait_for(predicate, timeout=10.0, poll=0.005):
    """Waits until predicate() is true (False after timeout seconds). For state kept by
    threads we do not own (counters); prefer threading.Event where we can set one."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll)
    return True


class Proc:
    """A child process whose stdout lines are read on a thread; expect() waits for a line."""

    def __init__(self, args, **kw):
        self.p = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, bufsize=1, **kw)
        self.lines = queue.Queue()
        self.seen = []
        self.t = threading.Thread(target=self._read, daemon=True)
        self.t.start()

    def _read(self):
        for line in self.p.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def expect(self, prefix, timeout=20.0):
        """The first line starting with prefix; fails the test after timeout seconds."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                pytest.fail("no line %r within %.0f s; saw %r" % (prefix, timeout, self.seen[-20:]))
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                continue
            if line is None:
                pytest.fail("process ended without %r; saw %r" % (prefix, self.seen[-20:]))
            self.seen.append(line)
            if line.startswith(prefix):
                return line

    def send(self, text):
        self.p.stdin.write(text + "\n")
        self.p.stdin.flush()

    def wait(self, timeout=20.0):
        return self.p.wait(timeout=timeout)

    def close(self):
        """Stops it as its user would, so that it removes its registry slot and segments:
        stdin closed and 0.1 s, then SIGTERM and 1 s, then SIGKILL."""
        steps = [(None, 0.1), (self.p.terminate, 1.0), (self.p.kill, None)]
        try:
            self.p.stdin.close()
        except OSError:
            pass
        for act, timeout in steps:
            if self.p.poll() is not None:
                return
            if act is not None:
                act()
            try:
                self.p.wait(timeout=timeout)
                return
            except subprocess.TimeoutExpired:
                pass


@pytest.fixture
def procs():
    started = []

    def start(args, **kw):
        p = Proc(args, **kw)
        started.append(p)
        return p

    def close_all(keep=()):
        """Stops every process started so far but those in keep (a fixture that tears down
        what they run in, before this fixture's own end)."""
        for p in started:
            if p not in keep:
                p.close()

    start.close_all = close_all
    yield start
    for p in started:
        p.close()


def python_script(code):
    """argv for a child Debian python3 (this interpreter) running code."""
    return [sys.executable, "-c", code]


def summary(line):
    """The key=value fields of a peer's report line ("SUMMARY channel=X received=20 ...")."""
    return dict(kv.split("=", 1) for kv in line.split()[1:])


def pattern(seq, n):
    """The C++ peers' content: byte i of message seq is (i * 131 + seq * 7) & 0xFF."""
    block = bytes(((i * 131 + seq * 7) & 0xFF) for i in range(256))
    return (block * (n // 256 + 1))[:n]


def image_fields(view):
    """(seq, width, height, data) of an lcmx_examples.image_t encoding; data is a slice of
    view (no copy). Fields: fingerprint, header (seq, stamp, frame_id), width, height, stride,
    encoding, size, data."""
    off = 8
    seq = struct.unpack_from(">q", view, off)[0]
    off += 16
    off += 4 + struct.unpack_from(">i", view, off)[0]
    w, h, _stride = struct.unpack_from(">iii", view, off)
    off += 12
    off += 4 + struct.unpack_from(">i", view, off)[0]
    size = struct.unpack_from(">i", view, off)[0]
    off += 4
    if size != len(view) - off:
        raise ValueError("image_t: size %d but %d bytes follow" % (size, len(view) - off))
    return seq, w, h, view[off:off + size]
