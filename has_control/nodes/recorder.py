"""Record a run's topics to a rosbag2 MCAP bag from the CDR bytes already in hand.

A :class:`Recorder` takes messages as serialized bytes, never re-encoding
them, from two intakes:

* raw subscriptions (``raw=True``: no deserialisation) on a node, for one
  namespace: the generic path, for a graph anywhere on the ROS network (the
  tuner's lanes);
* :meth:`Recorder.sink`, a tap the nodes composed in this process call
  with the bytes they publish (``has-control stack --record``): no executor
  event, callback or lock per message, a list append.

Messages are kept per topic and written in batches (:meth:`BagWriter.write_batches`)
on a writer thread, so the loop pays a list append per message. Log time is
simulation time: the header stamp of JointState and Clock, and the leading t
of our Float64MultiArray topics. A lock-step bag holds exactly one state and
one command per sample. :meth:`open` / :meth:`close` let a tuner record
episode after episode on the same subscriptions.
"""
from __future__ import annotations

import math
import struct
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from .. import cdr
from ..bag import PARAMETERS_KEY, BagWriter, QosSpec, parameters_json
from ..topics import (CLOCK, COMMAND, FLOAT64_ARRAY, GAINS, JOINT_STATE, QOS, RUN_TOPICS, STATE,
                      STATE_LAYOUT)

_CLASSES = {JOINT_STATE: JointState, CLOCK: Clock, FLOAT64_ARRAY: Float64MultiArray}

#: What the publishers offer (stored in the bag as rosbag2 does).
OFFERED = {rel: QosSpec(depth=depth, transient_local=latched) for rel, (depth, latched) in QOS.items()}

#: Messages of the state topic between two hand-overs to the writer thread.
BATCH = 4096

_Y = int(STATE_LAYOUT.values[0])          # byte offset of position[0] = y in a state message


def _subscription_qos(transient_local: bool) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local
                      else DurabilityPolicy.VOLATILE)


def topic_name(namespace: str, relative: str) -> str:
    ns = namespace.rstrip("/")
    return f"{ns}/{relative}" if ns else f"/{relative}"


def as_batch(msgtype: str, datas: list[bytes]) -> tuple[np.ndarray, np.ndarray | list[bytes]]:
    """(log times [ns], messages) of one topic's messages: simulation time from
    each message's stamp, or the leading t of our arrays; messages of one size
    become a (n, size) byte matrix, read column-wise without a loop per message."""
    size = len(datas[0])
    raw = b"".join(datas)
    if len(raw) != size * len(datas):                    # mixed sizes: one by one
        if msgtype in (JOINT_STATE, CLOCK):
            return cdr.stamps_ns(datas), datas
        return np.array([round(cdr.first_float64(d) * 1e9) for d in datas], dtype=np.int64), datas
    matrix = np.frombuffer(raw, dtype=np.uint8).reshape(len(datas), size)
    if msgtype in (JOINT_STATE, CLOCK):
        sec = matrix[:, 4:8].copy().view("<i4").ravel().astype(np.int64)
        nsec = matrix[:, 8:12].copy().view("<u4").ravel().astype(np.int64)
        return sec * 1_000_000_000 + nsec, matrix
    try:
        start, _, _ = cdr.float64_array_layout(datas[0])
    except (cdr.CdrError, struct.error):
        start = -1
    if start < 0 or start + 8 > size:
        return np.array([round(cdr.first_float64(d) * 1e9) for d in datas], dtype=np.int64), datas
    t = matrix[:, start:start + 8].copy().view("<f8").ravel()
    return np.rint(t * 1e9).astype(np.int64), matrix


class Recorder:
    """Records the run topics of ``namespace``; subscribes on ``node`` unless ``subscribe`` is False."""

    def __init__(self, node=None, namespace: str = "", topics: dict[str, str] | None = None,
                 y_limit: float = math.inf, subscribe: bool = True):
        self.namespace = namespace
        self.topics = {topic_name(namespace, rel): (rel, ty) for rel, ty in (topics or RUN_TOPICS).items()}
        self._state = topic_name(namespace, STATE)
        self._command = topic_name(namespace, COMMAND)
        self.writer: BagWriter | None = None
        self.prefix = ""
        self.written: dict[str, int] = {t: 0 for t in self.topics}
        self.pending: dict[str, list[bytes]] = {t: [] for t in self.topics}
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

    def sink(self, topic: str):
        """The in-process tap for ``topic`` (its full name): a function that takes
        each message as published, on the publishing thread, with no lock (the
        tap and the hand-over to the writer run on that one thread)."""
        pending = self.pending[topic]
        if topic != self._state:
            return pending.append

        def take(data: bytes) -> None:
            pending.append(data)
            if len(pending) >= BATCH:
                self._hand_over()
        return take

    def _hand_over(self) -> None:
        """Give what is pending to the writer thread."""
        if self.writer is None:
            return
        batch = {}
        for t, m in self.pending.items():
            if m:
                batch[t] = m[:]
                self.written[t] += len(m)
                m.clear()
        if batch:
            self._writes.append(self._pool.submit(_write, self.writer, batch, self.topics, self.prefix))

    def connected(self) -> bool:
        """Every subscription has matched a publisher."""
        return all(s.get_publisher_count() for s in self.subscriptions)

    def open(self, path: str | Path | None = None, cfg=None, samples: int = 0,
             writer: BagWriter | None = None, prefix: str = "") -> BagWriter:
        """Start writing to a new bag at ``path`` (or into ``writer`` under ``prefix``)."""
        custom = {PARAMETERS_KEY: parameters_json(cfg)} if cfg is not None else {}
        w = writer or BagWriter(path, custom)
        for full, (rel, ty) in self.topics.items():
            w.add_topic(prefix + full, ty, OFFERED.get(rel, QosSpec(depth=10)))
        with self._lock:
            self.writer, self.prefix = w, prefix
            self.written = {t: 0 for t in self.topics}
            for m in self.pending.values():
                m.clear()
            self.samples_wanted = samples
            self.diverged = False
            self.done.clear()
        return w

    def count(self, relative: str) -> int:
        """Messages of ``relative`` taken since :meth:`open`."""
        t = topic_name(self.namespace, relative)
        return self.written[t] + len(self.pending[t])

    def detach(self) -> BagWriter | None:
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
