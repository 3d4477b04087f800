"""Reading bags: our own sequential MCAP scan (CRCs checked, damage and
truncation tolerated and reported), and a ``ros2 bag info``-style summary."""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

from has_control.common.errors import shown
from has_control.common.files import MiB, read_bytes, read_text
from has_control.common.json_bounded import loads_bounded
from has_control.bag.base import PARAMETERS_KEY, BagError, warn
from has_control.bag.mcap_format import FOOTER_BYTES, MAGIC, Op, decode_string, decode_string_map
from has_control.config import build_config, load_config, load_yaml, read_parameter_files


@dataclass(frozen=True)
class Damage:
    """One reason a bag is incomplete: ``kind`` (chunk, data, record or
    truncated), the warning said, and its few words for a summary."""

    kind: str
    text: str
    short: str


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
    damage: list[Damage] = field(default_factory=list)          # why not complete, one item per finding
    lost_bytes: int = 0
    size: int = 0
    on_warning: Callable[[str], None] = field(default=warn, repr=False)

    def count(self, topic: str) -> int:
        return len(self.messages.get(topic, ()))

    def topics_named(self, relative: str, msgtype: str) -> list[str]:
        """Every topic of ``msgtype`` named ``relative`` under any namespace (``/x``, ``/ns/x``)."""
        return [t for t, ty in self.types.items()
                if (t == "/" + relative or t.endswith("/" + relative)) and ty == msgtype]

    def find(self, relative: str, msgtype: str) -> str:
        """The one topic named ``relative`` under any namespace, of ``msgtype``."""
        hits = self.topics_named(relative, msgtype)
        if len(hits) != 1:
            have = ", ".join(sorted(self.types)) or "none"
            what = "no" if not hits else f"{len(hits)} topics"
            raise BagError(f"{self.path}: {what} '…/{relative}' ({msgtype}) in the bag; topics: {have}")
        return hits[0]

    def config(self, overrides: Iterable[str | Path] = ()):
        """The run's Config from the bag (else the shipped defaults, with a warning)."""
        overrides = list(overrides)
        flat = self.parameters()
        if flat is None:
            self.on_warning(f"{self.path}: no {PARAMETERS_KEY} in the bag (the run's own parameters): read with "
                            "the configuration files config/*.yaml" + (" and --config" if overrides else "")
                            + ", not necessarily those the run had")
            return load_config(overrides)
        cfg = build_config(flat, source=f"{self.path} ({PARAMETERS_KEY})")
        if overrides:
            over, sources = read_parameter_files(overrides)
            cfg = build_config(over, source=", ".join(map(str, overrides)), base=cfg)
        return cfg

    def parameters(self) -> dict | None:
        """The run's flat parameters (custom_data ``has_control/parameters``,
        a JSON object of names to values or lists of values), None if the bag
        has none; one line naming the bag if they are anything else."""
        stored = self.custom_data.get(PARAMETERS_KEY)
        if stored is None:
            return None
        return parameters_from_json(stored, f"{self.path}: custom_data {PARAMETERS_KEY}")

    @property
    def start_ns(self) -> int:
        return min((min(t for t, _ in m) for m in self.messages.values() if m), default=0)

    @property
    def end_ns(self) -> int:
        return max((max(t for t, _ in m) for m in self.messages.values() if m), default=0)

    def damage_summary(self) -> str:
        """Why the bag is incomplete, in a few words."""
        chunks = sum(d.kind == "chunk" for d in self.damage)
        rest = [d.short for d in self.damage if d.kind != "chunk"]
        parts = ([f"{chunks} corrupted chunk{'s' if chunks > 1 else ''} skipped"] if chunks else [])
        return "; ".join(parts + rest) or "incomplete"

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
        _McapScan(f, bag, wanted, on_warning).run()
    bag.sort_by_log_time(on_warning)
    return bag


#: metadata.yaml is read whole; larger is not a rosbag2 metadata file [bytes].
MAX_METADATA_BYTES = 16 * MiB


def _files_from_metadata(meta: Path, bag: Bag) -> list[Path]:
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
    bag.custom_data.update(custom_data_map(info.get("custom_data"), f"{meta}: custom_data"))
    return files


def custom_data_map(value, where: str) -> dict[str, str]:
    """rosbag2's custom_data (a map of strings to strings) as read from YAML:
    absent is empty; anything but a mapping of names to scalars is one line
    naming ``where``."""
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise BagError(f"{where}: expected a mapping of names to strings, not {type(value).__name__} {shown(value)}")
    for k, v in value.items():
        if isinstance(v, (dict, list)) or not isinstance(k, (str, int, float, bool)):
            raise BagError(f"{where}: {shown(k)}: expected a string value, not {shown(v)}")
    return {str(k): str(v) for k, v in value.items()}


