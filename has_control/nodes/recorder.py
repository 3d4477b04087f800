"""Record a run's topics to a rosbag2 MCAP bag, CDR bytes straight to disk.

The :class:`Recorder` attaches raw subscriptions (``raw=True``: no
deserialisation) to any node, for one namespace, and writes what arrives to
the bag that is open at the time (:meth:`Recorder.open` / :meth:`close`),
so a tuner can record episode after episode on the same subscriptions. Log
time is simulation time: the header stamp of JointState and Clock, and the
leading t of our Float64MultiArray topics.

The subscriptions keep every message (reliable, keep-all): a lock-step bag
holds exactly one state and one command per sample.
"""
from __future__ import annotations

import math
import struct
import threading
from pathlib import Path
from typing import Callable

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from .. import cdr
from ..bag import (CLOCK, CLOCK_TOPIC, COMMAND, FLOAT64_ARRAY, GAINS, JOINT_STATE, PARAMETERS_KEY,
                   RUN_TOPICS, STATE, BagWriter, QosSpec, parameters_json)

_CLASSES = {JOINT_STATE: JointState, CLOCK: Clock, FLOAT64_ARRAY: Float64MultiArray}

#: What the publishers offer (stored in the bag as rosbag2 does).
OFFERED = {STATE: QosSpec(depth=1), COMMAND: QosSpec(depth=1), CLOCK_TOPIC: QosSpec(depth=10),
           GAINS: QosSpec(depth=1, transient_local=True)}


def _subscription_qos(transient_local: bool) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local
                      else DurabilityPolicy.VOLATILE)


def _stamp_ns(data: bytes) -> int:
    sec, nsec = struct.unpack_from("<iI", data, 4)
    return sec * 1_000_000_000 + nsec


def _leading_t_ns(data: bytes) -> int:
    return int(round(cdr.first_float64(data) * 1e9))


def topic_name(namespace: str, relative: str) -> str:
    ns = namespace.rstrip("/")
    return f"{ns}/{relative}" if ns else f"/{relative}"


class Recorder:
    """Raw subscriptions on ``node`` for the run topics of ``namespace``."""

    def __init__(self, node, namespace: str = "", topics: dict[str, str] | None = None,
                 y_limit: float = math.inf):
        self.node = node
        self.namespace = namespace
        self.topics = {topic_name(namespace, rel): (rel, ty) for rel, ty in (topics or RUN_TOPICS).items()}
        self.writer: BagWriter | None = None
        self.rename: Callable[[str], str] = lambda t: t
        self.counts: dict[str, int] = {t: 0 for t in self.topics}
        self.samples_wanted = 0
        self.done = threading.Event()
        self.diverged = False
        self.y_limit = y_limit
        self._y_offset: int | None = None
        self._lock = threading.Lock()
        self.subscriptions = []
        for full, (rel, ty) in self.topics.items():
            timefn = _stamp_ns if ty in (JOINT_STATE, CLOCK) else _leading_t_ns
            self.subscriptions.append(node.create_subscription(
                _CLASSES[ty], full, self._callback(full, rel, timefn),
                _subscription_qos(rel == GAINS), raw=True))

    def _callback(self, full: str, rel: str, timefn):
        def on_message(data: bytes) -> None:
            with self._lock:
                if self.writer is None:
                    return
                self.writer.write(self.rename(full), timefn(data), data)
                self.counts[full] += 1
                if rel == STATE:
                    self._check_state(data)
                elif rel == COMMAND and self.samples_wanted and self.counts[full] >= self.samples_wanted:
                    self.done.set()
        return on_message

    def _check_state(self, data: bytes) -> None:
        if self._y_offset is None:
            self._y_offset = cdr.joint_state_layout(data).position[0]
        y = struct.unpack_from("<d", data, self._y_offset)[0]
        if not math.isfinite(y) or abs(y) > self.y_limit:
            self.diverged = True
            self.done.set()

    def connected(self) -> bool:
        """Every subscription has matched a publisher."""
        return all(s.get_publisher_count() for s in self.subscriptions)

    def open(self, path: str | Path | None = None, cfg=None, samples: int = 0,
             writer: BagWriter | None = None, prefix: str = "") -> BagWriter:
        """Start writing to a new bag at ``path`` (or into ``writer`` under ``prefix``)."""
        custom = {PARAMETERS_KEY: parameters_json(cfg)} if cfg is not None else {}
        w = writer or BagWriter(path, custom)
        rename = (lambda t: prefix + t) if prefix else (lambda t: t)
        for full, (rel, ty) in self.topics.items():
            w.add_topic(rename(full), ty, OFFERED.get(rel, QosSpec(depth=10)))
        with self._lock:
            self.writer, self.rename = w, rename
            self.counts = {t: 0 for t in self.topics}
            self.samples_wanted = samples
            self.diverged = False
            self.done.clear()
        return w

    def count(self, relative: str) -> int:
        return self.counts[topic_name(self.namespace, relative)]

    def detach(self) -> BagWriter | None:
        """Stop writing; returns the writer (still open)."""
        with self._lock:
            w, self.writer = self.writer, None
        return w

    def close(self) -> Path | None:
        """Stop writing and close the bag."""
        w = self.detach()
        return w.close() if w is not None else None

    def destroy(self) -> None:
        for s in self.subscriptions:
            self.node.destroy_subscription(s)
        self.subscriptions = []
