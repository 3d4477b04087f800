"""The live view in a process of its own, so that it never costs the loop.

The loop's thread only copies each message into a shared-memory ring
(:class:`Ring`: a few hundred nanoseconds, no lock, no wait, no
allocation). A viewer process, at a lower priority (nice 10), reads the
ring every 2 ms and hands the messages to the Foxglove server
(:class:`~has_control.nodes.foxglove.LiveView`) there. A viewer that falls
behind by more than the ring (:data:`SLOTS` messages, about 0.5 s of a run
at 0.3 ms) loses the oldest; the loop never waits for it, never shares a
GIL with it, and the server's threads are the viewer's.

Run as ``python -m has_control.nodes.live_process RING PORT HOST NAME WHAT``
by :class:`LiveViewProcess`; it answers on stdout (``ok PORT`` or ``error
LINE``) and takes commands on stdin: ``topic ID NAME`` (answered ``channel
ID`` once the channel exists), ``wait SECONDS`` (answered ``subscribed`` or
``timeout``), ``close``.
"""
from __future__ import annotations

import mmap
import os
import select
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from has_control.common.errors import HasControlError
from has_control.nodes.foxglove import _TYPES, DEFAULT_PORT, LiveView, check_port
from has_control.wire.topics import RUN_TOPICS

SLOTS = 8192                     # messages the ring holds
SLOT = 512                       # bytes per message slot: sequence u64, topic u16, length u16, 4 spare, data
HEADER = 64                      # the count of messages written (u64), then spare
_HEAD = struct.Struct("<Q")
_SLOT_HEAD = struct.Struct("<QHH")
START_TIMEOUT = 60.0             # [s] for the viewer process to serve (imports included)


class Ring:
    """A single-writer ring of messages in a memory-mapped file (one per view)."""

    def __init__(self, path: Path, create: bool):
        self.path = path
        size = HEADER + SLOTS * SLOT
        if create:
            with open(path, "wb") as f:
                f.truncate(size)
        self._file = open(path, "r+b")
        self.buf = mmap.mmap(self._file.fileno(), size)
        self._count = [0]                                  # messages written (the writer's side)

    def writer(self, topic_id: int) -> Callable[[bytes], None]:
        """A function that copies one message of ``topic_id`` into the next slot (too long: dropped)."""
        buf, head, slot_head = self.buf, _HEAD.pack_into, _SLOT_HEAD.pack_into
        count = self._count

        def write(data: bytes) -> None:
            n = len(data)
            if n > SLOT - 16:
                return
            i = count[0]
            off = HEADER + (i % SLOTS) * SLOT
            slot_head(buf, off, 0, topic_id, n)            # sequence 0: being written
            buf[off + 16:off + 16 + n] = data
            head(buf, off, i + 1)                          # the slot holds message i (1-based)
            count[0] = i + 1
            head(buf, 0, i + 1)
        return write

    def read(self, start: int, take) -> int:
        """Hand messages ``start``.. to ``take(topic_id, bytes)``; the next index to read.
        Messages overwritten before they are read are skipped."""
        buf = self.buf
        written = _HEAD.unpack_from(buf, 0)[0]
        i = max(start, written - SLOTS + 1)
        while i < written:
            off = HEADER + (i % SLOTS) * SLOT
            seq, topic_id, n = _SLOT_HEAD.unpack_from(buf, off)
            if seq == i + 1:
                data = bytes(buf[off + 16:off + 16 + n])
                if _HEAD.unpack_from(buf, off)[0] == i + 1:      # not overwritten while copied
                    take(topic_id, data)
            i += 1
        return i

    def close(self, unlink: bool = False) -> None:
        self.buf.close()
        self._file.close()
        if unlink:
            self.path.unlink(missing_ok=True)


