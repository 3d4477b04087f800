"""The controller's two ports: how a state arrives and a command leaves, chosen once at configure.

* :class:`HasControlPort`: the plant's serialized ``sensor_msgs/JointState`` on
  ``state`` (decoded by compiled code), the command a JointState stamped like
  the state it answers on ``command``. A state sent again gets the same answer
  (not shown to observers); a state that goes back in time is a conflict, except
  one for sample 0: the plant was reset, a new run (estimates back to â(0),
  counted in ``restarts``).
* :class:`Ros2ControlPort`: a ``sensor_msgs/JointState`` (a message object, any
  joint order) read through ``state_interfaces`` (:mod:`has_control.wire.joint_mapping`),
  answered as the sample its header stamp names (the first state after a reset
  is sample 0, the stamp rounded to the nearest sample: jitter of less than half
  a step is absorbed), with ``std_msgs/Float64MultiArray`` ``[u]`` on the command
  topic. An unstamped state (stamp 0) is the next sample; a run whose first
  state is stamped 0 keeps a clock that starts at 0, and a state stamped 0 after
  stamped ones starts a new run (a simulated plant was reset: estimates back to
  â(0), counted in ``restarts``).

  *A sample that never arrives* (joint_state_broadcaster skips publishes) is
  counted in ``missing`` and *predicted*: the port keeps the model's plant
  (:func:`has_control.wire.steps.plant_sample` with the controller's
  ``actuator.*``/``plant.*``), set to each state received and stepped with the
  command sent for it; at a missing sample the law runs (not published) on the
  prediction, so the estimates integrate over the gap as the library's did,
  and the model steps on with the last command sent (what a
  forward_command_controller holds).
  When the model is the plant (the reference configuration, no measurement
  noise added by the plant) the prediction is the state, bit for bit, and every
  answered command equals ``simulate``'s. Otherwise equality is impossible: the
  library's â after the gap depends on the state of the missing sample, which
  the controller never got (test/test_loop.py proves both). A jump of more than
  :data:`PREDICTED_GAP` samples holds the estimates instead. Trace rows of
  missing samples are NaN.

  A state stamped at or before the last one answered is *stale*: the same
  stamp and values again is a repeat (counted in ``repeated``, not answered
  again); anything else only a second publisher on the topic sends: counted in
  ``stale`` and as a conflict, never answered. A message naming a joint twice is
  refused (``malformed_states``).

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
#: The longest run of missing states the ros2_control port predicts with the model [samples];
#: a longer jump of the stamps holds the estimates instead.
PREDICTED_GAP = 1000


@dataclass
class Outputs:
    """Where the controller writes: ``command`` (to observers too), ``command_again``
    (a repeat or a centred valve: the topic only), ``internals``, ``reference``, ``gains``;
    ``observe_internals``: where the internals go when they are not published (an
    in-process observer such as the stack's recorder; None: nowhere)."""

    command: Publish
    command_again: Publish
    internals: Publish
    reference: Publish
    gains: Publish
    publish_internals: bool = True
    observe_internals: Publish | None = None


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
        elif out.observe_internals is not None:
            out.observe_internals(bytes(p.internals))
        p.answered(began)


class HasControlPort(_Port):
    """The plant's ``state``/``command`` JointStates (see the module docstring)."""

    state_topic, command_topic = STATE, COMMAND

    def __init__(self, process, out: Outputs, conflicts: Conflicts, serialize: Callable | None = None):
        self.serialize = serialize               # a message object to bytes (in-process callers, tests)
        super().__init__(process, out, conflicts)

    def reset(self) -> None:
        self.last_state = self.last_command = b""
        self.restarts = 0

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
        p = self.process
        if self.last_state:
            i, last = self._sample(data), self._sample(self.last_state)
            if i == 0 < last:                    # the plant starts again at sample 0 (plant/reset): a new run
                self.restarts += 1
                p.reset()
            elif 0 < i <= last:
                self.conflicts.seen(f"state for sample {i} after sample {last}")
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
        self._twice = False
        self._read, self._last = np.zeros(4), np.zeros(4)
        self._state, self._clock, self._scratch = STATE_LAYOUT.buffer(), CLOCK_LAYOUT.buffer(), steps.scratch()
        self._next_state, self._next_clock = STATE_LAYOUT.buffer(), CLOCK_LAYOUT.buffer()
        self.missing = self.stale = self.repeated = self.restarts = 0
        super().__init__(process, out, conflicts)

    def reset(self) -> None:
        self._new_run()
        self.missing = self.stale = self.repeated = self.restarts = 0

    def _new_run(self) -> None:
        self.next = 0                            # the sample the next state is, if it is not stamped
        self.t0_ns = None                        # the stamp of sample 0
        self.last_ns = -1
        self.zero_start = False                  # the run's first state was stamped 0 (a clock starting at 0)
        p = self.process
        # the model's plant, stepped with each command sent: its state predicts a sample that never arrives
        self._x = steps.plant_state(p.cfg.plant.actuator(p.cfg.actuator).initial_state())
        self._last[:] = np.nan
        self._u_sent = 0.0

    def _sample(self, ns: int) -> int:
        """The sample a state stamped ``ns`` is: rounded to the grid from the first
        state's stamp; unstamped (0), the next one."""
        if ns <= 0:
            self.zero_start = self.zero_start or self.next == 0
            return self.next
        step = self.process.step_ns
        if self.t0_ns is None:
            self.t0_ns = 0 if self.zero_start else ns - self.next * step
        return int(math.floor((ns - self.t0_ns) / step + 0.5))

    def _predict(self, u: float, i: int) -> None:
        """Step the model's plant from the state of sample ``i`` with the command sent for it."""
        p = self.process
        steps.plant_sample(self._x, u, p.pp, p.dt, math.inf, i + 1, p.step_ns, self._next_state, self._next_clock,
                           self._scratch)

    def _answer(self, i: int) -> float:
        """Run the law on ``self._x`` as sample ``i``; the command u [m]."""
        p = self.process
        steps.encode_state(self._x, p.ap, i, p.step_ns, self._state, self._clock, self._scratch)
        p.answer(self._state)
        return steps.command_of(p.command, p.step_ns, self._scratch)[1]

    def on_state(self, msg) -> None:
        began = time.perf_counter_ns()
        if msg.name != self._names:              # the joints' order is looked up once per layout
            self._names = list(msg.name)
            self._index = resolve(self._names, self.mapping)
            self._twice = len(set(self._names)) != len(self._names)
        p, x = self.process, self._x
        if self._twice:
            return p.refused("a joint named twice in one message")
        arrays = (msg.position, msg.velocity, msg.effort)
        y = self._read
        for k, (j, kind) in enumerate(self._index):
            values = arrays[kind]
            if j < 0 or j >= len(values):
                return p.refused("a joint or interface of state_interfaces missing")
            y[k] = values[j]
        if not (math.isfinite(y[0]) and math.isfinite(y[1]) and math.isfinite(y[2]) and math.isfinite(y[3])):
            return p.refused("a non-finite value")
        header = getattr(msg, "header", None)
        ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec) if header is not None else 0
        if ns == 0 and self.t0_ns is not None and self.next > 0:
            self.restarts += 1                   # the stamps start again at 0: a new run (a plant reset)
            p.reset()
            self._new_run()
        i = self._sample(ns)
        if i < self.next:                        # at or before the last sample answered
            if ns == self.last_ns and np.array_equal(y, self._last):
                self.repeated += 1               # the same state again (a resend): answered already
                return None
            self.stale += 1                      # only a second publisher sends these
            self.conflicts.seen(f"state for sample {i} after sample {self.next - 1}")
            return None
        p.take_pending()
        if i - self.next > PREDICTED_GAP:        # a jump, not a gap: the estimates held, time re-based
            self.missing += i - self.next
            self.next = i
        while self.next < i:                     # samples that never arrived: the model's prediction
            j = self.next
            self._answer(j)                      # the estimates integrate over j, its command is not sent:
            self._predict(self._u_sent, j)       # the plant ran j with the last one held
            if j < len(p.trace):
                p.trace[j] = np.nan              # not answered
            self.missing += 1
            self.next = j + 1
        x[:4] = y
        self._last[:] = y
        self.last_ns = ns
        u = self._answer(i)
        self.next = i + 1
        self._announce(i)
        self.out.command(FORWARD_COMMAND_LAYOUT.encode([u]))
        self._u_sent = u
        self._predict(u, i)
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
