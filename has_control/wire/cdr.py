"""Column-wise decoding of the CDR messages a run records (no ROS needed).

A lock-step run records tens of thousands of messages of one layout each
(the same names, the same array lengths), so instead of decoding message by
message we parse the first one, check that every message shares its layout,
and read each float64 field as a strided NumPy column. ``scripts/bench``
times it. Little-endian CDR (encapsulation 0x0001) only, as ROS 2 writes it.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from has_control.common.errors import HasControlError

CDR_LE = b"\x00\x01"


class CdrError(HasControlError, ValueError):
    """A message that is not the little-endian CDR we expect."""


class _Cursor:
    """Reads CDR fields; alignment is relative to the end of the 4-byte header."""

    def __init__(self, data: bytes):
        if data[:2] != CDR_LE:
            raise CdrError(f"encapsulation {data[:2].hex()}: expected little-endian CDR (0001)")
        self.data = data
        self.pos = 4

    def align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) % n

    def u32(self) -> int:
        self.align(4)
        v = struct.unpack_from("<I", self.data, self.pos)[0]
        self.pos += 4
        return v

    def string(self) -> str:
        n = self.u32()
        s = self.data[self.pos:self.pos + n - 1].decode()
        self.pos += n
        return s

    def float64_sequence(self) -> tuple[int, int]:
        """(offset of the first element, count) of a sequence<float64>."""
        n = self.u32()
        if n:
            self.align(8)
        start = self.pos
        self.pos += 8 * n
        return start, n


@dataclass(frozen=True)
class JointStateLayout:
    names: list[str]
    position: tuple[int, int]
    velocity: tuple[int, int]
    effort: tuple[int, int]
    size: int


def parse_joint_state_layout(data: bytes) -> JointStateLayout:
    """The layout of one serialized JointState (its names and where its three
    arrays lie); ``codec.joint_state_layout`` builds the layout we write."""
    c = _Cursor(data)
    c.pos += 8                       # header.stamp: int32 sec, uint32 nanosec
    c.string()                       # header.frame_id
    names = [c.string() for _ in range(c.u32())]
    pos, vel, eff = c.float64_sequence(), c.float64_sequence(), c.float64_sequence()
    return JointStateLayout(names, pos, vel, eff, c.pos)


def float64_array_layout(data: bytes) -> tuple[int, int, int]:
    """(offset, count, size) of the data of a std_msgs/Float64MultiArray."""
    c = _Cursor(data)
    for _ in range(c.u32()):         # layout.dim[]: label, size, stride
        c.string()
        c.u32()
        c.u32()
    c.u32()                          # layout.data_offset
    start, n = c.float64_sequence()
    return start, n, c.pos


def _uniform(datas: list[bytes], prefix_end: int, what: str) -> np.ndarray:
    """The messages as one (n, size) byte matrix; all must share the first one's layout."""
    size = len(datas[0])
    if any(len(d) != size for d in datas):
        raise CdrError(f"{what}: messages differ in size; expected one layout per topic")
    raw = np.frombuffer(b"".join(datas), dtype=np.uint8).reshape(len(datas), size)
    if prefix_end > 12 and not np.all(raw[:, 12:prefix_end] == raw[0, 12:prefix_end]):
        raise CdrError(f"{what}: messages differ in names or array lengths")
    return raw


def _column(raw: np.ndarray, offset: int, count: int) -> np.ndarray:
    cols = raw[:, offset:offset + 8 * count].copy()
    return cols.view("<f8").reshape(len(raw), count)


def stamps_ns(datas: list[bytes]) -> np.ndarray:
    """header.stamp (or Clock.clock) of each message [ns]."""
    raw = np.frombuffer(b"".join(d[4:12] for d in datas), dtype=np.uint8).reshape(-1, 8)
    sec = raw[:, 0:4].copy().view("<i4").ravel().astype(np.int64)
    nsec = raw[:, 4:8].copy().view("<u4").ravel().astype(np.int64)
    return sec * 1_000_000_000 + nsec


def joint_states(datas: list[bytes], what: str = "JointState") -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """(names, position, velocity, effort), each array (n, joints)."""
    lay = parse_joint_state_layout(datas[0])
    raw = _uniform(datas, lay.position[0], what)
    return (lay.names, _column(raw, *lay.position), _column(raw, *lay.velocity),
            _column(raw, *lay.effort))


