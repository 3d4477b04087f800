"""The plant process: the simulated actuator at one step Δt per sample, without ROS.

State x = (y [m], ẏ [m/s], P1 [Pa], P2 [Pa], spool [m]) starts at rest (SPEC §4,
with this plant's own parameters, the spool centred). Each sample is one
compiled call (:func:`has_control.wire.steps.plant_sample`) of the one
implementation, :func:`has_control.core.actuator.plant_step`, that also encodes
the new state; commands arrive as serialized bytes decoded by compiled code
(:func:`has_control.wire.steps.command_of`), so a run through the graph equals
the in-process trace, bit for bit.

A command of another layout is read by the port's slow ``fallback`` decoder
(a frame_id, velocities, more joints); off the sample grid, non-finite or
undecodable it is refused and counted (``malformed_commands``) and never
reaches the state. Two different commands for one sample are a conflict
(:class:`~has_control.loop.guards.Conflicts`). A diverged state (|y| > y_limit
or not finite) is published and ends the episode.

**Unstamped commands** (the ros2_control layout, :meth:`PlantProcess.on_forward_command`):
a forward_command_controller's ``std_msgs/Float64MultiArray`` ``[u]`` has no header,
so a command answers *the latest state published*, which is awaiting one answer.
In lock-step that is exact: state i+1 is published only after command i has
arrived. A command that arrives with no state awaiting it is one more than the
states published: in lock-step a second controller on the topic (a conflict);
in a paced run a command that came after its deadline (counted in
``late_commands``, ignored), whereas a late command that arrives after the next
state was published is taken as that state's answer (it cannot be told apart).

**Dropped states** (a test hook, ``drop_every`` = N ≥ 2): the state of every
sample i with i mod N = N − 1 is not published, as joint_state_broadcaster's
realtime publisher skips one; in lock-step the sample then runs at once with
the last command held (as hardware runs on with a forward_command_controller's
last command), in a paced run it is a miss. Counted in ``dropped_states``.

The process writes through a port (the node's publishers, or a fake): an object
with ``publish(state, true_state | None, clock) -> bool`` (False: the transport
refused the write), ``resend(state)`` (the state again, not to observers) and
``connected() -> bool`` (both directions have matched a peer).
"""
from __future__ import annotations

import math
import time
from typing import Callable

from has_control.loop.guards import AnswerLedger, Conflicts, FailSafe
from has_control.wire import steps
from has_control.wire.codec import NOT_FINITE
from has_control.wire.topics import CLOCK_LAYOUT, FORWARD_COMMAND_LAYOUT, MISSED_LAYOUT, STATE_LAYOUT


def missed_message(sample: int, step: float, u: float, failsafe: bool) -> bytes:
    """The ``plant/missed`` message of a sample run without its answer: t [s]
    (``sample`` · Δt ``step``), the command it ran with u [m], 1.0 if on the fail-safe."""
    return MISSED_LAYOUT.encode((sample * step, u, 1.0 if failsafe else 0.0))


