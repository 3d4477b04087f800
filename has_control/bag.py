"""rosbag2 bags in MCAP: write, read (tolerating truncation), score, describe.

Outer layer: rosbags and the MCAP format, no rclpy. A bag is what
``ros2 bag record -s mcap`` writes: a directory with ``metadata.yaml``
(rosbag2 version 9) and one ``.mcap`` file, profile ``ros2``, schemas
``ros2msg``, messages ``cdr``, zstd-compressed chunks with their CRCs, each
channel with its ``offered_qos_profiles`` and ``topic_type_hash``. The MCAP
file is written by :mod:`~has_control.mcap_writer` (batches of messages as
NumPy arrays); rosbags supplies the message definitions, their type hashes
and the QoS profiles' form. Log time is simulation time. The run's parameters
travel in the bag's ``custom_data`` (key ``has_control/parameters``, JSON),
so a bag can be scored without knowing how it was made.

Reading is our own sequential MCAP scan, so that a bag whose recorder was
killed mid-write still yields every complete chunk (with a warning saying how
much was lost), and a bare ``.mcap`` file is accepted as rosbag2 accepts it.
"""
from __future__ import annotations

import json
import struct
import sys
import threading
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import yaml

from . import cdr
from .errors import HasControlError
from .files import MiB, read_bytes, read_text
from .topics import (  # noqa: F401  (re-exported: the bag code's vocabulary)
    CLOCK, CLOCK_TOPIC, COMMAND, COMMAND_NAMES, CONTROLLER_STATE, FLOAT64_ARRAY, GAINS, JOINT_STATE,
    REFERENCE, RUN_TOPICS, STATE, STATE_NAMES, STRING,
)

MAGIC = b"\x89MCAP0\r\n"
PARAMETERS_KEY = "has_control/parameters"


class BagError(HasControlError):
    """A bag that cannot be read or lacks what we need (one line naming the file)."""


def warn(message: str) -> None:
    print(f"has-control: warning: {message}", file=sys.stderr)


