"""The control loop's messages as fixed CDR layouts, read and written by compiled code.

Every message of the loop has one layout for a whole run: the same joint
names, the same array lengths, an empty ``frame_id``. So a message is a
template (one instance, serialised once, values zero) plus the offsets of its
stamp and of its float64 values. Encoding copies nothing but the values into
a preallocated buffer; decoding checks that every byte outside the stamp and
the values equals the template (so a message of another layout is refused,
never misread) and reads the values. The bytes are exactly what rclpy's
``serialize_message`` gives for the same message (a test proves it).

Little-endian CDR (encapsulation 0x0001), as ROS 2 writes it. No ROS import:
the templates come from :mod:`has_control.wire.cdr`.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numba import njit

from has_control.wire import cdr
from has_control.core.jit import INLINE

#: What a decoder returns for a message it refuses.
MALFORMED = -1      # not the expected layout (size, names, lengths, stamp off the sample grid)
NOT_FINITE = -2     # the layout is right but a value is NaN or infinite


@dataclass(frozen=True)
class Layout:
    """One message layout: ``template`` bytes, which of them are fixed, which
    are alignment padding, and where the float64 values sit (``values[k]`` is
    the byte offset of value k)."""

    template: np.ndarray     # uint8, one message with zero stamp, values and padding
    fixed: np.ndarray        # bool per byte: must equal the template when decoding
    padding: np.ndarray      # bool per byte: CDR alignment (rclpy leaves it uninitialised)
    values: np.ndarray       # int64 offsets of the values, in order
    stamped: bool            # bytes 4..12 are a builtin_interfaces/Time

    @property
    def size(self) -> int:
        return len(self.template)

    def buffer(self) -> np.ndarray:
        """A preallocated message of this layout to encode into."""
        return self.template.copy()

    def encode(self, values, stamp_ns: int = 0) -> bytes:
        """One message with these values (and stamp), in Python: for the rare
        messages (the gains); the loop's messages use the compiled writers."""
        buf = bytearray(self.template.tobytes())
        if self.stamped:
            struct.pack_into("<iI", buf, 4, *divmod(stamp_ns, 1_000_000_000))
        for off, v in zip(self.values, values, strict=True):
            struct.pack_into("<d", buf, int(off), float(v))
        return bytes(buf)

    def read(self, data: bytes) -> list[float] | None:
        """The values of a message of this layout, in Python (None: another layout,
        e.g. a Float64MultiArray of another length or label); for the rare readers."""
        if len(data) != self.size:
            return None
        raw = np.frombuffer(data, dtype=np.uint8)
        if not np.array_equal(raw[self.fixed], self.template[self.fixed]):
            return None
        return [struct.unpack_from("<d", data, int(off))[0] for off in self.values]


def _layout(builder, values: list[int], stamped: bool) -> Layout:
    t = np.frombuffer(bytes(builder.buf), dtype=np.uint8).copy()
    padding = np.zeros(len(t), dtype=np.bool_)
    padding[builder.padding] = True
    fixed = ~padding
    if stamped:
        fixed[4:12] = False
    for off in values:
        fixed[off:off + 8] = False
    return Layout(t, fixed, padding, np.asarray(values, dtype=np.int64), stamped)


def joint_state_layout(names: list[str], position: int, velocity: int, effort: int) -> Layout:
    """sensor_msgs/JointState with ``names`` and arrays of these lengths (each 0 or one per joint)."""
    if any(n not in (0, len(names)) for n in (position, velocity, effort)):
        raise ValueError("JointState arrays are empty or one value per joint")
    b, offsets = cdr.joint_state_template(names, (position, velocity, effort))
    values = [start + 8 * j for start, n in zip(offsets, (position, velocity, effort)) for j in range(n)]
    return _layout(b, values, stamped=True)


def float64_array_layout(columns: tuple[str, ...]) -> Layout:
    """std_msgs/Float64MultiArray of one value per column, its layout's one
    dimension labelled with the column names (what a viewer such as Foxglove shows)."""
    b, start = cdr.float64_array_template(len(columns), column_label(columns))
    return _layout(b, [start + 8 * j for j in range(len(columns))], stamped=False)


def column_label(columns: tuple[str, ...]) -> str:
    """The dimension label of a Float64MultiArray with these columns."""
    return ",".join(columns)


def clock_layout() -> Layout:
    """rosgraph_msgs/Clock: the stamp alone."""
    b = cdr._Builder()
    b.buf += bytes(8)
    return _layout(b, [], stamped=True)


# --- compiled primitives ------------------------------------------------------
# ``scratch`` is a float64[1] array and ``sb`` its uint8 view: the bytes of one
# value go through it, so nothing is allocated per message.

@njit(**INLINE)
def get_f64(data, offset, scratch, sb):
    """The little-endian float64 at ``offset`` of ``data`` (bytes or uint8 array)."""
    for k in range(8):
        sb[k] = data[offset + k]
    return scratch[0]


@njit(**INLINE)
def put_f64(buf, offset, value, scratch, sb):
    """Write ``value`` as a little-endian float64 at ``offset`` of ``buf``."""
    scratch[0] = value
    for k in range(8):
        buf[offset + k] = sb[k]


@njit(**INLINE)
def put_stamp(buf, ns):
    """builtin_interfaces/Time of ``ns`` [ns] at bytes 4..12 (sec int32, nanosec uint32)."""
    sec = ns // 1_000_000_000
    nsec = ns - sec * 1_000_000_000
    for k in range(4):
        buf[4 + k] = (sec >> (8 * k)) & 0xFF
        buf[8 + k] = (nsec >> (8 * k)) & 0xFF


@njit(**INLINE)
def get_stamp(data):
    """The stamp at bytes 4..12 [ns] (sec read as a signed int32)."""
    sec = 0
    nsec = 0
    for k in range(4):
        sec |= np.int64(data[4 + k]) << (8 * k)
        nsec |= np.int64(data[8 + k]) << (8 * k)
    if sec >= 2 ** 31:
        sec -= 2 ** 32
    return sec * 1_000_000_000 + nsec


@njit(**INLINE)
def sample_of_stamp(data, step_ns):
    """Sample index i of a stamp i·Δt, or MALFORMED if the stamp is not on the grid."""
    ns = get_stamp(data)
    if ns < 0:
        return MALFORMED
    i = ns // step_ns
    if i * step_ns != ns:
        return MALFORMED
    return i


#: Bytes rclpy may append after a message's last field (its serializer pads
#: JointState with empty arrays to 68 bytes where CDR needs 60).
TRAILING = 8


@njit(**INLINE)
def matches(data, template, fixed):
    """``data`` has the template's size (give or take TRAILING bytes after the
    last field) and the template's bytes wherever ``fixed``."""
    if not len(template) <= len(data) <= len(template) + TRAILING:
        return False
    for k in range(len(template)):
        if fixed[k] and data[k] != template[k]:
            return False
    return True


__all__ = ["Layout", "MALFORMED", "NOT_FINITE", "joint_state_layout", "float64_array_layout",
           "clock_layout", "get_f64", "put_f64", "put_stamp", "get_stamp", "sample_of_stamp", "matches"]
