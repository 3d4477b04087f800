"""The live view in a process of its own, so that it never costs the loop.

The loop's thread only copies each message into a shared-memory ring
(:class:`Ring`: a few hundred nanoseconds, no lock, no wait, no
allocation). A viewer process, at a lower priority (nice 10), reads the
ring every 2 ms and hands the messages to the Foxglove server
(:class:`~has_control.nodes.foxglove.LiveView`) there. A viewer that falls
behind by more than the ring (:data:`SLOTS` messages, about 0.5 s of a run
at 0.3 ms) loses the oldest; the loop never waits for it, never shares a
GIL with it, and the server's threads are the viewer's.

Run as ``python -m has_control.nodes.live_process RING_FD BIG_FD PORT HOST NAME WHAT``
by :class:`LiveViewProcess` (the rings' file descriptors are inherited: memfd,
no name in /dev/shm); it answers on stdout (``ok PORT`` or ``error LINE``)
and takes commands on stdin: ``topic ID NAME`` (answered ``channel ID`` once
the channel exists), ``wait SECONDS`` (answered ``subscribed`` or
``timeout``), ``close``.
"""
from __future__ import annotations

import mmap
import os
import select
import signal
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
#: A second ring for the few messages longer than a slot (/diagnostics: about 1 kB, once a second).
BIG_SLOTS, BIG_SLOT = 64, 8192
HEADER = 64                      # the count of messages written (u64), then spare
_HEAD = struct.Struct("<Q")
_SLOT_HEAD = struct.Struct("<QHH")
START_TIMEOUT = 60.0             # [s] for the viewer process to serve (imports included)
WAIT_MAX = 3600.0                # [s] the longest wait for a client
LINGER = 0.2                     # [s] served after the run's last message, before a subscribed client is cut off


def _anonymous_file(size: int) -> int:
    """A file descriptor of ``size`` zero bytes that no name leads to (memfd; else an
    unlinked temporary file): nothing is left in /dev/shm, whatever ends the process."""
    if hasattr(os, "memfd_create"):
        fd = os.memfd_create("has_control_live", os.MFD_CLOEXEC)
    else:
        shm = Path("/dev/shm") if Path("/dev/shm").is_dir() else Path(tempfile.gettempdir())
        fd, path = tempfile.mkstemp(prefix="has_control_live_", dir=shm)
        os.unlink(path)
    os.ftruncate(fd, size)
    return fd


class Ring:
    """A single-writer ring of messages in shared memory (the file descriptor ``fd``,
    mapped by the writer and by the viewer process, which inherits it)."""

    def __init__(self, fd: int, slots: int = SLOTS, slot: int = SLOT):
        self.fd, self.slots, self.slot = fd, slots, slot
        self.buf = mmap.mmap(fd, HEADER + slots * slot)
        self._count = [0]                                  # messages written (the writer's side)

    @classmethod
    def create(cls, slots: int = SLOTS, slot: int = SLOT) -> "Ring":
        return cls(_anonymous_file(HEADER + slots * slot), slots, slot)

    def writer(self, topic_id: int) -> Callable[[bytes], None]:
        """A function that copies one message of ``topic_id`` into the next slot (too long: dropped)."""
        buf, head, slot_head = self.buf, _HEAD.pack_into, _SLOT_HEAD.pack_into
        count, slots, slot = self._count, self.slots, self.slot

        def write(data: bytes) -> None:
            n = len(data)
            if n > slot - 16:
                return
            i = count[0]
            off = HEADER + (i % slots) * slot
            slot_head(buf, off, 0, topic_id, n)            # sequence 0: being written
            buf[off + 16:off + 16 + n] = data
            head(buf, off, i + 1)                          # the slot holds message i (1-based)
            count[0] = i + 1
            head(buf, 0, i + 1)
        return write

    def read(self, start: int, take) -> int:
        """Hand messages ``start``.. to ``take(topic_id, bytes)``; the next index to read.
        Messages overwritten before they are read are skipped."""
        buf, slots, slot = self.buf, self.slots, self.slot
        written = _HEAD.unpack_from(buf, 0)[0]
        i = max(start, written - slots + 1)
        while i < written:
            off = HEADER + (i % slots) * slot
            seq, topic_id, n = _SLOT_HEAD.unpack_from(buf, off)
            if seq == i + 1:
                data = bytes(buf[off + 16:off + 16 + n])
                if _HEAD.unpack_from(buf, off)[0] == i + 1:      # not overwritten while copied
                    take(topic_id, data)
            i += 1
        return i

    def close(self) -> None:
        self.buf.close()
        try:
            os.close(self.fd)
        except OSError:
            pass


