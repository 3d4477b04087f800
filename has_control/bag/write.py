"""Writing rosbag2 bags: the rosbag2 layer over :mod:`~has_control.bag.mcap_writer`
(message definitions, type hashes and QoS profiles from rosbags'
typestore, ``metadata.yaml``), and a trace written as the graph's messages."""
from __future__ import annotations

import json
import struct
import threading
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import yaml

from has_control.wire import cdr
from has_control.bag.base import BagError
from has_control.bag.mcap_writer import McapWriter
from has_control.config import config_parameters
from has_control.core.actuator import joint_state
from has_control.core.episode import Col, EpisodeArrays
from has_control.core.reference import reference_series
from has_control.wire.codec import column_label
from has_control.wire.topics import (
    CLOCK, COMMAND, COMMAND_NAMES, CONTROLLER_STATE, CONTROLLER_STATE_COLUMNS, FLOAT64_ARRAY, GAINS, GAINS_COLUMNS,
    JOINT_STATE, REFERENCE, REFERENCE_COLUMNS, STATE, STATE_NAMES,
)

#: The ROS release whose message definitions (and type hashes) the bags carry.
ROS_DISTRO = "kilted"


@lru_cache(maxsize=1)
def typestore():
    """Message definitions (rosbags' store of :data:`ROS_DISTRO`)."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(getattr(Stores, f"ROS2_{ROS_DISTRO.upper()}"))


def msgdef(msgtype: str) -> str:
    """The ``ros2msg`` schema text of ``msgtype`` (as rosbag2 writes it into MCAP)."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return text


@dataclass(frozen=True)
class QosSpec:
    """The QoS a topic was offered with, as rosbag2 stores it."""

    reliable: bool = True
    depth: int = 1
    transient_local: bool = False

    def profiles(self) -> list[dict]:
        """``offered_qos_profiles`` in rosbag2 version 9 form (rosbags' ``dump_qos_v9``)."""
        from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                        QosReliability, QosTime)
        from rosbags.rosbag2.metadata import dump_qos_v9
        never = QosTime(0x7FFFFFFF, 0xFFFFFFFF)
        return dump_qos_v9([Qos(QosHistory.KEEP_LAST, self.depth,
                                QosReliability.RELIABLE if self.reliable else QosReliability.BEST_EFFORT,
                                QosDurability.TRANSIENT_LOCAL if self.transient_local else QosDurability.VOLATILE,
                                never, never, QosLiveliness.AUTOMATIC, never, False)])


@dataclass(frozen=True)
class _Topic:
    channel: int
    msgtype: str
    qos: list[dict]
    type_hash: str                  # RIHS01_<sha256 hex> (REP 2011)


def _yaml(doc) -> str:
    return yaml.safe_dump(doc, default_flow_style=False)


