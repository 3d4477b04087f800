"""MCAP files written by hand, messages in NumPy batches, every CRC filled in.

MCAP (https://mcap.dev/spec) is the magic ``\\x89MCAP0\\r\\n``, records
(opcode u8, content length u64, content; integers little-endian, strings and
byte arrays prefixed by their u32 length) and the magic again. A file here is

* data section: Header; Schema and Channel records as they are added; Chunks
  of about :data:`CHUNK_BYTES` of Message records (uncompressed), each chunk
  followed by one MessageIndex per channel in it; at close the Metadata
  records, then DataEnd with the CRC-32 of every byte before it (magic
  included);
* summary section: Schemas, Channels, ChunkIndexes, MetadataIndexes and
  Statistics, then one SummaryOffset per group;
* Footer, whose CRC-32 covers the summary section and the footer's own fields
  before the CRC; then the magic.

Each Chunk carries the CRC-32 of its uncompressed records. Messages come in
batches, several channels at once, and are merged in log-time order; the
records of each channel's equal-size messages are one NumPy record matrix,
scattered into the chunk buffer at offsets from a cumulative sum, so the cost
per message is a few array elements, not a Python call. ``write`` buffers
single messages and writes them through the same path. A crash loses only
what came after the last :meth:`McapWriter.sync`: readers that tolerate a
missing summary get every chunk written before it.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zstandard
from numpy.lib.stride_tricks import as_strided

from has_control.bag.mcap_format import MAGIC, MESSAGE_HEAD, Op, encode_string, encode_string_map

CHUNK_BYTES = 1 << 20               # a chunk is closed once its records pass this [bytes]
NO_TIME = 2**63 - 1                 # start time [ns] before any message, as rosbags keeps it

COMPRESSIONS = {"zstd": "zstd", "none": ""}     # our option -> MCAP's compression string


def _record(op: int, content: bytes) -> bytes:
    return struct.pack("<BQ", op, len(content)) + content


def _message_records(channel: int, log_times: np.ndarray, data: np.ndarray) -> np.ndarray:
    """Message records of equal-size messages as an (n, 31 + size) uint8 matrix;
    sequence 0 and publish time = log time, as rosbags writes them."""
    n, size = data.shape
    rec = np.empty(n, np.dtype([("op", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
                                ("log_time", "<u8"), ("publish_time", "<u8"), ("data", "u1", (size,))]))
    rec["op"], rec["length"], rec["channel"], rec["sequence"] = Op.MESSAGE, MESSAGE_HEAD - 9 + size, channel, 0
    rec["log_time"] = rec["publish_time"] = log_times
    rec["data"] = data
    return rec.view(np.uint8).reshape(n, MESSAGE_HEAD + size)


def _scatter(buffer: np.ndarray, offsets: np.ndarray, rows: np.ndarray) -> None:
    """Copy each row of ``rows`` into the flat ``buffer`` at its offset: a strided
    copy when the offsets are evenly spaced (topics interleaved sample by
    sample, the common case), else a fancy-indexed one."""
    step = int(offsets[1] - offsets[0]) if len(offsets) > 1 else rows.shape[1]
    if np.all(np.diff(offsets) == step):
        as_strided(buffer[offsets[0]:], shape=rows.shape, strides=(step, 1))[...] = rows
    else:
        buffer[offsets[:, None] + np.arange(rows.shape[1])] = rows


def _equal_size_groups(data, n: int, where: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(row indices, (rows, size) uint8 matrix) per message size of one channel's batch."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8 or data.ndim != 2 or len(data) != n:
            raise ValueError(f"{where}: data is a {data.dtype} array of shape {data.shape}: "
                             f"expected uint8 of shape ({n}, size)")
        return [(np.arange(n), np.ascontiguousarray(data))]
    if len(data) != n:
        raise ValueError(f"{where}: {len(data)} messages for {n} log times")
    lengths = np.fromiter(map(len, data), np.int64, n)
    sizes, which = np.unique(lengths, return_inverse=True)
    if len(sizes) == 1:
        return [(np.arange(n), np.frombuffer(b"".join(data), np.uint8).reshape(n, int(sizes[0])))]
    groups = []
    for k, size in enumerate(sizes):
        rows = np.flatnonzero(which == k)
        flat = np.frombuffer(b"".join([data[i] for i in rows]), np.uint8)
        groups.append((rows, flat.reshape(len(rows), int(size))))
    return groups


@dataclass
class _OpenChunk:
    """Message records waiting for their chunk to close, and their index entries."""

    parts: list[np.ndarray] = field(default_factory=list)
    channels: list[np.ndarray] = field(default_factory=list)
    log_times: list[np.ndarray] = field(default_factory=list)
    offsets: list[np.ndarray] = field(default_factory=list)      # within the uncompressed records [bytes]
    size: int = 0                                                  # [bytes]
    start: int = NO_TIME                                           # [ns]
    end: int = 0                                                   # [ns]

    def add(self, records: np.ndarray, channels: np.ndarray, log_times: np.ndarray, offsets: np.ndarray) -> None:
        self.parts.append(records)
        self.channels.append(channels)
        self.log_times.append(log_times)
        self.offsets.append(offsets + self.size)
        self.size += len(records)
        self.start, self.end = min(self.start, int(log_times.min())), max(self.end, int(log_times.max()))


class McapWriter:
    """One MCAP file being written (see the module's docstring).

    ``compression`` is ``"zstd"`` (the default) or ``"none"``. Channel and
    schema ids count from 1. Log times are int64 nanoseconds, non-negative.
    """

    def __init__(self, path: str | Path, profile: str, library: str, compression: str = "zstd",
                 chunk_bytes: int = CHUNK_BYTES):
        if compression not in COMPRESSIONS:
            raise ValueError(f"{path}: compression {compression!r}: expected one of {', '.join(COMPRESSIONS)}")
        self.path = Path(path)
        self.compression = COMPRESSIONS[compression]
        self.chunk_bytes = chunk_bytes
        self._compressor = zstandard.ZstdCompressor() if self.compression else None
        self._file = open(self.path, "xb")
        self._pos = 0                                  # bytes written [bytes]
        self._crc = 0                                  # CRC-32 of those bytes
        self._schemas: list[bytes] = []                # records, repeated in the summary
        self._channels: list[bytes] = []
        self._chunk_indexes: list[bytes] = []
        self._chunk = _OpenChunk()
        self._pending: dict[int, tuple[list[int], list[bytes]]] = {}
        self._pending_bytes = 0
        self.counts: dict[int, int] = {}               # messages per channel id
        self.start_ns, self.end_ns = NO_TIME, 0        # first and last log time [ns]
        self.closed = False
        self._emit(MAGIC + _record(Op.HEADER, encode_string(profile) + encode_string(library)))

    def _emit(self, data: bytes) -> None:
        with self._naming_path():
            self._file.write(data)
        self._pos += len(data)
        self._crc = zlib.crc32(data, self._crc)

    def _naming_path(self):
        """A context in which an OSError (a full disk) names this file."""
        import contextlib
        path = self.path

        @contextlib.contextmanager
        def naming():
            try:
                yield
            except OSError as exc:
                if exc.filename is not None:
                    raise
                raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        return naming()

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Write a Schema record; its id."""
        sid = len(self._schemas) + 1
        self._schemas.append(_record(Op.SCHEMA, struct.pack("<H", sid) + encode_string(name) + encode_string(encoding)
                                     + encode_string(data)))
        self._emit(self._schemas[-1])
        return sid

    def add_channel(self, topic: str, schema_id: int, message_encoding: str, metadata: dict[str, str]) -> int:
        """Write a Channel record; its id."""
        cid = len(self._channels) + 1
        self._channels.append(_record(Op.CHANNEL, struct.pack("<HH", cid, schema_id) + encode_string(topic)
                                      + encode_string(message_encoding) + encode_string_map(metadata)))
        self._emit(self._channels[-1])
        self.counts[cid] = 0
        return cid

    def _check(self, channel: int, first_ns: int) -> None:
        if channel not in self.counts:
            raise ValueError(f"{self.path}: no channel {channel}")
        if first_ns < 0:
            raise ValueError(f"{self.path}: negative log time {first_ns} ns on channel {channel}")

    def _count(self, channel: int, n: int, first_ns: int, last_ns: int) -> None:
        self.counts[channel] += n
        self.start_ns, self.end_ns = min(self.start_ns, first_ns), max(self.end_ns, last_ns)

    def write(self, channel: int, log_time_ns: int, data: bytes) -> None:
        """One message (buffered: written with the next batch, sync or close)."""
        log_time_ns = int(log_time_ns)
        self._check(channel, log_time_ns)
        self._count(channel, 1, log_time_ns, log_time_ns)
        times, datas = self._pending.setdefault(channel, ([], []))
        times.append(log_time_ns)
        datas.append(data)
        self._pending_bytes += MESSAGE_HEAD + len(data)
        if self._pending_bytes > self.chunk_bytes:
            self._write_pending()

    def _write_pending(self) -> None:
        pending, self._pending, self._pending_bytes = self._pending, {}, 0
        self._merge([(c, np.array(t, np.int64), _equal_size_groups(d, len(t), f"{self.path}: channel {c}"))
                     for c, (t, d) in pending.items()])

    def write_batches(self, batches: dict[int, tuple[np.ndarray, np.ndarray | list[bytes]]]) -> None:
        """Messages of several channels: ``{channel: (log_times_ns (n,), data)}``,
        data a (n, size) uint8 matrix or a list of n ``bytes``. They are merged
        in log-time order (ties: channels in the order given, then arrival)."""
        self._write_pending()
        prepared = []
        for c, (t, data) in batches.items():
            t = np.asarray(t, np.int64)
            if t.ndim != 1:
                raise ValueError(f"{self.path}: channel {c}: log times of shape {t.shape}: expected (n,)")
            self._check(c, int(t.min()) if len(t) else 0)
            prepared.append((c, t, _equal_size_groups(data, len(t), f"{self.path}: channel {c}")))
        for c, t, _ in prepared:
            if len(t):
                self._count(c, len(t), int(t.min()), int(t.max()))
        self._merge(prepared)

    def _merge(self, batches: list[tuple[int, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]]) -> None:
        """Write ``(channel, log times, equal-size groups)`` batches merged in
        log-time order into the open chunk, closing it whenever it is full."""
        matrices, times, channels, matrix_of, row_of = [], [], [], [], []
        for c, t, groups in batches:
            which, row = np.empty(len(t), np.int64), np.empty(len(t), np.int64)
            for rows, matrix in groups:
                which[rows], row[rows] = len(matrices), np.arange(len(rows))
                matrices.append(_message_records(c, t[rows], matrix))
            times.append(t)
            channels.append(np.full(len(t), c, np.uint16))
            matrix_of.append(which)
            row_of.append(row)
        if not matrices:
            return
        times, channels = np.concatenate(times), np.concatenate(channels)
        matrix_of, row_of = np.concatenate(matrix_of), np.concatenate(row_of)
        order = np.argsort(times, kind="stable")
        sizes = np.array([m.shape[1] for m in matrices], np.int64)[matrix_of[order]]
        ends = np.cumsum(sizes)                       # of each record in merged order [bytes]
        a = 0
        while a < len(order):
            base = int(ends[a - 1]) if a else 0
            b = min(int(np.searchsorted(ends, base - self._chunk.size + self.chunk_bytes, side="right")) + 1,
                    len(order))                       # up to the record that fills the chunk
            ids = order[a:b]
            offsets = ends[a:b] - sizes[a:b] - base
            records = np.empty(int(ends[b - 1]) - base, np.uint8)
            which = matrix_of[ids]
            for k in np.unique(which):
                sel = which == k
                _scatter(records, offsets[sel], matrices[k][row_of[ids[sel]]])
            self._chunk.add(records, channels[ids], times[ids], offsets)
            if self._chunk.size > self.chunk_bytes:
                self._close_chunk()
            a = b

    def _close_chunk(self) -> None:
        chunk, self._chunk = self._chunk, _OpenChunk()
        if not chunk.size:
            return
        raw = b"".join(chunk.parts)
        data = self._compressor.compress(raw) if self._compressor else raw
        start = self._pos
        head = struct.pack("<QQQI", chunk.start, chunk.end, len(raw), zlib.crc32(raw)) + encode_string(self.compression)
        self._emit(_record(Op.CHUNK, head + struct.pack("<Q", len(data)) + data))
        chunk_end = self._pos
        channels, times = np.concatenate(chunk.channels), np.concatenate(chunk.log_times)
        offsets = np.concatenate(chunk.offsets)
        index_offsets = []
        for c in np.unique(channels):
            sel = channels == c
            entries = np.empty((int(sel.sum()), 2), "<u8")
            entries[:, 0], entries[:, 1] = times[sel], offsets[sel]
            index_offsets.append(struct.pack("<HQ", c, self._pos))
            self._emit(_record(Op.MESSAGE_INDEX, struct.pack("<HI", c, entries.nbytes) + entries.tobytes()))
        self._chunk_indexes.append(_record(Op.CHUNK_INDEX, struct.pack("<QQQQ", chunk.start, chunk.end, start,
                                                                       chunk_end - start)
                                           + encode_string(b"".join(index_offsets))
                                           + struct.pack("<Q", self._pos - chunk_end) + encode_string(self.compression)
                                           + struct.pack("<QQ", len(data), len(raw))))

    def sync(self) -> None:
        """Write what is buffered, close the open chunk and flush the file: a
        crash after this loses nothing written so far."""
        self._write_pending()
        self._close_chunk()
        with self._naming_path():
            self._file.flush()

    def close(self, metadata: dict[str, dict[str, str]] | None = None) -> None:
        """Write the rest, the Metadata records ``{name: {key: value}}``, the
        summary and the footer; close the file. Closing twice does nothing."""
        if self.closed:
            return
        self._write_pending()
        self._close_chunk()
        metadata_indexes = []
        for name, values in (metadata or {}).items():
            record = _record(Op.METADATA, encode_string(name) + encode_string_map(values))
            metadata_indexes.append(_record(Op.METADATA_INDEX, struct.pack("<QQ", self._pos, len(record))
                                            + encode_string(name)))
            self._emit(record)
        self._emit(_record(Op.DATA_END, struct.pack("<I", self._crc)))
        summary_start = self._pos
        count = sum(self.counts.values())
        per_channel = b"".join(struct.pack("<HQ", c, n) for c, n in sorted(self.counts.items()))
        statistics = _record(Op.STATISTICS, struct.pack("<QHIIII", count, len(self._schemas), len(self._channels), 0,
                                                        len(metadata_indexes), len(self._chunk_indexes))
                             + struct.pack("<QQ", self.start_ns if count else 0, self.end_ns)
                             + encode_string(per_channel))
        summary, offsets = b"", b""
        for op, group in ((Op.SCHEMA, self._schemas), (Op.CHANNEL, self._channels),
                          (Op.CHUNK_INDEX, self._chunk_indexes), (Op.METADATA_INDEX, metadata_indexes),
                          (Op.STATISTICS, [statistics])):
            if group:
                data = b"".join(group)
                offsets += _record(Op.SUMMARY_OFFSET, struct.pack("<BQQ", op, summary_start + len(summary), len(data)))
                summary += data
        footer = struct.pack("<BQQQ", Op.FOOTER, 20, summary_start, summary_start + len(summary))
        summary += offsets
        self._emit(summary + footer + struct.pack("<I", zlib.crc32(footer, zlib.crc32(summary))) + MAGIC)
        with self._naming_path():
            self._file.close()
        self.closed = True
