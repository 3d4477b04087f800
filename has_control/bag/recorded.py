"""One reader of recorded samples: a bag's states and commands on the sample
grid, as a machine records them (``identify``, ``plot``, ``score`` and
``bag-info`` read through it).

Two layouts, told apart by the topics the bag has:

* **has_control**: ``…/state`` and ``…/command`` (sensor_msgs/JointState, the
  layout of :mod:`has_control.wire.topics`); the command carries the stamp of
  the state it answers, so they pair by stamp.
* **ros2_control** (read when ``…/state`` is absent): joint_state_broadcaster's
  ``/joint_states`` read through the ``state_interfaces`` mapping of
  :mod:`has_control.wire.joint_mapping`, and a forward_command_controller's
  ``std_msgs/Float64MultiArray`` commands, which have no header: **the first
  command logged after state k answers state k** (log-time order).

Stamps: simulation time (a stamp below :data:`EPOCH_NS`) puts sample i at
i·Δt; any later epoch (a wall clock) is a run whose sample 0 is the first
state, the grid's origin fitted to the stamps (median offset). Each message
goes to its nearest sample when within :data:`TOLERANCE` of a step (±0.4 Δt,
120 µs at 0.3 ms), else one line naming the bag, topic, message index and
offset. On the grid: repeated identical messages for a sample are collapsed
and counted; two different states for one sample are refused naming the
sample; samples without a state are counted (dropped); states with
non-finite values, or values beyond :data:`IMPOSSIBLE`, are counted, read as
NaN and flagged (each consumer says what it does with them); a truncated or malformed CDR payload is one line naming the
message. Every finding is one line on ``bag.on_warning`` before any result.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from has_control.bag.base import BagError, warn
from has_control.bag.read import MAX_METADATA_BYTES, Bag, read_bag, summary_message_counts
from has_control.common.errors import HasControlError
from has_control.config import load_yaml
from has_control.wire import cdr
from has_control.wire.joint_mapping import (
    DEFAULT_COMMAND_TOPIC, DEFAULT_JOINT_STATES_TOPIC, DEFAULT_STATE_INTERFACES, INTERFACE_KINDS,
    parse_state_interfaces, read_state, resolve,
)
from has_control.wire.topics import COMMAND, COMMAND_NAMES, FLOAT64_ARRAY, JOINT_STATE, STATE, TRUE_STATE

#: A message is taken as its nearest sample when its stamp is within this of a step from it.
TOLERANCE = 0.4
#: Stamps from this on [ns] (one day) are an epoch (a wall clock), not simulation time.
EPOCH_NS = 86_400 * 1_000_000_000
#: Stamps reaching this many samples beyond the message count are not one run.
MAX_SPREAD = 100
#: Magnitudes no sensor of this actuator reads (y [m], ẏ [m/s], P1, P2 [Pa]): a state beyond is read as
#: not measured (NaN), counted in the non-finite states' line (a 1e300 sample must not set a fit's weights
#: or a figure's axes).
IMPOSSIBLE = np.array([1e2, 1e3, 1e10, 1e10])
#: The most samples a reader of recorded samples takes (60 s at the reference 0.3 ms step): its
#: memory grows with the recording (every message is held), so a longer run is refused up front,
#: from metadata.yaml's message counts, before a message is read (docs/bags.md: the peaks measured).
MAX_SAMPLES = 200_000
#: The has_control layout's command: joint ``valve``, position [m].
VALVE = [(COMMAND_NAMES[0], 0)]

HAS_CONTROL, ROS2_CONTROL = "has_control", "ros2_control"
BY_STAMP = "each command carries its state's stamp"
BY_LOG_TIME = "the first command logged after state k answers state k (log-time order)"

_MALFORMED = (cdr.CdrError, struct.error, ValueError, IndexError, UnicodeDecodeError)


@dataclass(frozen=True)
class Reading:
    """How to read a bag (the CLI's ``--state-interfaces``, ``--command-topic``)."""

    state_interfaces: tuple[str, ...] | None = None    # joint/interface x 4 (default: joint_mapping's)
    command_topic: str | None = None                   # default: ``…/command``, else joint_mapping's


@dataclass
class Recording:
    """States x (n, 4) = (y [m], ẏ [m/s], P1 [Pa], P2 [Pa]) and commands u (n,)
    [m] on samples 0 .. n − 1 of the grid t = i·Δt, NaN where nothing was recorded."""

    path: str
    layout: str
    state_topic: str
    command_topic: str | None
    rule: str
    step: float                 # [s]
    origin_ns: int              # stamp of sample 0 [ns]
    x: np.ndarray
    u: np.ndarray
    state: np.ndarray           # bool (n,): a state was recorded for the sample
    command: np.ndarray         # bool (n,): a command was recorded for the sample
    first: int                  # the first sample with a state
    nonfinite: int = 0          # state messages with a non-finite value
    notes: list[str] = field(default_factory=list)

    @property
    def samples(self) -> int:
        return len(self.u)

    @property
    def epoch(self) -> bool:
        return self.origin_ns >= EPOCH_NS

    @property
    def dropped(self) -> np.ndarray:
        """Samples from the first state to the last without a state."""
        return np.flatnonzero(~self.state[self.first:]) + self.first

    def time_ns(self, t_ns: np.ndarray) -> np.ndarray:
        """Times [ns] of the run's own arrays (the leading t of the controller's
        topics, simulation time) relative to sample 0."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if self.epoch and len(t_ns) and t_ns.min() < EPOCH_NS:
            return t_ns                         # simulation time beside wall-clock stamps: from sample 0
        return t_ns - self.origin_ns


def has_topic(bag: Bag, relative: str, msgtype: str) -> bool:
    return bool(bag.topics_named(relative, msgtype))


def layout_of(bag: Bag, reading: Reading = Reading(), true_state: bool = False) -> tuple[str, str, str | None]:
    """(layout, state topic, command topic or None) of ``bag`` (see the module)."""
    if has_topic(bag, STATE, JOINT_STATE):
        st = bag.find(TRUE_STATE if true_state and has_topic(bag, TRUE_STATE, JOINT_STATE) else STATE, JOINT_STATE)
        if reading.command_topic:
            return HAS_CONTROL, st, _named(bag, reading.command_topic)
        return HAS_CONTROL, st, (bag.find(COMMAND, JOINT_STATE) if has_topic(bag, COMMAND, JOINT_STATE) else None)
    js = [t for t, ty in bag.types.items() if ty == JOINT_STATE
          and (t == DEFAULT_JOINT_STATES_TOPIC or t.endswith(DEFAULT_JOINT_STATES_TOPIC))]
    if len(js) != 1:
        have = ", ".join(sorted(bag.types)) or "none"
        what = "no" if not js else f"{len(js)} topics"
        raise BagError(f"{bag.path}: no '…/{STATE}' ({JOINT_STATE}, has_control layout) and {what} "
                       f"'{DEFAULT_JOINT_STATES_TOPIC}' (ros2_control layout) in the bag; topics: {have}")
    if reading.command_topic:
        return ROS2_CONTROL, js[0], _named(bag, reading.command_topic)
    if bag.types.get(DEFAULT_COMMAND_TOPIC) == FLOAT64_ARRAY:
        return ROS2_CONTROL, js[0], DEFAULT_COMMAND_TOPIC
    cmds = [t for t, ty in bag.types.items() if ty == FLOAT64_ARRAY and t.endswith("/commands")]
    return ROS2_CONTROL, js[0], (cmds[0] if len(cmds) == 1 else None)


def _named(bag: Bag, topic: str) -> str:
    if bag.types.get(topic) not in (JOINT_STATE, FLOAT64_ARRAY):
        have = ", ".join(sorted(bag.types)) or "none"
        what = f"is {bag.types[topic]}" if topic in bag.types else "is not in the bag"
        raise BagError(f"{bag.path}: --command-topic {topic} {what} (expected {JOINT_STATE} or {FLOAT64_ARRAY}); "
                       f"topics: {have}")
    return topic


def read_run_bag(path: str | Path, on_warning=warn) -> Bag:
    """The bag at ``path`` for ``identify``, ``score`` and ``plot``: refused
    up front (one line naming the limit) when metadata.yaml counts more than
    MAX_SAMPLES messages on a topic, or a bare .mcap's summary does (one
    without a summary is counted once read, :func:`read_recording`)."""
    path = Path(path)
    counts, source = (_metadata_counts(path / "metadata.yaml"), "metadata.yaml") if path.is_dir() else ({}, "")
    if not counts and path.suffix == ".mcap" and path.is_file():
        counts, source = summary_message_counts(path, MAX_METADATA_BYTES), "the MCAP summary"
    long = {t: c for t, c in counts.items() if c > MAX_SAMPLES}
    if long:
        t, c = max(long.items(), key=lambda tc: tc[1])
        raise BagError(f"{path}: {t} has {c} messages ({source}): more than the {MAX_SAMPLES} samples "
                       f"(60 s at 0.3 ms) identify, score and plot read, as their memory grows with the "
                       "recording; record or split the run into shorter bags")
    return read_bag(path, topics=None, on_warning=on_warning)


def _metadata_counts(meta: Path) -> dict[str, int]:
    """Messages per topic as metadata.yaml states them; {} when it does not
    (read_bag then says what is wrong with the file)."""
    try:
        if not meta.is_file() or meta.stat().st_size > MAX_METADATA_BYTES:
            return {}
        info = load_yaml(meta.read_text(), str(meta), BagError, "malformed YAML").get("rosbag2_bagfile_information")
        out = {}
        for entry in info.get("topics_with_message_count") or []:
            name, count = entry["topic_metadata"]["name"], entry["message_count"]
            if isinstance(name, str) and isinstance(count, int):
                out[name] = count
        return out
    except (HasControlError, AttributeError, KeyError, TypeError, OSError, UnicodeDecodeError):
        return {}


def read_recording(bag: Bag, step: float | None, reading: Reading = Reading(),
                   true_state: bool = False, emit: bool = True) -> Recording:
    """The states and commands of ``bag`` on the grid of ``step`` [s] (None:
    Δt fitted to the state stamps); ``true_state``: the plant's true state
    where the bag has one (scoring). One line per finding on ``bag.on_warning``
    (``emit``; else in ``notes``, for a caller that may refuse the recording first)."""
    layout, st, cm = layout_of(bag, reading, true_state)
    where = f"{bag.path}: {st}"
    messages = bag.messages.get(st, [])
    if not messages:
        raise BagError(f"{where}: no messages")
    if len(messages) > MAX_SAMPLES:
        raise BagError(f"{where}: {len(messages)} messages: more than the {MAX_SAMPLES} samples (60 s at 0.3 ms) "
                       "identify, score and plot read; record or split the run into shorter bags")
    entries = reading.state_interfaces or DEFAULT_STATE_INTERFACES
    try:
        mapping = parse_state_interfaces(entries)
    except ValueError as exc:
        raise BagError(f"--state-interfaces: {str(exc).replace('parameter state_interfaces', '').strip(' =:')}") \
            from None
    stamps, x = joint_values(messages, mapping, where, f"state_interfaces {' '.join(entries)}")
    if step is None:
        step = fitted_step(stamps)
    step_ns = step * 1e9
    origin = _origin(stamps, step_ns)
    idx, worst = on_grid(stamps, origin, step_ns, where)
    notes: list[str] = []
    if origin >= EPOCH_NS:
        notes.append(f"{where}: stamps from {stamps.min() / 1e9:.6f} s, not simulation time: sample 0 is "
                     f"the first state (grid origin {origin / 1e9:.9f} s, fitted to the stamps)")
    if worst > 0.01:
        notes.append(f"{where}: stamps up to {worst * step * 1e6:.1f} µs off the {step * 1e3:g} ms grid: each "
                     f"message taken as its nearest sample (tolerance ±{TOLERANCE:g} step = "
                     f"{TOLERANCE * step * 1e6:g} µs)")
    finite = np.isfinite(x).all(axis=1)
    impossible = finite & (np.abs(x) > IMPOSSIBLE[:x.shape[1]]).any(axis=1)
    if impossible.any():                 # read as not measured: every consumer treats it as a bad sample
        x = x.copy()
        x[impossible] = math.nan
        finite &= ~impossible
    n = int(idx.max()) + 1
    if n > MAX_SPREAD * len(idx) + 1_000_000:
        raise BagError(f"{where}: stamps up to sample {n - 1} for {len(idx)} messages: not one run")
    xs, have, repeated = _collapse(n, idx, x, where, "states", step)
    if repeated:
        notes.append(f"{where}: {repeated} repeated identical message{'s' * (repeated != 1)} collapsed "
                     "(one state per sample)")
    nonfinite = int((~finite).sum())
    if nonfinite:
        wild = int(impossible.sum())
        bad = np.flatnonzero(~finite)
        notes.append(f"{where}: {nonfinite} state{'s' * (nonfinite != 1)} with non-finite values (NaN or inf"
                     + (f"; {wild} beyond what a sensor of this actuator reads, |y| > {IMPOSSIBLE[0]:g} m, "
                        f"|ẏ| > {IMPOSSIBLE[1]:g} m/s or |P| > {IMPOSSIBLE[2]:g} Pa" if wild else "")
                     + f"), the first message {int(bad[0])}: read as not measured")
    first = int(np.argmax(have))
    gaps = np.flatnonzero(~have[first:])
    if len(gaps):
        runs = np.split(gaps, np.flatnonzero(np.diff(gaps) != 1) + 1)
        longest = max(runs, key=len)
        notes.append(f"{where}: {len(gaps)} of {n - first} samples have no state (dropped; "
                     f"{len(runs)} gap{'s' * (len(runs) != 1)}, the longest {len(longest)} "
                     f"sample{'s' * (len(longest) != 1)} from t = {(longest[0] + first) * step:.6f} s)")
    u = np.full(n, math.nan)
    got = np.zeros(n, bool)
    rule = ""
    if cm is not None and bag.messages.get(cm):
        cwhere = f"{bag.path}: {cm}"
        if bag.types[cm] == JOINT_STATE:
            rule = BY_STAMP
            cst, cu = joint_values(bag.messages[cm], VALVE, cwhere, "the valve command (joint valve, position)")
            cidx, _ = on_grid(cst, origin, step_ns, cwhere)
            keep = cidx < n
            u1, got, crep = _collapse(n, cidx[keep], cu[keep], cwhere, "commands", step)
            u = u1[:, 0]
            if crep:
                notes.append(f"{cwhere}: {crep} repeated identical command{'s' * (crep != 1)} collapsed")
        else:
            rule = BY_LOG_TIME
            u, got, extra, early = _by_log_time(n, [t for t, _ in messages], idx, bag.messages[cm], cwhere)
            if extra or early:
                notes.append(f"{cwhere}: {extra} command{'s' * (extra != 1)} not first after their state and "
                             f"{early} logged before the first state: ignored")
    if layout == ROS2_CONTROL:
        notes.insert(0, f"{bag.path}: read in the ros2_control layout: states {st} ({' '.join(entries)}), "
                        f"commands {cm or 'none'}" + (f" ({rule})" if rule else ""))
    for line in notes if emit else ():
        bag.on_warning(line)
    state_ok = have.copy()
    return Recording(str(bag.path), layout, st, cm, rule, step, origin, xs, u, state_ok, got, first,
                     nonfinite, notes)


def joint_values(messages, mapping, where: str, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(header stamps [ns], values (n, len(mapping))) of JointState messages
    through a ``joint/interface`` mapping; a message that is not a readable
    JointState, or lacks a mapped joint, is one line naming it."""
    datas = [d for _, d in messages]
    try:
        names, pos, vel, eff = cdr.joint_states(datas, where)
        _unique(names, 0, where)
        if all(len(d) >= 12 for d in datas):
            arrays = (pos, vel, eff)
            res = resolve(names, mapping)
            if all(0 <= j < arrays[k].shape[1] for j, k in res):
                return cdr.stamps_ns(datas), np.column_stack([arrays[k][:, j] for j, k in res])
            _missing(names, mapping, res, 0, where, what, [a.shape[1] for a in arrays])
    except _MALFORMED:
        pass
    stamps, rows, cache = np.zeros(len(datas), np.int64), np.zeros((len(datas), len(mapping))), {}
    for k, d in enumerate(datas):
        try:
            lay = cdr.parse_joint_state_layout(d)
            ok = lay.size <= len(d)
        except _MALFORMED:
            ok = False
        if not ok:
            if d[:2] in (b"\x00\x00", b"\x00\x02"):     # CDR_BE, PL_CDR_BE: the encapsulation header
                raise BagError(f"{where}: message {k}: big-endian CDR (encapsulation {d[:2].hex()}): only "
                               "little-endian CDR (0001) is read")
            raise BagError(f"{where}: message {k}: truncated or malformed CDR payload ({len(d)} bytes): "
                           f"not a {JOINT_STATE}")
        key = tuple(lay.names)
        if key not in cache:
            _unique(lay.names, k, where)
            cache[key] = resolve(lay.names, mapping)
        arrays = [np.frombuffer(d, "<f8", n, off) for off, n in (lay.position, lay.velocity, lay.effort)]
        v = read_state(arrays, cache[key])
        if v is None:
            _missing(lay.names, mapping, cache[key], k, where, what, [len(a) for a in arrays])
        sec, nsec = struct.unpack_from("<iI", d, 4)
        stamps[k], rows[k] = sec * 1_000_000_000 + nsec, v
    return stamps, rows