class BagWriter:
    """A rosbag2 (version 9) MCAP bag, as ``ros2 bag record -s mcap`` writes it
    (see the module's docstring), written message by message or in NumPy
    batches by :class:`~has_control.bag.mcap_writer.McapWriter`.

    ``compression`` is ``"zstd"`` (chunks, the default) or ``"none"``.
    ``metadata.yaml`` is written on :meth:`close`, as rosbags writes it."""

    def __init__(self, path: str | Path, custom_data: dict[str, str] | None = None, compression: str = "zstd"):
        self.path = Path(path)
        self.custom_data = dict(custom_data or {})
        bad = [k for k, v in self.custom_data.items() if not isinstance(v, str)]
        if bad:
            raise BagError(f"{self.path}: custom_data {bad[0]!r} is not a string")
        try:
            self.path.mkdir(parents=True)
        except FileExistsError:
            raise BagError(f"{self.path}: exists already; a bag is never overwritten") from None
        self.file = self.path / f"{self.path.name}.mcap"
        self._mcap = McapWriter(self.file, "ros2", "has_control", compression)
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, _Topic] = {}
        self._lock = threading.RLock()            # a recorder's writer thread and the caller share a bag

    def add_topic(self, topic: str, msgtype: str, qos: QosSpec = QosSpec()) -> None:
        """Declare ``topic`` (again: no-op): its schema (``ros2msg``) and channel,
        with ``offered_qos_profiles`` and ``topic_type_hash`` as rosbag2 writes them."""
        with self._lock:
            self._add_topic(topic, msgtype, qos)

    def _add_topic(self, topic: str, msgtype: str, qos: QosSpec) -> None:
        if topic in self._topics:
            return
        ts = typestore()
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._mcap.add_schema(msgtype, "ros2msg", msgdef(msgtype).encode())
        profiles, type_hash = qos.profiles(), ts.hash_rihs01(msgtype)
        channel = self._mcap.add_channel(topic, self._schemas[msgtype], "cdr", {
            "offered_qos_profiles": _yaml(profiles).strip(), "topic_type_hash": type_hash})
        self._topics[topic] = _Topic(channel, msgtype, profiles, type_hash)

    def _channel(self, topic: str) -> int:
        if topic not in self._topics:
            raise BagError(f"{self.path}: no topic {topic} (add_topic first)")
        return self._topics[topic].channel

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic."""
        return {t: self._mcap.counts[x.channel] for t, x in self._topics.items()}

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """One CDR message (buffered until the next batch, sync or close)."""
        with self._lock:
            self._mcap.write(self._channel(topic), log_time_ns, data)

    def write_message(self, topic: str, log_time_ns: int, msg, msgtype: str) -> None:
        self.write(topic, log_time_ns, bytes(typestore().serialize_cdr(msg, msgtype)))

    def write_batches(self, batches: dict[str, tuple[np.ndarray, np.ndarray | list[bytes]]]) -> None:
        """CDR messages of several topics: ``{topic: (log_times_ns int64 (n,), data)}``,
        data a (n, size) uint8 matrix or a list of n ``bytes``; merged in
        log-time order (ties: topics in the order given, then arrival)."""
        with self._lock:
            self._mcap.write_batches({self._channel(t): batch for t, batch in batches.items()})

    def sync(self) -> None:
        """Close the open chunk and flush it to disk: a crash after this loses
        nothing written so far."""
        with self._lock:
            self._mcap.sync()

    def _metadata(self) -> dict:
        """``rosbag2_bagfile_information`` as rosbags writes it (version 9)."""
        start, counts = self._mcap.start_ns, self._mcap.counts
        duration, count = max(0, self._mcap.end_ns - start), sum(counts.values())
        return {
            "version": 9,
            "storage_identifier": "mcap",
            "relative_file_paths": [self.file.name],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": topic, "type": x.msgtype, "serialization_format": "cdr",
                                    "offered_qos_profiles": x.qos, "type_description_hash": x.type_hash},
                 "message_count": counts[x.channel]}
                for topic, x in self._topics.items()],
            "compression_format": "",           # chunk compression is the storage's own business
            "compression_mode": "",
            "files": [{"path": self.file.name, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": count}],
            "custom_data": self.custom_data or None,
            "ros_distro": ROS_DISTRO,
        }

    def close(self) -> Path:
        """Finish the MCAP file (with the ``rosbag2`` metadata record) and write
        ``metadata.yaml``; the bag's path. Closing twice does nothing."""
        with self._lock:
            self._close()
        return self.path

    def _close(self) -> None:
        if not self._mcap.closed:
            info = self._metadata()
            self._mcap.close({"rosbag2": {"serialized_metadata": _yaml(info).strip()}})
            tmp = self.path / "metadata.yaml.tmp"
            tmp.write_text(_yaml({"rosbag2_bagfile_information": info}), "utf8")
            tmp.replace(self.path / "metadata.yaml")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def parameters_json(cfg) -> str:
    return json.dumps(config_parameters(cfg))


def write_trace(writer: BagWriter, trace, cfg, prefix: str = "", log_offset_ns: int = 0) -> None:
    """Write an in-process :class:`~has_control.core.episode.Trace` as the messages
    the node graph publishes for it: state, command, reference, controller
    state and gains, under ``prefix`` (e.g. ``/validation``). Log time is
    simulation time plus ``log_offset_ns``; stamps are simulation time."""
    d = trace.data
    n = len(d)
    step_ns = cfg.episode.step_ns
    stamps = np.arange(n, dtype=np.int64) * step_ns
    t = d[:, Col.t]
    js = joint_state(d[:, Col.y], d[:, Col.ydot], d[:, Col.P1], d[:, Col.P2], cfg.actuator.as_array())
    pos, vel, eff = js[0:3], js[3:6], js[6:9]
    rp = EpisodeArrays.from_config(cfg).reference
    ref = np.column_stack([t, reference_series(rp, np.ascontiguousarray(t))]).reshape(n, 5)
    k = trace.gains.as_tuple()
    topics = {
        STATE: (JOINT_STATE, cdr.encode_joint_states(stamps, STATE_NAMES, np.column_stack(pos),
                                                     np.column_stack(vel), np.column_stack(eff))),
        COMMAND: (JOINT_STATE, cdr.encode_joint_states(stamps, COMMAND_NAMES, d[:, [Col.u]])),
        REFERENCE: (FLOAT64_ARRAY, cdr.encode_float64_arrays(ref, column_label(REFERENCE_COLUMNS))),
        CONTROLLER_STATE: (FLOAT64_ARRAY, cdr.encode_float64_arrays(
            d[:, [Col.t, Col.e1, Col.e2, Col.e3, Col.a1_hat, Col.a2_hat, Col.x1d]],
            column_label(CONTROLLER_STATE_COLUMNS))),
        GAINS: (FLOAT64_ARRAY, cdr.encode_float64_arrays([[0.0, *k]], column_label(GAINS_COLUMNS))),
    }
    for rel, (ty, _) in topics.items():
        writer.add_topic(f"{prefix}/{rel}", ty)
    writer.write_batches({f"{prefix}/{rel}": ((stamps if len(msgs) == n else np.zeros(1, np.int64)) + log_offset_ns,
                                              msgs)
                          for rel, (_, msgs) in topics.items()})


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