def _json_kind(value) -> str:
    return ("null" if value is None else "an array" if isinstance(value, list) else "a string"
            if isinstance(value, str) else "a boolean" if isinstance(value, bool) else "a number")


def parameters_from_json(text: str, where: str) -> dict:
    """Stored flat parameters: a JSON object of names to a value or a list of
    values (as :func:`has_control.bag.write.parameters_json` writes them),
    nesting bounded; else one line naming ``where``."""
    flat = loads_bounded(text, where, BagError)
    if not isinstance(flat, dict):
        raise BagError(f"{where}: expected a JSON object of parameter names to values, not {_json_kind(flat)}")
    for k, v in flat.items():
        if isinstance(v, dict) or (isinstance(v, list) and any(isinstance(x, (dict, list)) for x in v)):
            raise BagError(f"{where}: {shown(k)} = {shown(v)}: expected a value or a list of values")
    return flat


class _ChunkDamage(Exception):
    """One chunk cannot be decompressed as it declares (the chunk is skipped, not the bag)."""


def _decompress(kind: str, data, size: int, where: str) -> bytes:
    if kind == "":
        return bytes(data)
    if kind == "zstd":
        import zstandard
        data = bytes(data)
        declared = zstandard.frame_content_size(data)
        if declared > size:                    # a damaged frame header: never allocate what it claims
            raise _ChunkDamage(f"a zstd frame declares {declared} bytes in a chunk of {size}")
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if kind == "lz4":
        import lz4.frame
        return lz4.frame.decompress(bytes(data))
    raise BagError(f"{where}: unsupported chunk compression {kind!r}")


#: A chunk's records, uncompressed, are at most this [bytes] (ours are about 1 MiB).
MAX_CHUNK_BYTES = 1 << 30


def _has_footer(buf: bytes) -> bool:
    """Whether ``buf`` ends in an MCAP footer record and the magic."""
    n = len(buf)
    at = n - 8 - FOOTER_BYTES
    return (at >= 8 and buf[n - 8:] == MAGIC and buf[at] == Op.FOOTER
            and struct.unpack_from("<Q", buf, at + 1)[0] == FOOTER_BYTES - 9)


def _check_summary(buf: bytes, f: Path, on_warning) -> None:
    """Warn if the summary section's CRC (in the footer) does not match; the
    reader does not use the summary, so the bag stays complete."""
    at = len(buf) - 8 - FOOTER_BYTES
    start, crc = struct.unpack_from("<Q", buf, at + 9)[0], struct.unpack_from("<I", buf, at + 25)[0]
    if crc and 0 < start <= at and zlib.crc32(buf[start:at + 25]) != crc:
        on_warning(f"{f}: summary section CRC mismatch (the summary is not used for reading)")


def summary_message_counts(f: Path, limit: int = 16 * 1024 * 1024) -> dict[str, int]:
    """Messages per topic as the summary section of the MCAP file ``f`` states
    them (its Channel and Statistics records), read from the file's end and
    nothing of its data section; {} when it has no whole summary (an
    unfinished file) or one larger than ``limit`` bytes."""
    try:
        with open(f, "rb") as stream:
            size = stream.seek(0, 2)
            if size < 16 + 8 + FOOTER_BYTES:
                return {}
            stream.seek(size - 8 - FOOTER_BYTES)
            tail = stream.read(8 + FOOTER_BYTES)
            if tail[-8:] != MAGIC or tail[0] != Op.FOOTER or struct.unpack_from("<Q", tail, 1)[0] != FOOTER_BYTES - 9:
                return {}
            start = struct.unpack_from("<Q", tail, 9)[0]
            end = size - 8 - FOOTER_BYTES
            if not 8 < start <= end or end - start > limit:
                return {}
            stream.seek(start)
            buf = stream.read(end - start)
        topics, counts, pos = {}, {}, 0
        while pos + 9 <= len(buf):
            op, length = buf[pos], struct.unpack_from("<Q", buf, pos + 1)[0]
            body = buf[pos + 9:pos + 9 + length]
            if op == Op.CHANNEL:
                topics[struct.unpack_from("<H", body, 0)[0]] = decode_string(body, 4)[0]
            elif op == Op.STATISTICS:
                n = struct.unpack_from("<I", body, 42)[0]
                counts = dict(struct.iter_unpack("<HQ", body[46:46 + n]))
            pos += 9 + length
        out: dict[str, int] = {}
        for channel, count in counts.items():
            if channel in topics:
                out[topics[channel]] = out.get(topics[channel], 0) + count
        return out
    except (OSError, struct.error, UnicodeDecodeError):
        return {}