def _unique(names, k: int, where: str) -> None:
    """One line when a JointState names a joint twice: which copy is the joint's is not said."""
    twice = sorted({n for n in names if list(names).count(n) > 1})
    if twice:
        raise BagError(f"{where}: message {k}: joint{'s' * (len(twice) > 1)} {', '.join(twice)} named twice in one "
                       "JointState: refused (which copy is the joint's?)")


def _missing(names, mapping, res, k: int, where: str, what: str, lengths=None):
    """One line: the mapped joint/interface pairs message k lacks (a joint not named, or an interface
    array shorter than the joint's index, e.g. a JointState without effort)."""
    lack = [f"{joint}/{INTERFACE_KINDS[kind]}" for (joint, kind), (j, c) in zip(mapping, res)
            if j < 0 or (lengths is not None and j >= lengths[c])] or \
        [f"{joint}/{INTERFACE_KINDS[kind]}" for joint, kind in mapping]
    raise BagError(f"{where}: message {k}: joints {list(names)} lack {', '.join(lack)} of {what}: "
                   "a bag of another model (or set --state-interfaces)")


def fitted_step(stamps: np.ndarray) -> float:
    """Δt [s] of stamps on a grid with gaps: each step between distinct stamps
    is a whole number of the median step; the least-squares slope."""
    u = np.unique(np.asarray(stamps, dtype=np.int64))
    if len(u) < 2:
        raise BagError("one state: no sample step to read from the recording (give simulation.step with --config)")
    rel = (u - u[0]).astype(np.float64)
    d = np.diff(rel)
    k = np.maximum(1.0, np.rint(d / np.median(d)))
    idx = np.concatenate([[0.0], np.cumsum(k)])
    return float(np.polyfit(idx, rel, 1)[0]) / 1e9


