"""A bag written by a process of its own, so that recording does not hold the
recording process's GIL.

The recorder of a lock-step loop runs in a Python thread that is busy all the
time; a writer thread beside it (building MCAP records with NumPy) would take
the GIL from it for several microseconds per sample. :class:`BagProcess` forks
a child that owns the :class:`~has_control.bag.write.BagWriter`; the parent
hands it batches of messages as bytes through a pipe (a copy, in C) and
keeps running. The child ignores SIGINT and SIGTERM, so Ctrl-C ends the run
in the parent, which then closes the bag; if the parent dies, the child
closes the bag on end-of-file. Errors come back at :meth:`close`, one line
naming the bag.
"""
from __future__ import annotations

import gc
import multiprocessing
import signal
from pathlib import Path

from has_control.bag.base import BagError
from has_control.bag.write import BagWriter, QosSpec, as_batch


class BagProcess:
    """The part of :class:`BagWriter` a recorder uses, in a forked process."""

    def __init__(self, path: str | Path, custom_data: dict[str, str] | None = None):
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path}: exists already; a bag is never overwritten")
        ctx = multiprocessing.get_context("fork")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, self._conn, self.path, custom_data or {}),
                                 name="bag-writer", daemon=True)
        self._proc.start()
        child.close()
        self._reply()                                # the writer is open (or why not)

    def add_topic(self, topic: str, msgtype: str, qos: QosSpec = QosSpec()) -> None:
        self._conn.send(("topic", topic, msgtype, qos))

    def write_messages(self, batch: dict[str, tuple[str, list[bytes]]]) -> None:
        """Messages of several topics: ``{topic: (message type, [CDR bytes, ...])}``."""
        self._conn.send(("batch", batch))

    def close(self) -> Path:
        """Write what is left, close the bag; its path."""
        if self._proc is None:
            return self.path
        try:
            self._conn.send(("close",))
            self._reply()
        finally:
            self._conn.close()
            self._proc.join(timeout=60)
            self._proc = None
        return self.path

    def _reply(self) -> None:
        try:
            kind, text = self._conn.recv()
        except EOFError:
            raise BagError(f"{self.path}: the bag writer process ended unexpectedly") from None
        if kind == "error":
            raise BagError(text)


def _serve(conn, parents_end, path: Path, custom_data: dict[str, str]) -> None:
    """The child: open the bag, write what arrives, close on request or end-of-file."""
    parents_end.close()                              # so that the parent's death is our end-of-file
    gc.freeze()             # the parent's objects are not ours to collect: finalising its garbage here
    #                         (an rclpy node, a DDS handle) runs its C++ destructors in a fork: a crash
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        writer = BagWriter(path, custom_data)
    except Exception as exc:                         # noqa: BLE001 - reported to the parent, one line
        conn.send(("error", str(exc)))
        return
    conn.send(("ok", ""))
    failed = None
    while True:
        try:
            msg = conn.recv()
        except EOFError:                             # the parent is gone: keep what we have
            msg = ("close",)
        try:
            if msg[0] == "topic":
                writer.add_topic(*msg[1:])
            elif msg[0] == "batch" and failed is None:
                writer.write_batches({t: as_batch(ty, msgs) for t, (ty, msgs) in msg[1].items()})
            elif msg[0] == "close":
                writer.close()
        except (BagError, OSError) as exc:
            failed = failed or (str(exc) if isinstance(exc, BagError)
                                else f"{getattr(exc, 'filename', None) or path}: {exc.strerror or exc}")
        if msg[0] == "close":
            try:
                conn.send(("error", failed) if failed else ("ok", ""))
            except OSError:                          # nobody left to tell
                pass
            return