class LiveViewProcess:
    """:class:`~has_control.nodes.foxglove.LiveView`'s interface (``sink``, ``port``,
    ``channels``, ``close``) with the server in a viewer process fed through a :class:`Ring`.

    The viewer failing (killed, crashed) never costs the run: the loop keeps
    copying into the ring, :meth:`close` reports it in one line (``ended``) and
    leaves nothing behind. The rings have no name in the file system, so a
    SIGKILLed run leaves no shared memory; the viewer runs in a session of its
    own (Ctrl-C at the terminal reaches the run, which closes it) and ends when
    its parent's pipe closes."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1", name: str = "has_control",
                 what: str = "--foxglove", warn: Callable[[str], None] | None = None):
        if port != 0:
            check_port(port, what)
        self._warn = warn or _warn
        self.ring, self.big = Ring.create(), Ring.create(BIG_SLOTS, BIG_SLOT)
        self.channels: dict[str, int] = {}
        self.ended: str | None = None            # why the viewer ended before close, if it did
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "has_control.nodes.live_process", str(self.ring.fd), str(self.big.fd),
             str(port), host, name, what],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
            pass_fds=(self.ring.fd, self.big.fd), start_new_session=True)
        answer = self._answer(START_TIMEOUT)
        if not answer.startswith("ok "):
            self.close()
            raise HasControlError(answer.removeprefix("error ") or f"{what} {port}: the live view did not start")
        self.port = int(answer.split()[1])

    def _answer(self, timeout: float) -> str:
        try:
            ready, _, _ = select.select([self._proc.stdout], [], [], timeout)
            return self._proc.stdout.readline().strip() if ready else ""
        except (OSError, ValueError):
            return ""

    def _send(self, line: str) -> None:
        try:
            self._proc.stdin.write(line + "\n")
            self._proc.stdin.flush()
        except (BrokenPipeError, ValueError, OSError):
            pass

    def sink(self, topic: str) -> Callable[[bytes], None]:
        """The tap for ``topic`` (its full name): copies each message into the ring
        (one longer than a slot into the ring of long messages)."""
        if topic.rsplit("/", 1)[-1] not in _TYPES:
            raise HasControlError(f"live view: {topic}: not a run topic ({', '.join(RUN_TOPICS)})")
        if topic not in self.channels:
            self.channels[topic] = len(self.channels)
            self._send(f"topic {self.channels[topic]} {topic}")
            if self._answer(10.0) != f"channel {self.channels[topic]}":
                raise HasControlError(f"live view: {topic}: the viewer process did not open the channel")
        short, long = self.ring.writer(self.channels[topic]), self.big.writer(self.channels[topic])
        limit = SLOT - 16

        def write(data: bytes) -> None:
            (short if len(data) <= limit else long)(data)
        return write

    def wait_for_client(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s (0..:data:`WAIT_MAX`) for a client to subscribe to a channel; whether one did."""
        if not (isinstance(timeout, (int, float)) and 0.0 <= timeout <= WAIT_MAX):
            raise HasControlError(f"live view: wait {timeout!r}: expected 0 .. {WAIT_MAX:g} s")
        self._send(f"wait {timeout}")
        return self._answer(timeout + 10.0) == "subscribed"

    def close(self) -> None:
        """Stop the viewer (clients are disconnected) and release the rings; again: no-op.
        A viewer that ended before is noted in :attr:`ended`, never raised."""
        if self._proc is None:
            return
        died = self._proc.poll()
        self._send("close")
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        for f in (self._proc.stdin, self._proc.stdout):
            try:
                f.close()
            except OSError:                       # what was left to write to a viewer that is gone
                pass
        if died is not None:
            how = f"signal {-died}" if died < 0 else f"status {died}"
            self.ended = f"the live view's viewer process ended early ({how}); the run went on without it"
            self._warn(self.ended)
        self._proc = None
        self.ring.close()
        self.big.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _warn(text: str) -> None:
    print(f"live view: {text}", file=sys.stderr, flush=True)


def _viewer(ring_fd: int, big_fd: int, port: int, host: str, name: str, what: str) -> None:
    """The viewer process: serve, then move the rings' messages to the server until
    ``close`` or the end of its input (the parent gone). Ctrl-C is the parent's to
    handle (ignored here); SIGTERM ends it quietly."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)      # the parent gone: end, no BrokenPipeError
    try:
        os.nice(10)                           # below the loop, always
    except OSError:
        pass
    try:
        view = LiveView(port, host=host, name=name, what=what)
    except HasControlError as exc:
        print(f"error {exc}", flush=True)
        return
    rings = (Ring(ring_fd), Ring(big_fd, BIG_SLOTS, BIG_SLOT))
    print(f"ok {view.port}", flush=True)
    takes: dict[int, Callable[[bytes], None]] = {}

    def take(topic_id: int, data: bytes) -> None:
        f = takes.get(topic_id)
        if f is not None:
            f(data)
    next_read, waiting = [0, 0], None
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
                waiting = time.monotonic() + min(max(float(rest), 0.0), WAIT_MAX)
            elif cmd == "close":                         # what the run wrote before it closed is served first
                for k, r in enumerate(rings):
                    next_read[k] = r.read(next_read[k], take)
                if view.subscribed.is_set():
                    time.sleep(LINGER)
                view.close()
                for r in rings:
                    r.close()
                return
        if waiting is not None and (view.subscribed.is_set() or time.monotonic() > waiting):
            print("subscribed" if view.subscribed.is_set() else "timeout", flush=True)
            waiting = None
        for k, r in enumerate(rings):
            next_read[k] = r.read(next_read[k], take)
        view.relatch()                                         # a new client gets the gains in force


if __name__ == "__main__":
    _viewer(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5], sys.argv[6])