def _origin(stamps: np.ndarray, step_ns: float) -> int:
    """Stamp of sample 0 [ns]: 0 for simulation time, else the first state
    plus the median offset of the stamps from its grid."""
    s0 = int(stamps.min())
    if s0 < EPOCH_NS:
        return 0
    rel = (stamps - s0).astype(np.float64)
    off = rel - np.rint(rel / step_ns) * step_ns
    return s0 + int(round(float(np.median(off))))


def on_grid(stamps: np.ndarray, origin: int, step_ns: float, where: str) -> tuple[np.ndarray, float]:
    """(sample of each stamp, the largest offset [steps]); beyond :data:`TOLERANCE`
    or before sample 0: one line naming the message."""
    x = (np.asarray(stamps, dtype=np.int64) - origin) / step_ns
    idx = np.rint(x).astype(np.int64)
    off = np.abs(x - idx)
    bad = (off > TOLERANCE) | (idx < 0)
    if bad.any():
        k = int(np.argmax(bad))
        why = ("before sample 0" if idx[k] < 0 else
               f"{(x[k] - idx[k]) * step_ns / 1e3:+.1f} µs from sample {idx[k]}, beyond the tolerance of "
               f"±{TOLERANCE:g} step ({TOLERANCE * step_ns / 1e3:g} µs)")
        raise BagError(f"{where}: message {k} is stamped {stamps[k] / 1e9:.9f} s, {why} of the "
                       f"{step_ns / 1e6:g} ms grid from {origin / 1e9:.9f} s "
                       "(simulation.step: the bag's parameters, else --config)")
    return idx, float(off.max()) if len(off) else 0.0


