"""The controller process: the adaptive back-stepping law answering each state, without ROS.

One compiled call (:func:`has_control.wire.steps.controller_sample`) decodes a
serialized state, runs the one implementation (:func:`~has_control.core.abc_controller.abc_law`,
``adapt``, :func:`~has_control.core.reference.reference`) with the sample time
taken from its stamp, and encodes the valve command (stamped like the state it
answers), the internals and the reference into preallocated buffers.

Parameter swaps are *pending*: :meth:`ControllerProcess.propose` builds the
arrays of an accepted parameter set (a tabulated road, O(n log n), off the
caller's thread) and the first sample after they are ready applies them
(:meth:`ControllerProcess.take_pending`); a newer proposal drops an older one
still building.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from has_control.common.errors import ConfigError
from has_control.core.episode import TRACE_COLUMNS, EpisodeArrays
from has_control.core.reference import road_cached
from has_control.wire import steps
from has_control.wire.topics import COMMAND_LAYOUT, CONTROLLER_STATE_LAYOUT, REFERENCE_LAYOUT


class ControllerProcess:
    """The law of ``cfg`` (gains, adaptation, reference, model, noise) with its
    estimates â and buffers; ``logger`` takes the refusals."""

    def __init__(self, cfg, logger):
        self.logger = logger
        self.mem = np.zeros(steps.CONTROLLER_MEMORY)
        self.command = COMMAND_LAYOUT.buffer()
        self.internals = CONTROLLER_STATE_LAYOUT.buffer()
        self.reference = REFERENCE_LAYOUT.buffer()
        self.trace = np.zeros((0, len(TRACE_COLUMNS)))
        self.malformed_states = self.states_answered = self.late = 0
        self._pending = None
        self._pending_lock = threading.Lock()
        self._generation = 0                    # accepted parameter sets: a road built for an old one is dropped
        self.apply(cfg)
        self.reset()

    def apply(self, cfg, arr: EpisodeArrays | None = None) -> None:
        """Take ``cfg`` (and its arrays, if built) from the next sample on."""
        self.cfg = cfg
        arr = arr or EpisodeArrays.from_config(cfg)
        self.ap, self.cp, self.rp = arr.actuator, arr.adaptation, arr.reference
        self.pp = arr.plant                     # the model's plant: predicts a state that never arrives
        # noise.added_by plant: the states arrive measured already; the law adds nothing
        self.sp = arr.sensor if cfg.noise.added_by == "controller" else np.zeros_like(arr.sensor)
        self.seed = arr.seed
        self.k = cfg.gains.as_tuple()
        self.gains = np.array(self.k)
        self.dt = cfg.episode.step
        self.step_ns = cfg.episode.step_ns
        self.announce = True                    # publish the gains in force at the next sample

    def reset(self) -> None:
        """Estimates back to â(0); the next sample starts a new run."""
        self.mem[steps.A1_HAT], self.mem[steps.A2_HAT] = self.cfg.adaptation.initial
        self.mem[steps.X3D_PREV] = self.mem[steps.HAS_PREV] = 0.0
        self.announce = True

    def record_trace(self, samples: int) -> np.ndarray:
        """Keep rows 0..samples-1 of the run (TRACE_COLUMNS) in a preallocated array."""
        self.trace = np.full((samples, len(TRACE_COLUMNS)), np.nan)
        return self.trace

    # --- pending parameter swaps ---------------------------------------------
    def propose(self, cfg) -> None:
        """An accepted parameter set: pending for the next sample (a road not yet
        tabulated is built on a thread of its own; the old reference runs meanwhile)."""
        with self._pending_lock:
            self._generation += 1
            generation = self._generation
            self._pending = None
        if cfg.reference.kind == "road" and not road_cached(cfg.reference, cfg.episode):
            threading.Thread(target=self._build, args=(cfg, generation), name="controller-road", daemon=True).start()
        else:
            self._build(cfg, generation)

    def _build(self, cfg, generation: int) -> None:
        try:
            arrays = EpisodeArrays.from_config(cfg)
        except (MemoryError, ConfigError) as exc:
            self.logger.error(f"cannot build the reference of the accepted parameters: {exc}")
            return
        with self._pending_lock:
            if generation == self._generation:
                self._pending = (cfg, arrays)

    @property
    def pending(self):
        return self._pending

    def take_pending(self) -> None:
        """Apply a pending parameter set (called at the start of a sample)."""
        if self._pending is not None:
            with self._pending_lock:
                pending, self._pending = self._pending, None
            if pending is not None:
                self.apply(*pending)

    # --- update ----------------------------------------------------------------
    def answer(self, data) -> int:
        """Answer one serialized state: the sample index, or MALFORMED / NOT_FINITE (nothing written)."""
        if self._pending is not None:
            self.take_pending()
        return steps.controller_sample(data, self.mem, self.gains, self.ap, self.cp, self.rp, self.sp, self.seed,
                                       self.dt, self.step_ns, self.command, self.internals, self.reference,
                                       self.trace)

    def answered(self, began_ns: int) -> None:
        """Count an answer begun at ``began_ns`` (perf_counter_ns); late: over one step."""
        self.states_answered += 1
        if time.perf_counter_ns() - began_ns > self.step_ns:
            self.late += 1

    def refused(self, what: str) -> None:
        self.malformed_states += 1
        self.logger.warning(f"refused a state ({what}); {self.malformed_states} so far", throttle_duration_sec=5.0)

    @property
    def a1_hat(self) -> float:
        return float(self.mem[steps.A1_HAT])

    @property
    def a2_hat(self) -> float:
        return float(self.mem[steps.A2_HAT])

    def estimates_in_bounds(self) -> bool:
        cp = self.cfg.adaptation
        return all(lo <= v <= hi for v, lo, hi in zip((self.a1_hat, self.a2_hat), cp.lower, cp.upper))

    def diagnosis(self, lifecycle: str, conflicts: int, port) -> tuple[dict, bool, str]:
        """The "control law" report: (values, OK, message). ``lifecycle``: the node's state;
        ``conflicts``: states from a second plant; ``port``: its counts of states missing,
        stale, repeated and of restarts (a port without them: 0)."""
        in_bounds = self.estimates_in_bounds()
        values = {"lifecycle": lifecycle, "states_answered": self.states_answered, "late": self.late,
                  "malformed_states": self.malformed_states, "conflicts": conflicts,
                  "a1_hat": f"{self.a1_hat:.6g}", "a2_hat": f"{self.a2_hat:.6g}", "estimates_in_bounds": in_bounds,
                  "states_missing": getattr(port, "missing", 0), "states_stale": getattr(port, "stale", 0),
                  "states_repeated": getattr(port, "repeated", 0), "restarts": getattr(port, "restarts", 0)}
        message = (f"{lifecycle}, {self.states_answered} answered, {self.late} late, "
                   f"{self.malformed_states} malformed" + ("" if in_bounds else ", estimates out of bounds"))
        return values, in_bounds and not conflicts, message