def float64_arrays(datas: list[bytes], what: str = "Float64MultiArray") -> np.ndarray:
    """The data of each message as rows of an (n, k) array."""
    start, n, _ = float64_array_layout(datas[0])
    raw = _uniform(datas, start, what)
    return _column(raw, start, n)


def first_float64(data: bytes) -> float:
    """data[0] of one Float64MultiArray (the sample time our arrays lead with)."""
    start, n, _ = float64_array_layout(data)
    if n == 0:
        raise CdrError("Float64MultiArray without data: expected [t, ...]")
    return struct.unpack_from("<d", data, start)[0]


# --- encoding, column-wise (the inverse of the readers above) -----------------

class _Builder:
    """Builds one message; ``padding`` lists the alignment bytes it inserted
    (zeros here; rclpy leaves them uninitialised)."""

    def __init__(self):
        self.buf = bytearray(CDR_LE + b"\x00\x00")
        self.padding: list[int] = []

    def align(self, n: int) -> None:
        pad = (-(len(self.buf) - 4)) % n
        self.padding.extend(range(len(self.buf), len(self.buf) + pad))
        self.buf += b"\x00" * pad

    def u32(self, v: int) -> None:
        self.align(4)
        self.buf += struct.pack("<I", v)

    def string(self, s: str) -> None:
        b = s.encode() + b"\x00"
        self.u32(len(b))
        self.buf += b

    def float64_sequence(self, n: int) -> int:
        self.u32(n)
        if n:
            self.align(8)
        at = len(self.buf)
        self.buf += b"\x00" * (8 * n)
        return at


def _rows(template: bytes, n: int) -> np.ndarray:
    return np.tile(np.frombuffer(template, dtype=np.uint8), (n, 1))


def _put(raw: np.ndarray, offset: int, values: np.ndarray) -> None:
    v = np.ascontiguousarray(values, dtype="<f8").reshape(len(raw), -1)
    raw[:, offset:offset + 8 * v.shape[1]] = v.view(np.uint8).reshape(len(raw), -1)


def _put_stamps(raw: np.ndarray, stamps_ns: np.ndarray) -> None:
    ns = np.asarray(stamps_ns, dtype=np.int64)
    raw[:, 4:8] = (ns // 1_000_000_000).astype("<i4").view(np.uint8).reshape(-1, 4)
    raw[:, 8:12] = (ns % 1_000_000_000).astype("<u4").view(np.uint8).reshape(-1, 4)


def joint_state_template(names: list[str], lengths: tuple[int, int, int]) -> tuple[_Builder, list[int]]:
    """One sensor_msgs/JointState with zero stamp and values (``frame_id`` empty),
    and the offsets of its position, velocity and effort data."""
    b = _Builder()
    b.buf += b"\x00" * 8
    b.string("")
    b.u32(len(names))
    for name in names:
        b.string(name)
    return b, [b.float64_sequence(n) for n in lengths]


def float64_array_template(n: int, label: str | None = None) -> tuple[_Builder, int]:
    """One std_msgs/Float64MultiArray of ``n`` zeros, and the offset of its data.
    With ``label``, its layout has one dimension (label, size n, stride n), e.g.
    the column names; without, none."""
    b = _Builder()
    if label is None:
        b.u32(0)                     # layout.dim[]
    else:
        b.u32(1)
        b.string(label)
        b.u32(n)                     # size
        b.u32(n)                     # stride
    b.u32(0)                         # layout.data_offset
    return b, b.float64_sequence(n)


def encode_joint_states(stamps_ns, names: list[str], position, velocity=None, effort=None) -> list[bytes]:
    """sensor_msgs/JointState CDR messages, one per row of the (n, joints) arrays."""
    n, k = len(stamps_ns), len(names)
    b, offsets = joint_state_template(names, tuple(k if a is not None else 0 for a in (position, velocity, effort)))
    raw = _rows(bytes(b.buf), n)
    _put_stamps(raw, stamps_ns)
    for off, a in zip(offsets, (position, velocity, effort)):
        if a is not None:
            _put(raw, off, a)
    return [r.tobytes() for r in raw]


def encode_float64_arrays(rows, label: str | None = None) -> list[bytes]:
    """std_msgs/Float64MultiArray CDR messages, one per row (see :func:`float64_array_template`)."""
    rows = np.asarray(rows, dtype=np.float64)
    b, off = float64_array_template(rows.shape[1], label)
    raw = _rows(bytes(b.buf), len(rows))
    _put(raw, off, rows)
    return [r.tobytes() for r in raw]