def _chunk_records(rec, f: Path) -> tuple[bytes | None, str]:
    """The uncompressed records of the Chunk whose content is ``rec``, checked
    against its size and CRC (CRC 0: not computed, accepted); else None and why."""
    size, crc = struct.unpack_from("<QI", rec, 16)
    if size > MAX_CHUNK_BYTES:
        return None, f"declares {size} uncompressed bytes, more than the limit of {MAX_CHUNK_BYTES}"
    kind, q = decode_string(rec, 28)
    clen = struct.unpack_from("<Q", rec, q)[0]
    if q + 8 + clen > len(rec):
        return None, "its compressed size runs past the record"
    try:
        raw = _decompress(kind, rec[q + 8:q + 8 + clen], size, str(f))
    except _ChunkDamage as exc:
        return None, str(exc)
    except BagError:                                          # a compression we cannot read: the whole bag
        raise
    except Exception as exc:                                  # zstd/lz4 on damaged bytes
        return None, f"does not decompress ({type(exc).__name__})"
    if len(raw) != size:
        return None, f"decompresses to {len(raw)} bytes, not {size}"
    if crc and zlib.crc32(raw) != crc:
        return None, "CRC mismatch"
    return raw, ""


class _McapScan:
    """One MCAP file scanned record by record (chunks decompressed and checked
    as they come). A chunk whose CRC or size does not match is named, skipped
    and the bag marked incomplete; so is a data section whose CRC does not
    match (DataEnd), and a record that cannot be parsed ends the scan: as a
    truncation if the file has no footer, as damage if it has one."""

    def __init__(self, f: Path, bag: Bag, wanted: set[str] | None, on_warning):
        self.f, self.bag, self.wanted, self.on_warning = f, bag, wanted, on_warning
        self.schemas: dict[int, str] = {}
        self.channels: dict[int, str] = {}
        self.chunks = self.bad_chunks = 0
        self.data_end = self.data_checked = False

    def run(self) -> None:
        buf = read_bytes(self.f, error=BagError)
        self.bag.size += len(buf)
        if buf[:8] != MAGIC:
            raise BagError(f"{self.f}: not an MCAP file (no MCAP magic at the start)")
        pos = 8
        try:
            pos = self._data_section(buf)
        except (struct.error, UnicodeDecodeError, BagError):
            pass                                              # a torn record: stop at the last good one
        self._finish(buf, pos)

    def _damaged(self, kind: str, what: str, short: str = "") -> None:
        self.bag.complete = False
        self.bag.damage.append(Damage(kind, what, short or what))
        self.on_warning(f"{self.f}: {what}")

    def _data_section(self, buf: bytes) -> int:
        """Read the top-level records up to DataEnd or the footer; the position reached."""
        view, n, pos = memoryview(buf), len(buf), 8
        while pos + 9 <= n:
            op = buf[pos]
            ln = struct.unpack_from("<Q", buf, pos + 1)[0]
            body = pos + 9
            if body + ln > n:
                break                                         # truncated (or damaged) record
            rec = view[body:body + ln]
            if op == Op.CHUNK:
                self._chunk(rec, pos)
            elif op in (Op.SCHEMA, Op.CHANNEL, Op.MESSAGE):
                self._records(view[pos:body + ln], str(self.f))
            elif op == Op.METADATA:
                name, q = decode_string(rec, 0)
                meta, _ = decode_string_map(rec, q)
                if name == "rosbag2" and "serialized_metadata" in meta:
                    _custom_from_serialized(meta["serialized_metadata"], self.bag, self.f)
            elif op == Op.DATA_END:
                crc = struct.unpack_from("<I", rec, 0)[0] if ln >= 4 else 0
                if crc and zlib.crc32(view[:pos]) != crc and not self.bad_chunks:
                    self._damaged("data", "data section CRC mismatch (a record outside the chunks is damaged)",
                                  "data section CRC mismatch")
                self.data_end, self.data_checked = True, crc != 0
                return body + ln
            elif op == Op.FOOTER:
                return pos
            pos = body + ln
        return pos

    def _chunk(self, rec, pos: int) -> None:
        raw, why = _chunk_records(rec, self.f)
        if raw is None:
            self.bad_chunks += 1
            self._damaged("chunk", f"chunk at offset {pos} is corrupted ({why}): skipped")
            return
        try:
            self._records(memoryview(raw), f"{self.f}: chunk at offset {pos}")
            self.chunks += 1
        except (struct.error, UnicodeDecodeError, BagError):
            self.bad_chunks += 1
            self._damaged("chunk", f"chunk at offset {pos} holds a malformed record: skipped")

    def _records(self, records, origin: str) -> None:
        """Schemas, channels and messages of ``records``, kept only if all parse."""
        got: list[tuple[str, int, bytes]] = []
        p, end = 0, len(records)
        while p + 9 <= end:
            op = records[p]
            ln = struct.unpack_from("<Q", records, p + 1)[0]
            body = p + 9
            if body + ln > end:
                raise BagError(f"{origin}: a record runs past its end")
            if op == Op.MESSAGE:
                cid = struct.unpack_from("<H", records, body)[0]
                topic = self.channels.get(cid)
                if topic is not None and (self.wanted is None or topic in self.wanted):
                    t = struct.unpack_from("<Q", records, body + 6)[0]
                    got.append((topic, t, bytes(records[body + 22:body + ln])))
            elif op == Op.SCHEMA:
                sid = struct.unpack_from("<H", records, body)[0]
                self.schemas[sid], _ = decode_string(records, body + 2)
            elif op == Op.CHANNEL:
                self._channel(records, body)
            p = body + ln
        for topic, t, data in got:
            self.bag.messages[topic].append((t, data))

    def _channel(self, records, body: int) -> None:
        cid, sid = struct.unpack_from("<HH", records, body)
        topic, q = decode_string(records, body + 4)
        enc, q = decode_string(records, q)
        meta, _ = decode_string_map(records, q)
        if cid not in self.channels:
            self.channels[cid] = topic
            self.bag.types.setdefault(topic, self.schemas.get(sid, ""))
            self.bag.encodings.setdefault(topic, enc)
            self.bag.qos.setdefault(topic, meta.get("offered_qos_profiles", ""))
            self.bag.messages.setdefault(topic, [])

    def _finish(self, buf: bytes, pos: int) -> None:
        """What the end of the scan says: a whole file, damage after an intact data section, or a truncation."""
        footer = _has_footer(buf)
        if self.data_end and footer:
            _check_summary(buf, self.f, self.on_warning)
            return
        if self.data_end and self.data_checked:          # the data section is all there and its CRC checked
            self.on_warning(f"{self.f}: the summary or footer after the data section is damaged; "
                            "the data section is intact (its CRC checked)")
            return
        lost = len(buf) - pos
        messages = sum(map(len, self.bag.messages.values()))
        self.bag.lost_bytes += lost
        if footer:
            self._damaged("record", f"damaged record at offset {pos} (the footer is there: not a truncation): "
                                    f"kept {self.chunks} chunks, {messages} messages; the last {lost} bytes unread",
                          f"damaged record at offset {pos}")
            return
        self.bag.complete = False
        self.bag.damage.append(Damage("truncated", f"truncated, {lost} bytes lost", f"truncated, {lost} bytes lost"))
        self.on_warning(f"{self.f}: truncated (no MCAP footer): kept {self.chunks} complete chunks, "
                        f"{messages} messages; lost the last {lost} bytes")


