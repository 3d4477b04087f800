"""The controller's two ports: how a state arrives and a command leaves, chosen once at configure.

* :class:`HasControlPort`: the plant's serialized ``sensor_msgs/JointState`` on
  ``state`` (decoded by compiled code), the command a JointState stamped like
  the state it answers on ``command``. A state sent again gets the same answer
  (not shown to observers); a state that goes back in time is a conflict.
* :class:`Ros2ControlPort`: a ``sensor_msgs/JointState`` (a message object, any
  joint order) read through ``state_interfaces`` (:mod:`has_control.wire.joint_mapping`),
  answered as the sample its header stamp names (the first state after a reset
  is sample 0, the stamp rounded to the nearest sample: jitter of less than half
  a step is absorbed), with ``std_msgs/Float64MultiArray`` ``[u]`` on the command
  topic. A sample that never arrives (joint_state_broadcaster skips publishes) is
  counted in ``missing``; a state stamped at or before the last one answered is
  stale, counted in ``stale`` and not answered. Across a gap the estimates are
  held (their rates at the missing samples are unknown; in the reference
  configuration they sit on their projection bounds, so nothing changes) and
  the reference is evaluated at the stamp. An unstamped state (stamp 0) is the
  next sample, as before.

Both drive one :class:`~has_control.loop.controller.ControllerProcess` and write
through :class:`Outputs` (publish functions the node makes); both publish the
gains in force at the first sample and after each swap, and the internals when asked.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from has_control.loop.guards import Conflicts
from has_control.wire import steps
from has_control.wire.codec import NOT_FINITE, get_stamp
from has_control.wire.joint_mapping import resolve
from has_control.wire.topics import (CLOCK_LAYOUT, COMMAND, COMMAND_LAYOUT, FORWARD_COMMAND_LAYOUT, GAINS_LAYOUT,
                                     STATE, STATE_LAYOUT)

Publish = Callable[[bytes], None]


@dataclass
class Outputs:
    """Where the controller writes: ``command`` (to observers too), ``command_again``
    (a repeat or a centred valve: the topic only), ``internals``, ``reference``, ``gains``."""

    command: Publish
    command_again: Publish
    internals: Publish
    reference: Publish
    gains: Publish
    publish_internals: bool = True


class _Port:
    """What both ports share: the process, the outputs, the gains' announcement."""

    state_topic = command_topic = ""
    raw = True                                   # the state arrives serialized
    command_type = "JointState"                  # sensor_msgs/JointState | Float64MultiArray

    def __init__(self, process, out: Outputs, conflicts: Conflicts):
        self.process, self.out, self.conflicts = process, out, conflicts
        self.reset()

    def reset(self) -> None:
        """A new run: forget the last state answered."""

    def _announce(self, i: int) -> None:
        p = self.process
        if p.announce:
            self.out.gains(GAINS_LAYOUT.encode([i * p.dt, *p.k]))
            p.announce = False

    def _answered(self, began: int) -> None:
        """The internals of the sample after its command; count it."""
        p, out = self.process, self.out
        if out.publish_internals:
            out.internals(bytes(p.internals))
            out.reference(bytes(p.reference))
        p.answered(began)


class HasControlPort(_Port):
    """The plant's ``state``/``command`` JointStates (see the module docstring)."""

    state_topic, command_topic = STATE, COMMAND

    def __init__(self, process, out: Outputs, conflicts: Conflicts, serialize: Callable | None = None):
        self.serialize = serialize               # a message object to bytes (in-process callers, tests)
        super().__init__(process, out, conflicts)

    def reset(self) -> None:
        self.last_state = self.last_command = b""

    def _sample(self, data: bytes) -> int:
        """Sample index of a serialized state's stamp."""
        return int(get_stamp(data)) // self.process.step_ns if len(data) >= 12 else -1

    def on_state(self, data) -> None:
        began = time.perf_counter_ns()
        if not isinstance(data, bytes):
            data = self.serialize(data)
        if data == self.last_state:              # the plant sent it again: the same answer (not to observers)
            self.out.command_again(self.last_command)
            return
        if self.last_state and 0 < self._sample(data) <= self._sample(self.last_state):
            self.conflicts.seen(f"state for sample {self._sample(data)} after sample {self._sample(self.last_state)}")
        p = self.process
        i = p.answer(data)
        if i < 0:
            p.refused("a non-finite value" if i == NOT_FINITE else "not the plant's JointState on the sample grid")
            return
        if p.announce:
            self._announce(i)
        self.last_state, self.last_command = data, bytes(p.command)
        self.out.command(self.last_command)
        self._answered(began)

    def centre(self) -> None:
        """A command u = 0 for the sample after the last one answered."""
        if self.last_state:
            stamp = (self._sample(self.last_state) + 1) * self.process.step_ns
            self.out.command_again(COMMAND_LAYOUT.encode([0.0], stamp_ns=stamp))


