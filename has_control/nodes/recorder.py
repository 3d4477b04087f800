"""Record a run's topics to a rosbag2 MCAP bag from the CDR bytes already in hand.

A :class:`Recorder` takes messages as serialized bytes, never re-encoding
them, from two intakes:

* raw subscriptions (``raw=True``: no deserialisation) on a node, for one
  namespace: the generic path, for a graph anywhere on the ROS network (the
  tuner's lanes);
* :meth:`Recorder.sink`, a tap the nodes composed in this process call
  with the bytes they publish (``has-control stack --record``): no executor
  event, callback or lock per message, a list append.

Messages are kept per topic and handed over in batches of :data:`BATCH`
samples: to a process of its own that writes the bag
(:class:`~has_control.bag.process.BagProcess`, ``process=True``, what
``stack`` uses) or to a writer thread (:meth:`BagWriter.write_batches`; the
tuner, whose episodes share its session bag), so the loop pays a list append
per message. Log time is
simulation time: the header stamp of JointState and Clock, and the leading t
of our Float64MultiArray topics. A lock-step bag holds exactly one state and
one command per sample. :meth:`open` / :meth:`close` let a tuner record
episode after episode on the same subscriptions.
"""
from __future__ import annotations

import math
import struct
import threading
from typing import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from has_control.bag import PARAMETERS_KEY, BagWriter, QosSpec, as_batch, parameters_json
from has_control.bag.process import BagProcess
from has_control.nodes.runtime import normalise_namespace
from has_control.wire.topics import (CLOCK, COMMAND, FLOAT64_ARRAY, GAINS, JOINT_STATE, QOS, RUN_TOPICS, STATE,
                                     STATE_LAYOUT)

_CLASSES = {JOINT_STATE: JointState, CLOCK: Clock, FLOAT64_ARRAY: Float64MultiArray}

#: What the publishers offer (stored in the bag as rosbag2 does).
OFFERED = {rel: QosSpec(depth=depth, transient_local=latched) for rel, (depth, latched) in QOS.items()}

#: Messages of the state topic between two hand-overs to the writer.
BATCH = 4096

_Y = int(STATE_LAYOUT.values[0])          # byte offset of position[0] = y in a state message


def _subscription_qos(transient_local: bool) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local
                      else DurabilityPolicy.VOLATILE)


def topic_name(namespace: str, relative: str) -> str:
    """The absolute name of run topic ``relative`` in ``namespace`` (``sim0`` and ``/sim0/`` are ``/sim0``)."""
    return f"{normalise_namespace(namespace)}/{relative}"