def _custom_from_serialized(text: str, bag: Bag, f: Path) -> None:
    """custom_data of the MCAP file's rosbag2 Metadata record (inside the
    CRC-checked data), if metadata.yaml gave none. metadata.yaml's wins (it may
    be edited on purpose), but never silently: a difference is warned about."""
    try:
        doc = load_yaml(text, f"{f} (rosbag2 metadata)", BagError)
        info = doc.get("rosbag2_bagfile_information", doc)     # rosbag2 stores the inner mapping
        if not isinstance(info, dict):
            return
        stored = custom_data_map(info.get("custom_data"), f"{f}: the rosbag2 metadata record's custom_data")
    except BagError as exc:
        if not bag.custom_data:                # it would have been used: refuse it
            raise
        bag.on_warning(str(exc))
        return
    if not bag.custom_data:
        bag.custom_data.update(stored)
    elif stored and stored != bag.custom_data:
        keys = sorted(k for k in set(stored) | set(bag.custom_data) if stored.get(k) != bag.custom_data.get(k))
        bag.on_warning(f"{f}: metadata.yaml's custom_data ({', '.join(keys)}) differs from the copy inside the "
                       "MCAP file; using metadata.yaml's (edited, or damaged: it carries no CRC)")


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
            what = f"{len(bag.parameters())} parameters"
        except BagError as exc:
            what = f"invalid: {str(exc).rsplit(': ', 1)[-1]}"
        lines.append(f"custom_data:       {PARAMETERS_KEY} ({what})")
    return "\n".join(lines)