# --- writing ----------------------------------------------------------------

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
    batches by :class:`~has_control.mcap_writer.McapWriter`.

    ``compression`` is ``"zstd"`` (chunks, the default) or ``"none"``.
    ``metadata.yaml`` is written on :meth:`close`, as rosbags writes it."""

    def __init__(self, path: str | Path, custom_data: dict[str, str] | None = None, compression: str = "zstd"):
        from .mcap_writer import McapWriter
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
    from .config import config_parameters
    return json.dumps(config_parameters(cfg))


def write_trace(writer: BagWriter, trace, cfg, prefix: str = "", log_offset_ns: int = 0) -> None:
    """Write an in-process :class:`~has_control.episode.Trace` as the messages
    the node graph publishes for it: state, command, reference, controller
    state and gains, under ``prefix`` (e.g. ``/validation``). Log time is
    simulation time plus ``log_offset_ns``; stamps are simulation time."""
    from .actuator import joint_state
    from .episode import EpisodeArrays
    from .topics import CONTROLLER_STATE_COLUMNS, GAINS_COLUMNS, REFERENCE_COLUMNS
    from .wire import column_label
    from .reference import reference
    d = trace.data
    n = len(d)
    step_ns = int(round(cfg.episode.step * 1e9))
    stamps = np.arange(n, dtype=np.int64) * step_ns
    t = d[:, 0]
    js = joint_state(d[:, 2], d[:, 3], d[:, 4], d[:, 5], cfg.actuator.as_array())
    pos, vel, eff = js[0:3], js[3:6], js[6:9]
    rp = EpisodeArrays.from_config(cfg).reference
    ref = np.array([(ti, *reference(rp, ti)) for ti in t]).reshape(n, 5)
    k = trace.gains.as_tuple()
    topics = {
        STATE: (JOINT_STATE, cdr.encode_joint_states(stamps, STATE_NAMES, np.column_stack(pos),
                                                     np.column_stack(vel), np.column_stack(eff))),
        COMMAND: (JOINT_STATE, cdr.encode_joint_states(stamps, COMMAND_NAMES, d[:, 6:7])),
        REFERENCE: (FLOAT64_ARRAY, cdr.encode_float64_arrays(ref, column_label(REFERENCE_COLUMNS))),
        CONTROLLER_STATE: (FLOAT64_ARRAY, cdr.encode_float64_arrays(
            np.column_stack([t, d[:, 7], d[:, 8], d[:, 9], d[:, 10], d[:, 11], d[:, 1]]),
            column_label(CONTROLLER_STATE_COLUMNS))),
        GAINS: (FLOAT64_ARRAY, cdr.encode_float64_arrays([[0.0, *k]], column_label(GAINS_COLUMNS))),
    }
    for rel, (ty, _) in topics.items():
        writer.add_topic(f"{prefix}/{rel}", ty)
    writer.write_batches({f"{prefix}/{rel}": ((stamps if len(msgs) == n else np.zeros(1, np.int64)) + log_offset_ns,
                                              msgs)
                          for rel, (_, msgs) in topics.items()})


# --- reading ----------------------------------------------------------------

@dataclass
class Bag:
    """What a bag holds, topic by topic, as (log time [ns], CDR bytes)."""

    path: Path                       # the bag (directory or .mcap file) as given
    files: list[Path]
    types: dict[str, str] = field(default_factory=dict)
    qos: dict[str, str] = field(default_factory=dict)
    messages: dict[str, list[tuple[int, bytes]]] = field(default_factory=dict)
    custom_data: dict[str, str] = field(default_factory=dict)
    encodings: dict[str, str] = field(default_factory=dict)     # topic -> message encoding
    complete: bool = True
    damage: list[str] = field(default_factory=list)             # why not complete, one item per finding
    lost_bytes: int = 0
    size: int = 0
    on_warning: Callable[[str], None] = field(default=warn, repr=False)

    def count(self, topic: str) -> int:
        return len(self.messages.get(topic, ()))

    def find(self, relative: str, msgtype: str) -> str:
        """The one topic named ``relative`` under any namespace, of ``msgtype``."""
        hits = [t for t, ty in self.types.items()
                if (t == "/" + relative or t.endswith("/" + relative)) and ty == msgtype]
        if len(hits) != 1:
            have = ", ".join(sorted(self.types)) or "none"
            what = "no" if not hits else f"{len(hits)} topics"
            raise BagError(f"{self.path}: {what} '…/{relative}' ({msgtype}) in the bag; topics: {have}")
        return hits[0]

    def config(self, overrides: Iterable[str | Path] = ()):
        """The run's Config from the bag (else the shipped defaults, with a warning)."""
        from .config import build_config, load_config, read_parameter_files
        overrides = list(overrides)
        stored = self.custom_data.get(PARAMETERS_KEY)
        if stored is None:
            self.on_warning(f"{self.path}: no {PARAMETERS_KEY} in the bag; scoring with the shipped configuration")
            return load_config(overrides)
        try:
            flat = json.loads(stored)
        except ValueError:
            raise BagError(f"{self.path}: custom_data {PARAMETERS_KEY} is not JSON") from None
        cfg = build_config(flat, source=f"{self.path} ({PARAMETERS_KEY})")
        if overrides:
            over, sources = read_parameter_files(overrides)
            cfg = build_config(over, source=", ".join(map(str, overrides)), base=cfg)
        return cfg

    @property
    def start_ns(self) -> int:
        return min((min(t for t, _ in m) for m in self.messages.values() if m), default=0)

    @property
    def end_ns(self) -> int:
        return max((max(t for t, _ in m) for m in self.messages.values() if m), default=0)

    def damage_summary(self) -> str:
        """Why the bag is incomplete, in a few words."""
        chunks = sum("chunk at offset" in d for d in self.damage)
        rest = [d.split(" (")[0] if "chunk at offset" not in d else "" for d in self.damage]
        parts = ([f"{chunks} corrupted chunk{'s' if chunks > 1 else ''} skipped"] if chunks else [])
        return "; ".join(parts + [r for r in rest if r]) or "incomplete"

    def sort_by_log_time(self, on_warning) -> None:
        """Each topic's messages in log-time order (as MCAP readers give them),
        with a warning naming the topics that were not."""
        unordered = [t for t, m in self.messages.items() if any(a[0] > b[0] for a, b in zip(m, m[1:]))]
        for t in unordered:
            self.messages[t].sort(key=lambda m: m[0])
        if unordered:
            on_warning(f"{self.path}: messages out of log-time order on {', '.join(sorted(unordered))} "
                       "(a reordered bag): read in log-time order")