class Ros2ControlPort(_Port):
    """A JointState read through ``mapping`` ([(joint, interface)] of y, ẏ, P1, P2),
    ``[u]`` written as Float64MultiArray (see the module docstring)."""

    raw = False
    command_type = "Float64MultiArray"

    def __init__(self, process, out: Outputs, conflicts: Conflicts, mapping, state_topic: str, command_topic: str):
        self.mapping, self.state_topic, self.command_topic = mapping, state_topic, command_topic
        self._names = self._index = None
        self._x = np.zeros(5)
        self._state, self._clock, self._scratch = STATE_LAYOUT.buffer(), CLOCK_LAYOUT.buffer(), steps.scratch()
        super().__init__(process, out, conflicts)

    def reset(self) -> None:
        self.next = 0                            # the sample the next state is, if it is not stamped
        self.t0_ns = None                        # the stamp of sample 0
        self.missing = self.stale = 0

    def _sample(self, msg) -> int:
        """The sample a state is: from its header stamp (rounded to the grid from the
        first state's), else the next one."""
        header = getattr(msg, "header", None)
        ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec) if header is not None else 0
        if ns <= 0:
            return self.next
        step = self.process.step_ns
        if self.t0_ns is None:
            self.t0_ns = ns - self.next * step
        return int(math.floor((ns - self.t0_ns) / step + 0.5))

    def on_state(self, msg) -> None:
        began = time.perf_counter_ns()
        if msg.name != self._names:              # the joints' order is looked up once per layout
            self._names = list(msg.name)
            self._index = resolve(self._names, self.mapping)
        p, x = self.process, self._x
        arrays = (msg.position, msg.velocity, msg.effort)
        for k, (j, kind) in enumerate(self._index):
            values = arrays[kind]
            if j < 0 or j >= len(values):
                return p.refused("a joint or interface of state_interfaces missing")
            x[k] = values[j]
        if not (math.isfinite(x[0]) and math.isfinite(x[1]) and math.isfinite(x[2]) and math.isfinite(x[3])):
            return p.refused("a non-finite value")
        i = self._sample(msg)
        if i < self.next:                        # stale: at or before the last sample answered
            self.stale += 1
            return None
        self.missing += i - self.next
        p.take_pending()
        steps.encode_state(x, p.ap, i, p.step_ns, self._state, self._clock, self._scratch)
        p.answer(self._state)
        self.next = i + 1
        self._announce(i)
        _, u = steps.command_of(p.command, p.step_ns, self._scratch)
        self.out.command(FORWARD_COMMAND_LAYOUT.encode([u]))
        self._answered(began)

    def centre(self) -> None:
        """``[0.0]`` on the command topic."""
        self.out.command_again(FORWARD_COMMAND_LAYOUT.encode([0.0]))


def make_port(interface: str, process, out: Outputs, conflicts: Conflicts, *, mapping=None, state_topic: str = "",
              command_topic: str = "", serialize: Callable | None = None) -> _Port:
    """The port of ``interface`` ('has_control' | 'ros2_control'), chosen once at configure."""
    if interface == "ros2_control":
        return Ros2ControlPort(process, out, conflicts, mapping, state_topic, command_topic)
    return HasControlPort(process, out, conflicts, serialize)


INTERFACES = ("has_control", "ros2_control")