class PlantProcess:
    """The plant of ``cfg`` (its ``plant.*`` over the model ``actuator.*``), run
    under ``schedule`` (:mod:`has_control.loop.schedule`), ``samples`` per episode (0: until stopped)."""

    def __init__(self, cfg, schedule, port, logger, *, samples: int = 0,
                 fallback: Callable[[bytes], tuple[int, float] | None] | None = None, drop_every: int = 0):
        if drop_every == 1 or drop_every < 0:
            raise ValueError(f"drop_every = {drop_every}: 0 (none) or >= 2")
        self.schedule, self.port, self.logger, self.fallback = schedule, port, logger, fallback
        self.drop_every = drop_every
        self.actuator = cfg.plant.actuator(cfg.actuator)      # this plant's own parameters
        self.ap = cfg.plant.as_array(cfg.actuator)            # ... and its valve
        self.step_s, self.step_ns, self.y_limit = cfg.episode.step, cfg.episode.step_ns, cfg.episode.y_limit
        self.samples = samples
        # noise.added_by plant: ``state`` carries the sensors' readings, ``true_state`` the state
        self.measured = cfg.noise.added_by == "plant"
        self.sp, self.seed = cfg.noise.as_array(cfg.episode.step), int(cfg.noise.seed)
        self.state_msg, self.true_msg = STATE_LAYOUT.buffer(), STATE_LAYOUT.buffer()
        self.clock_msg = CLOCK_LAYOUT.buffer()
        self._scratch = steps.scratch()
        self.fail_safe = FailSafe(logger)
        self.conflicts = Conflicts(logger, getattr(port, "command_publishers", lambda: ""), "conflicting commands")
        self.conflicts.on_stop = self._stop_now
        self.answers = AnswerLedger()
        self.malformed_commands = self.late_commands = self.dropped_states = 0
        self.publish_failures = 0                 # states the transport refused to send
        #: A record of every step, (sample, y, ẏ, P1, P2, u it ran with), when set to a list (None: off).
        self.log: list[tuple[int, float, float, float, float, float]] | None = None
        #: An observer of the samples run without their answer: takes each as a ``plant/missed``
        #: message (:data:`~has_control.wire.topics.MISSED_COLUMNS`; None: not reported).
        self.on_unanswered: Callable[[bytes], None] | None = None
        self.started_at = self.run_seconds = 0.0
        self.reset()

    def _stop_now(self) -> None:
        self.finished = True

    def reset(self) -> None:
        """Back to the initial state at sample 0, idle until :meth:`start`."""
        self.x = steps.plant_state(self.actuator.initial_state())    # spool, its velocity, the delay ring
        self.sample = self.first_sample = 0
        self.finished = self.diverged = False
        self.command_sample, self.command_u = -1, 0.0
        self._centred_at = -1                     # the sample the fail-safe last centred the valve for
        self.answers.reset()
        steps.encode_state(self.x, self.ap, 0, self.step_ns, self.state_msg, self.clock_msg, self._scratch)
        self._measure()
        self.last_publish = time.monotonic()
        self.published = self.awaiting = False

    def start(self) -> None:
        """Run an episode from the current state (lock-step: its state is published now)."""
        self.finished = False
        self.started_at = time.perf_counter()
        self.first_sample = self.sample
        if not self.schedule.paced:
            self.publish_state()

    def stop(self) -> None:
        """End the episode; the next command expected is u = 0 for this sample."""
        self.command_sample, self.command_u = self.sample, 0.0
        if not self.finished:
            self.finish()

    def finish(self) -> None:
        self.finished = True
        self.run_seconds = time.perf_counter() - self.started_at

    def first_answer_timeout(self) -> float:
        """How long the first sample of a run waits [s]: ``startup_timeout`` while a
        matched controller has not answered yet, else ``timeout``."""
        return self.schedule.startup_timeout if self.port.connected() else self.schedule.timeout

    # --- write -------------------------------------------------------------------
    def _measure(self) -> None:
        """With measured states: the true state just encoded moves to ``true_msg``,
        the sensors' readings of it (seeded noise of this sample) take its place."""
        if self.measured:
            self.true_msg[:] = self.state_msg
            steps.encode_measured(self.x, self.ap, self.sample, self.step_ns, self.sp, self.seed,
                                  self.state_msg, self.clock_msg, self._scratch)

    def publish_state(self) -> None:
        """The state of the current sample (with measured states, then the true
        state), then its clock; a write the transport refuses is a miss, not a crash.
        A state dropped by ``drop_every`` is not written (lock-step: the sample runs
        at once with the last command held)."""
        if self.drop_every and self.sample % self.drop_every == self.drop_every - 1:
            self.dropped_states += 1
            self.last_publish = time.monotonic()
            self.published, self.awaiting = True, False
            if not self.schedule.paced and not self.finished:
                if self.step(self.command_u if self.command_sample >= 0 else 0.0, answered=False):
                    self.publish_state()
            return
        self.awaiting = True
        if not self.port.publish(bytes(self.state_msg), bytes(self.true_msg) if self.measured else None,
                                 bytes(self.clock_msg)):
            self.publish_failures += 1
            self.logger.warning(f"sample {self.sample} not published; {self.publish_failures} so far",
                                throttle_duration_sec=5.0)
        self.last_publish = time.monotonic()
        self.published = True

    def resend(self) -> None:
        self.port.resend(bytes(self.state_msg))

    # --- update ----------------------------------------------------------------
    def step(self, u: float, answered: bool = True) -> bool:
        """Advance one sample with valve command u [m] (``answered``: the
        controller's answer to it, not a held or fail-safe value); False when the
        episode ends (the diverged state is then published, for the record)."""
        if self.log is not None:
            self.log.append((self.sample, *map(float, self.x[:4]), u))
        if not answered and self.on_unanswered is not None:
            self.on_unanswered(missed_message(self.sample, self.step_s, u, self._centred_at == self.sample))
        self.answers.ran(self.sample, u, answered)
        self.sample += 1
        bad = steps.plant_sample(self.x, u, self.ap, self.step_s, self.y_limit, self.sample, self.step_ns,
                                 self.state_msg, self.clock_msg, self._scratch)
        self._measure()
        if self.samples and self.sample - self.first_sample >= self.samples:     # this episode's samples
            self.finish()
            return False
        if bad:
            self.logger.error(f"diverged at sample {self.sample}: y = {self.x[0]:.4g} m")
            self.publish_state()
            self.diverged = True
            self.finish()
            return False
        return True

    def failsafe(self, missing: int) -> None:
        """The valve is centred for this sample (``missing`` commands in a row)."""
        self.fail_safe.centre(missing, self.sample)
        self._centred_at = self.sample

    def commands_back(self) -> None:
        self.fail_safe.back(self.sample)

    # --- read ------------------------------------------------------------------
    def on_command(self, data: bytes) -> None:
        """A serialized command: keep the latest; the schedule decides whether it advances the plant."""
        i, u = steps.command_of(data, self.step_ns, self._scratch)
        if i < 0:
            i, u = self._other_layout(data, i)
            if i < 0:
                return
        if (i == self.command_sample and u != self.command_u) or (i < self.sample and self.answers.differs(i, u)):
            self.conflicts.seen(f"two different commands for sample {i}")
        if i >= self.command_sample:
            self.command_sample, self.command_u = i, u
        self.schedule.answer(self, i, u)

    def on_forward_command(self, data: bytes) -> None:
        """A serialized ``std_msgs/Float64MultiArray`` ``[u]`` (no stamp): the answer to
        the latest state published (see the module docstring); another layout is read
        by the port's ``fallback`` (→ (−1, u)) if it can, else refused and counted."""
        values = FORWARD_COMMAND_LAYOUT.read(data)
        u = values[0] if values is not None else None
        if u is None and self.fallback is not None:
            read = self.fallback(data)
            u = read[1] if read is not None else None
        if u is None or not math.isfinite(u):
            self.malformed_commands += 1
            what = "not a Float64MultiArray [u]" if u is None else "a non-finite value"
            self.logger.warning(f"refused a command ({what}); {self.malformed_commands} so far",
                                throttle_duration_sec=5.0)
            return
        if not self.awaiting:
            if self.schedule.paced:
                self.late_commands += 1
            elif self.published and not self.finished:
                self.conflicts.seen(f"a command with no state awaiting it at sample {self.sample}")
            return
        self.awaiting = False
        i = self.sample
        self.command_sample, self.command_u = i, u
        self.schedule.answer(self, i, u)

    def _other_layout(self, data: bytes, status: int) -> tuple[int, float]:
        """A command the fast decoder refused: read by the port's ``fallback``
        (stamp [ns], u [m]) if it can; otherwise counted and ignored."""
        if status != NOT_FINITE and self.fallback is not None:
            read = self.fallback(data)
            if read is not None:
                ns, u = read
                if ns >= 0 and ns % self.step_ns == 0:              # on the sample grid, as the fast path asks
                    if math.isfinite(u):
                        return ns // self.step_ns, u
                    status = NOT_FINITE
        self.malformed_commands += 1
        what = "a non-finite value" if status == NOT_FINITE else "not a valve JointState on the sample grid"
        self.logger.warning(f"refused a command ({what}); {self.malformed_commands} so far",
                            throttle_duration_sec=5.0)
        return -1, 0.0

    def figures(self) -> dict[str, float]:
        """The counts the diagnostics report."""
        figures = {"failsafe_samples": float(self.fail_safe.samples),
                   "malformed_commands": float(self.malformed_commands), "conflicts": float(self.conflicts.count)}
        if self.drop_every:
            figures["dropped_states"] = float(self.dropped_states)
        if self.late_commands:
            figures["late_commands"] = float(self.late_commands)
        return figures