def read_bag(path: str | Path, topics: Iterable[str] | None = None,
             on_warning: Callable[[str], None] = warn) -> Bag:
    """Read a bag directory or a bare ``.mcap`` file (see the module's docstring)."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag (directory or .mcap file)")
    wanted = set(topics) if topics is not None else None
    bag = Bag(path, [], on_warning=on_warning)
    if path.is_dir():
        meta = path / "metadata.yaml"
        mcaps = sorted(path.glob("*.mcap"))
        if meta.exists():
            bag.files = _files_from_metadata(meta, bag)
        elif len(mcaps) == 1:
            on_warning(f"{path}: no metadata.yaml (was the recorder stopped?); reading {mcaps[0].name}")
            bag.files = mcaps
        else:
            raise BagError(f"{path}: not a bag: no metadata.yaml and {len(mcaps)} .mcap files")
    else:
        bag.files = [path]
    for f in bag.files:
        _read_mcap(f, bag, wanted, on_warning)
    bag.sort_by_log_time(on_warning)
    return bag


#: metadata.yaml is read whole; larger is not a rosbag2 metadata file [bytes].
MAX_METADATA_BYTES = 16 * MiB


def _files_from_metadata(meta: Path, bag: Bag) -> list[Path]:
    from .config import load_yaml
    doc = load_yaml(read_text(meta, MAX_METADATA_BYTES, BagError), str(meta), BagError, "malformed YAML")
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise BagError(f"{meta}: no rosbag2_bagfile_information mapping")
    storage = info.get("storage_identifier")
    if storage != "mcap":
        raise BagError(f"{meta}: storage_identifier = {storage!r}: expected 'mcap'")
    rel = info.get("relative_file_paths")
    if not isinstance(rel, list) or not rel or not all(isinstance(r, str) for r in rel):
        raise BagError(f"{meta}: relative_file_paths: expected a list of file names")
    files = [meta.parent / r for r in rel]
    for f in files:
        if not f.exists():
            raise BagError(f"{meta}: lists {f.name}, which does not exist")
    custom = info.get("custom_data") or {}
    if isinstance(custom, dict):
        bag.custom_data.update({str(k): str(v) for k, v in custom.items()})
    return files


def _string(buf, pos: int) -> tuple[str, int]:
    n = struct.unpack_from("<I", buf, pos)[0]
    return bytes(buf[pos + 4:pos + 4 + n]).decode(), pos + 4 + n


def _string_map(buf, pos: int) -> tuple[dict[str, str], int]:
    n = struct.unpack_from("<I", buf, pos)[0]
    end, pos, out = pos + 4 + n, pos + 4, {}
    while pos < end:
        k, pos = _string(buf, pos)
        v, pos = _string(buf, pos)
        out[k] = v
    return out, end


def _decompress(kind: str, data, size: int, where: str) -> bytes:
    if kind == "":
        return bytes(data)
    if kind == "zstd":
        import zstandard
        data = bytes(data)
        declared = zstandard.frame_content_size(data)
        if declared > size:                    # a damaged frame header: never allocate what it claims
            raise BagError(f"{where}: a zstd frame declares {declared} bytes in a chunk of {size}")
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if kind == "lz4":
        import lz4.frame
        return lz4.frame.decompress(bytes(data))
    raise BagError(f"{where}: unsupported chunk compression {kind!r}")


#: A chunk's records, uncompressed, are at most this [bytes] (ours are about 1 MiB).
MAX_CHUNK_BYTES = 1 << 30
#: Footer record: opcode, length 20, summary start, summary offset start, summary CRC [bytes].
FOOTER_BYTES = 29
_CHUNK, _DATA_END, _FOOTER, _METADATA = 0x06, 0x0F, 0x02, 0x0C


def _has_footer(buf: bytes) -> bool:
    """Whether ``buf`` ends in an MCAP footer record and the magic."""
    n = len(buf)
    at = n - 8 - FOOTER_BYTES
    return (at >= 8 and buf[n - 8:] == MAGIC and buf[at] == _FOOTER
            and struct.unpack_from("<Q", buf, at + 1)[0] == FOOTER_BYTES - 9)


def _check_summary(buf: bytes, f: Path, on_warning) -> None:
    """Warn if the summary section's CRC (in the footer) does not match; the
    reader does not use the summary, so the bag stays complete."""
    at = len(buf) - 8 - FOOTER_BYTES
    start, crc = struct.unpack_from("<Q", buf, at + 9)[0], struct.unpack_from("<I", buf, at + 25)[0]
    if crc and 0 < start <= at and zlib.crc32(buf[start:at + 25]) != crc:
        on_warning(f"{f}: summary section CRC mismatch (the summary is not used for reading)")


def _chunk_records(rec, f: Path, offset: int) -> tuple[bytes | None, str]:
    """The uncompressed records of the Chunk whose content is ``rec``, checked
    against its size and CRC (CRC 0: not computed, accepted); else None and why."""
    size, crc = struct.unpack_from("<QI", rec, 16)
    if size > MAX_CHUNK_BYTES:
        return None, f"declares {size} uncompressed bytes, more than the limit of {MAX_CHUNK_BYTES}"
    kind, q = _string(rec, 28)
    clen = struct.unpack_from("<Q", rec, q)[0]
    if q + 8 + clen > len(rec):
        return None, "its compressed size runs past the record"
    try:
        raw = _decompress(kind, rec[q + 8:q + 8 + clen], size, str(f))
    except BagError as exc:
        if "unsupported chunk compression" in str(exc):
            raise
        return None, str(exc).split(": ", 1)[-1]
    except Exception as exc:                                  # zstd/lz4 on damaged bytes
        return None, f"does not decompress ({type(exc).__name__})"
    if len(raw) != size:
        return None, f"decompresses to {len(raw)} bytes, not {size}"
    if crc and zlib.crc32(raw) != crc:
        return None, "CRC mismatch"
    return raw, ""


def _read_mcap(f: Path, bag: Bag, wanted: set[str] | None, on_warning) -> None:
    """Scan one MCAP file record by record (chunks decompressed and checked
    as they come). A chunk whose CRC or size does not match is named, skipped
    and the bag marked incomplete; so is a data section whose CRC does not
    match (DataEnd), and a record that cannot be parsed ends the scan: as a
    truncation if the file has no footer, as damage if it has one."""
    buf = read_bytes(f, error=BagError)
    bag.size += len(buf)
    if buf[:8] != MAGIC:
        raise BagError(f"{f}: not an MCAP file (no MCAP magic at the start)")
    schemas: dict[int, str] = {}
    channels: dict[int, str] = {}
    footer = _has_footer(buf)
    pos, chunks, bad_chunks, data_end, data_checked = 8, 0, 0, False, False
    n = len(buf)

    def damaged(what: str) -> None:
        bag.complete = False
        bag.damage.append(what)
        on_warning(f"{f}: {what}")

    def take(records, origin: str) -> None:
        """Schemas, channels and messages of ``records``, kept only if all parse."""
        got: list[tuple[str, int, bytes]] = []
        p, end = 0, len(records)
        while p + 9 <= end:
            op = records[p]
            ln = struct.unpack_from("<Q", records, p + 1)[0]
            body = p + 9
            if body + ln > end:
                raise BagError(f"{origin}: a record runs past its end")
            if op == 0x05:                                   # Message
                cid = struct.unpack_from("<H", records, body)[0]
                topic = channels.get(cid)
                if topic is not None and (wanted is None or topic in wanted):
                    t = struct.unpack_from("<Q", records, body + 6)[0]
                    got.append((topic, t, bytes(records[body + 22:body + ln])))
            elif op == 0x03:                                 # Schema
                sid = struct.unpack_from("<H", records, body)[0]
                name, _ = _string(records, body + 2)
                schemas[sid] = name
            elif op == 0x04:                                 # Channel
                cid, sid = struct.unpack_from("<HH", records, body)
                topic, q = _string(records, body + 4)
                enc, q = _string(records, q)
                meta, _ = _string_map(records, q)
                if cid not in channels:
                    channels[cid] = topic
                    bag.types.setdefault(topic, schemas.get(sid, ""))
                    bag.encodings.setdefault(topic, enc)
                    bag.qos.setdefault(topic, meta.get("offered_qos_profiles", ""))
                    bag.messages.setdefault(topic, [])
            p = body + ln
        for topic, t, data in got:
            bag.messages[topic].append((t, data))

    view = memoryview(buf)
    try:
        while pos + 9 <= n:
            op = buf[pos]
            ln = struct.unpack_from("<Q", buf, pos + 1)[0]
            body = pos + 9
            if body + ln > n:
                break                                         # truncated (or damaged) record
            rec = view[body:body + ln]
            if op == _CHUNK:
                raw, why = _chunk_records(rec, f, pos)
                if raw is None:
                    bad_chunks += 1
                    damaged(f"chunk at offset {pos} is corrupted ({why}): skipped")
                else:
                    try:
                        take(memoryview(raw), f"{f}: chunk at offset {pos}")
                        chunks += 1
                    except (struct.error, UnicodeDecodeError, BagError):
                        bad_chunks += 1
                        damaged(f"chunk at offset {pos} holds a malformed record: skipped")
            elif op in (0x03, 0x04, 0x05):
                take(view[pos:body + ln], str(f))
            elif op == _METADATA:
                name, q = _string(rec, 0)
                meta, _ = _string_map(rec, q)
                if name == "rosbag2" and "serialized_metadata" in meta:
                    _custom_from_serialized(meta["serialized_metadata"], bag, f)
            elif op == _DATA_END:
                crc = struct.unpack_from("<I", rec, 0)[0] if ln >= 4 else 0
                if crc and zlib.crc32(view[:pos]) != crc and not bad_chunks:
                    damaged("data section CRC mismatch (a record outside the chunks is damaged)")
                data_end, data_checked = True, crc != 0
                pos = body + ln
                break
            elif op == _FOOTER:
                break
            pos = body + ln
    except (struct.error, UnicodeDecodeError, BagError):
        pass                                                  # a torn record: stop at the last good one
    if data_end and footer:
        _check_summary(buf, f, on_warning)
        return
    if data_end and data_checked:          # the data section is all there and its CRC checked
        on_warning(f"{f}: the summary or footer after the data section is damaged; "
                   "the data section is intact (its CRC checked)")
        return
    lost = n - pos
    if footer:
        damaged(f"damaged record at offset {pos} (the footer is there: not a truncation): "
                f"kept {chunks} chunks, {sum(map(len, bag.messages.values()))} messages; "
                f"the last {lost} bytes unread")
        bag.lost_bytes += lost
        return
    bag.complete = False
    bag.lost_bytes += lost
    bag.damage.append(f"truncated, {lost} bytes lost")
    on_warning(f"{f}: truncated (no MCAP footer): kept {chunks} complete chunks, "
               f"{sum(map(len, bag.messages.values()))} messages; lost the last {lost} bytes")


def _custom_from_serialized(text: str, bag: Bag, f: Path) -> None:
    """custom_data of the MCAP file's rosbag2 Metadata record, if metadata.yaml
    gave none (metadata.yaml's wins: it may be edited on purpose)."""
    from .config import load_yaml
    if bag.custom_data:
        return
    try:
        doc = load_yaml(text, f"{f} (rosbag2 metadata)", BagError)
        info = doc.get("rosbag2_bagfile_information", doc)     # rosbag2 stores the inner mapping
        bag.custom_data.update({str(k): str(v) for k, v in (info.get("custom_data") or {}).items()})
    except (BagError, AttributeError):
        pass


# --- what a run's bag says ----------------------------------------------------

@dataclass
class RecordedRun:
    """A lock-step run read back from its bag, one row per sample."""

    t: np.ndarray          # [s]
    y: np.ndarray          # [m]
    ydot: np.ndarray       # [m/s]
    p1: np.ndarray         # [Pa]
    p2: np.ndarray         # [Pa]
    u: np.ndarray          # [m]
    x1d: np.ndarray        # [m]
    diverged: bool
    cfg: object

    @property
    def samples(self) -> int:
        return len(self.u)

    def __getitem__(self, column: str) -> np.ndarray:
        """Trace-style columns: t, x1d, y, ydot, P1, P2, u, e1."""
        if column == "e1":
            return self.x1d - self.y                  # SPEC §3: e1 = x1d − x1
        return {"t": self.t, "x1d": self.x1d, "y": self.y, "ydot": self.ydot, "P1": self.p1,
                "P2": self.p2, "u": self.u}[column]


def _by_sample(stamps_ns: np.ndarray, step_ns: int, what: str, path) -> np.ndarray:
    idx = np.rint(stamps_ns / step_ns).astype(np.int64)
    grid = np.arange(len(idx))
    if len(idx) and not np.array_equal(idx, grid) and np.array_equal(np.sort(idx), grid):
        first = int(np.argmax(idx != np.arange(len(idx))))
        raise BagError(f"{path}: {what}: message {first} carries sample {idx[first]}: the samples are "
                       "reordered (log times and header stamps disagree)")
    if len(idx) and not np.array_equal(idx, np.arange(len(idx))):
        dup = len(idx) - len(np.unique(idx))
        raise BagError(f"{path}: {what} is not one message per sample from sample 0 "
                       f"({len(idx)} messages, {dup} repeated); was it a lock-step run?")
    return idx


def recorded_run(bag: Bag, overrides: Iterable[str | Path] = ()) -> RecordedRun:
    """The samples of a lock-step run in ``bag``: states, commands and reference.
    An incomplete bag (truncated or damaged) is refused: its J would not be the run's."""
    if not bag.complete:
        raise BagError(f"{bag.path}: the bag is incomplete ({bag.damage_summary()}); "
                       "an incomplete run is not scored")
    cfg = bag.config(overrides)
    step_ns = int(round(cfg.episode.step * 1e9))
    st, cm, rf = bag.find(STATE, JOINT_STATE), bag.find(COMMAND, JOINT_STATE), bag.find(REFERENCE, FLOAT64_ARRAY)
    states, commands, refs = bag.messages[st], bag.messages[cm], bag.messages[rf]
    if not states or not commands or not refs:
        empty = [t for t, m in ((st, states), (cm, commands), (rf, refs)) if not m]
        raise BagError(f"{bag.path}: no messages on {', '.join(empty)}")
    _, pos, vel, eff = cdr.joint_states([d for _, d in states], f"{bag.path}: {st}")
    _by_sample(cdr.stamps_ns([d for _, d in states]), step_ns, st, bag.path)
    _by_sample(cdr.stamps_ns([d for _, d in commands]), step_ns, cm, bag.path)
    _, u, _, _ = cdr.joint_states([d for _, d in commands], f"{bag.path}: {cm}")
    ref = cdr.float64_arrays([d for _, d in refs], f"{bag.path}: {rf}")
    _by_sample(np.rint(ref[:, 0] * 1e9).astype(np.int64), step_ns, rf, bag.path)
    m = min(len(u), len(ref), len(pos), cfg.episode.samples)
    y = pos[:, 0]
    bad = ~np.isfinite(y) | (np.abs(y) > cfg.episode.y_limit)
    diverged = bool(bad.any())
    if not diverged and m < cfg.episode.samples:
        raise BagError(f"{bag.path}: {m} of {cfg.episode.samples} samples recorded: the run is incomplete")
    return RecordedRun(ref[:m, 0], y[:m], vel[:m, 0], eff[:m, 1], eff[:m, 2], u[:m, 0],
                       ref[:m, 1], diverged, cfg)


def score_bag(path: str | Path, overrides: Iterable[str | Path] = (),
              on_warning: Callable[[str], None] = warn):
    """J, e_max, e_μ, e_σ of a recorded lock-step run (SPEC §6), as the core
    scores it; warnings (truncation, missing parameters) go to ``on_warning``."""
    from .cost import score_arrays
    bag = read_bag(path, topics=None, on_warning=on_warning)
    run = recorded_run(bag, overrides)
    return score_arrays(run["e1"], run.u, run.cfg.episode.as_array(), diverged=run.diverged), run


def describe(bag: Bag) -> str:
    """A ``ros2 bag info``-style summary."""
    dur = (bag.end_ns - bag.start_ns) / 1e9
    total = sum(bag.count(t) for t in bag.types)
    lines = [f"Files:             {', '.join(str(f) for f in bag.files)}",
             f"Bag size:          {bag.size / 2**20:.1f} MiB",
             "Storage id:        mcap",
             f"Duration:          {dur:.6f} s",
             f"Start:             {bag.start_ns / 1e9:.6f} s",
             f"End:               {bag.end_ns / 1e9:.6f} s",
             f"Messages:          {total}",
             f"Complete:          {'yes' if bag.complete else f'no ({bag.damage_summary()})'}",
             "Topic information:"]
    width = max((len(t) for t in bag.types), default=0)
    for t in sorted(bag.types):
        lines.append(f"  Topic: {t:<{width}} | Type: {bag.types[t]} | Count: {bag.count(t)} | "
                     f"Serialization Format: {bag.encodings.get(t) or 'unknown'}")
    if PARAMETERS_KEY in bag.custom_data:
        try:
            what = f"{len(json.loads(bag.custom_data[PARAMETERS_KEY]))} parameters"
        except (ValueError, TypeError):
            what = "not JSON"
        lines.append(f"custom_data:       {PARAMETERS_KEY} ({what})")
    return "\n".join(lines)