def _collapse(n: int, idx: np.ndarray, v: np.ndarray, where: str, what: str, step: float):
    """(values on the n-sample grid, NaN where none; recorded mask; repeats
    collapsed): a sample's messages must be identical, else one line naming it."""
    v = np.asarray(v, dtype=np.float64).reshape(len(idx), -1)
    out = np.full((n, v.shape[1]), math.nan)
    have = np.zeros(n, bool)
    order = np.argsort(idx, kind="stable")
    si, sv = idx[order], v[order]
    same = si[1:] == si[:-1]
    if same.any():
        a, b = sv[:-1][same], sv[1:][same]
        differ = ~((a == b) | (np.isnan(a) & np.isnan(b))).all(axis=1)
        if differ.any():
            j = int(np.flatnonzero(same)[np.argmax(differ)])
            i = int(si[j])
            raise BagError(f"{where}: messages {order[j]} and {order[j + 1]} are two different {what} for "
                           f"sample {i} (t = {i * step:.6f} s): refused (which one ran?)")
    out[si] = sv
    have[si] = True
    return out, have, int(same.sum())


def _by_log_time(n: int, state_log, state_idx: np.ndarray, commands, where: str):
    """Float64MultiArray commands on the grid: the first command logged after
    state k (log time at or after it, before the next state) answers state k."""
    datas = [d for _, d in commands]
    u_rows = _float64_first(datas, where)
    log = np.asarray(state_log, dtype=np.int64)
    order = np.argsort(log, kind="stable")
    k = np.searchsorted(log[order], np.asarray([t for t, _ in commands], dtype=np.int64), side="right") - 1
    early = int((k < 0).sum())
    u = np.full(n, math.nan)
    got = np.zeros(n, bool)
    extra = 0
    for kk, val in zip(k.tolist(), u_rows.tolist()):
        if kk < 0:
            continue
        i = int(state_idx[order[kk]])
        if got[i]:
            extra += 1
            continue
        got[i], u[i] = True, val
    return u, got, extra, early


def _float64_first(datas: list[bytes], where: str) -> np.ndarray:
    """data[0] of each Float64MultiArray; a malformed or empty one is one line naming it."""
    try:
        a = cdr.float64_arrays(datas, where)
        if a.shape[1] >= 1 and cdr.float64_array_layout(datas[0])[2] <= len(datas[0]):
            return a[:, 0].copy()
    except _MALFORMED:
        pass
    out = np.zeros(len(datas))
    for k, d in enumerate(datas):
        try:
            start, cnt, size = cdr.float64_array_layout(d)
            ok = size <= len(d) and cnt >= 1
        except _MALFORMED:
            ok = False
        if not ok:
            raise BagError(f"{where}: message {k}: truncated, malformed or empty CDR payload ({len(d)} bytes): "
                           f"not a {FLOAT64_ARRAY} [u]")
        out[k] = struct.unpack_from("<d", d, start)[0]
    return out