class Recorder:
    """Records the run topics of ``namespace``; subscribes on ``node`` unless ``subscribe`` is False."""

    def __init__(self, node=None, namespace: str = "", topics: dict[str, str] | None = None,
                 y_limit: float = math.inf, subscribe: bool = True, process: bool = False, keep=()):
        """``process``: a bag this recorder opens is written by a process of its
        own (:class:`~has_control.bag.process.BagProcess`), so that writing
        takes no GIL from a busy loop; else by a thread. ``keep``: topics
        (relative names, among ``topics``) whose messages are also kept, bag or
        no bag, for :meth:`taken`."""
        self.namespace = namespace
        self.topics = {topic_name(namespace, rel): (rel, ty) for rel, ty in (topics or RUN_TOPICS).items()}
        self._state = topic_name(namespace, STATE)
        self._command = topic_name(namespace, COMMAND)
        self.writer: BagWriter | BagProcess | None = None
        self.process = process
        self.prefix = ""
        self.written: dict[str, int] = {t: 0 for t in self.topics}
        self.pending: dict[str, list[bytes]] = {t: [] for t in self.topics}
        self.kept: dict[str, list[bytes]] = {topic_name(namespace, rel): [] for rel in keep}
        self.samples_wanted = 0
        self.done = threading.Event()
        self.diverged = False
        self.y_limit = y_limit
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="bag-writer")
        self._writes: list = []
        self.subscriptions = []
        if node is not None and subscribe:
            for full, (rel, ty) in self.topics.items():
                self.subscriptions.append(node.create_subscription(
                    _CLASSES[ty], full, lambda data, t=full: self.observe(t, data),
                    _subscription_qos(rel == GAINS), raw=True))

    def observe(self, topic: str, data: bytes) -> None:
        """Take one message of ``topic`` (its full name) from a subscription."""
        with self._lock:
            if self.writer is None:
                return
            pending = self.pending[topic]
            pending.append(data)
            if topic == self._state:
                if self.y_limit < math.inf:
                    y = struct.unpack_from("<d", data, _Y)[0] if len(data) == STATE_LAYOUT.size else math.nan
                    if not abs(y) <= self.y_limit:
                        self.diverged = True
                        self.done.set()
                if len(pending) >= BATCH:
                    self._hand_over()
            elif topic == self._command and self.samples_wanted and \
                    self.written[topic] + len(pending) >= self.samples_wanted:
                self.done.set()

    def sink(self, topic: str) -> Callable[[bytes], None] | None:
        """The in-process tap for ``topic`` (its full name): a function that takes
        each message as published, on the publishing thread, with no lock (the
        tap and the hand-over to the writer run on that one thread); None for a
        topic not recorded."""
        if topic not in self.pending:
            return None
        pending = self.pending[topic]
        if topic != self._state:
            return pending.append

        def take(data: bytes) -> None:
            pending.append(data)
            if len(pending) >= BATCH:
                self._hand_over()
        return take

    def _hand_over(self) -> None:
        """Give what is pending to the writer (process or thread); what is kept,
        joined into one chunk per topic (no object per message)."""
        if self.writer is None:
            for t, chunks in self.kept.items():
                m = self.pending.get(t)
                if m:
                    chunks.append(b"".join(m))
                    self.written[t] += len(m)
                    m.clear()
            return
        batch = {}
        for t, m in self.pending.items():
            if m:
                batch[t] = m[:]
                self.written[t] += len(m)
                if t in self.kept:
                    self.kept[t].append(b"".join(m))
                m.clear()
        if not batch:
            return
        if isinstance(self.writer, BagProcess):     # copied through a pipe; the child builds the records
            self.writer.write_messages({self.prefix + t: (self.topics[t][1], m) for t, m in batch.items()})
        else:
            self._writes.append(self._pool.submit(_write, self.writer, batch, self.topics, self.prefix))

    def connected(self) -> bool:
        """Every subscription has matched a publisher."""
        return all(s.get_publisher_count() for s in self.subscriptions)

    def open(self, path: str | Path | None = None, cfg=None, samples: int = 0,
             writer: BagWriter | None = None, prefix: str = "") -> BagWriter:
        """Start writing to a new bag at ``path`` (or into ``writer`` under ``prefix``)."""
        custom = {PARAMETERS_KEY: parameters_json(cfg)} if cfg is not None else {}
        w = writer or (BagProcess(path, custom) if self.process else BagWriter(path, custom))
        for full, (rel, ty) in self.topics.items():
            w.add_topic(prefix + full, ty, OFFERED.get(rel, QosSpec(depth=10)))
        with self._lock:
            self.writer, self.prefix = w, prefix
            self.written = {t: 0 for t in self.topics}
            for m in (*self.pending.values(), *self.kept.values()):
                m.clear()
            self.samples_wanted = samples
            self.diverged = False
            self.done.clear()
        return w

    def add(self, relative: str, msgtype: str, messages: list[bytes]) -> None:
        """A topic the nodes do not publish to the recorder (e.g. what a realtime
        loop reports after its run), declared even with no messages, into the open bag."""
        if self.writer is None:
            return
        topic = self.prefix + topic_name(self.namespace, relative)
        self.writer.add_topic(topic, msgtype, OFFERED.get(relative, QosSpec(depth=10)))
        if not messages:
            return
        if isinstance(self.writer, BagProcess):
            self.writer.write_messages({topic: (msgtype, messages)})
        else:
            self._writes.append(self._pool.submit(self.writer.write_batches, {topic: as_batch(msgtype, messages)}))

    def taken(self, relative: str) -> list[bytes]:
        """Every message of ``relative`` taken since :meth:`open` (a topic named in
        ``keep``), in order, as messages and chunks of joined messages."""
        t = topic_name(self.namespace, relative)
        return self.kept.get(t, []) + self.pending.get(t, [])

    def count(self, relative: str) -> int:
        """Messages of ``relative`` taken since :meth:`open`."""
        t = topic_name(self.namespace, relative)
        return self.written[t] + len(self.pending[t])

    def detach(self) -> BagWriter | BagProcess | None:
        """Stop taking messages; everything taken is written. Returns the writer (still open)."""
        with self._lock:
            self._hand_over()
            w, self.writer = self.writer, None
            writes, self._writes = self._writes, []
        for f in writes:
            f.result()                          # re-raises a write error here
        return w

    def close(self) -> Path | None:
        """Stop taking messages and close the bag."""
        w = self.detach()
        return w.close() if w is not None else None


def _write(writer: BagWriter, batch: dict[str, list[bytes]], topics: dict, prefix: str) -> None:
    """One batch of messages, topic by topic, into the bag (on the writer thread)."""
    writer.write_batches({prefix + t: as_batch(topics[t][1], msgs) for t, msgs in batch.items()})