class LiveViewProcess:
    """:class:`~has_control.nodes.foxglove.LiveView`'s interface (``sink``, ``port``,
    ``channels``, ``close``) with the server in a viewer process fed through a :class:`Ring`."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1", name: str = "has_control",
                 what: str = "--foxglove"):
        if port != 0:
            check_port(port, what)
        shm = Path("/dev/shm") if Path("/dev/shm").is_dir() else Path(tempfile.gettempdir())
        fd, path = tempfile.mkstemp(prefix="has_control_live_", dir=shm)
        os.close(fd)
        self.ring = Ring(Path(path), create=True)
        self.channels: dict[str, int] = {}
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "has_control.nodes.live_process", path, str(port), host, name, what],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
        answer = self._answer(START_TIMEOUT)
        if not answer.startswith("ok "):
            self.close()
            raise HasControlError(answer.removeprefix("error ") or f"{what} {port}: the live view did not start")
        self.port = int(answer.split()[1])

    def _answer(self, timeout: float) -> str:
        ready, _, _ = select.select([self._proc.stdout], [], [], timeout)
        return self._proc.stdout.readline().strip() if ready else ""

    def _send(self, line: str) -> None:
        try:
            self._proc.stdin.write(line + "\n")
            self._proc.stdin.flush()
        except (BrokenPipeError, ValueError, OSError):
            pass

    def sink(self, topic: str) -> Callable[[bytes], None]:
        """The tap for ``topic`` (its full name): copies each message into the ring."""
        if topic.rsplit("/", 1)[-1] not in _TYPES:
            raise HasControlError(f"live view: {topic}: not a run topic ({', '.join(RUN_TOPICS)})")
        if topic not in self.channels:
            self.channels[topic] = len(self.channels)
            self._send(f"topic {self.channels[topic]} {topic}")
            if self._answer(10.0) != f"channel {self.channels[topic]}":
                raise HasControlError(f"live view: {topic}: the viewer process did not open the channel")
        return self.ring.writer(self.channels[topic])

    def wait_for_client(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for a client to subscribe to a channel; whether one did."""
        self._send(f"wait {timeout}")
        return self._answer(timeout + 10.0) == "subscribed"

    def close(self) -> None:
        """Stop the viewer (clients are disconnected) and remove the ring; again: no-op."""
        if self._proc is None:
            return
        self._send("close")
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        for f in (self._proc.stdin, self._proc.stdout):
            f.close()
        self._proc = None
        self.ring.close(unlink=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _viewer(path: str, port: int, host: str, name: str, what: str) -> None:
    """The viewer process: serve, then move the ring's messages to the server until ``close``."""
    try:
        os.nice(10)                           # below the loop, always
    except OSError:
        pass
    try:
        view = LiveView(port, host=host, name=name, what=what)
    except HasControlError as exc:
        print(f"error {exc}", flush=True)
        return
    ring = Ring(Path(path), create=False)
    print(f"ok {view.port}", flush=True)
    takes: dict[int, Callable[[bytes], None]] = {}

    def take(topic_id: int, data: bytes) -> None:
        f = takes.get(topic_id)
        if f is not None:
            f(data)
    i, waiting = 0, None
    while True:
        ready, _, _ = select.select([sys.stdin], [], [], 0.002)       # commands, or a 2 ms pause
        if ready:
            line = sys.stdin.readline()
            cmd, _, rest = (line.strip() or "close").partition(" ")     # end of input: the parent is gone
            if cmd == "topic":
                tid, topic = rest.split(" ", 1)
                takes[int(tid)] = view.sink(topic)
                print(f"channel {tid}", flush=True)          # the channel exists before the sink is used
            elif cmd == "wait":
                waiting = time.monotonic() + float(rest)
            elif cmd == "close":
                view.close()
                ring.close()
                return
        if waiting is not None and (view.subscribed.is_set() or time.monotonic() > waiting):
            print("subscribed" if view.subscribed.is_set() else "timeout", flush=True)
            waiting = None
        i = ring.read(i, take)


if __name__ == "__main__":
    _viewer(sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4], sys.argv[5])
