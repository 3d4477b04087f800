"""Typed parameter objects for the actuator, the ABC controller and an episode.

Every default here is SPEC.md's reference configuration; the files in
``config/`` repeat them in ``ros__parameters`` form and ``has_control.config.schema``
loads those files into these dataclasses. All quantities are SI.

The numerical kernels take flat ``float64`` arrays (``as_array``) whose
layout is fixed by the index constants below, so numba sees plain arrays.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

# --- actuator array layout --------------------------------------------------
MASS, AREA_CAP, AREA_ROD, BULK, DAMPING, LEAKAGE, V_CAP0, V_ROD0, GRAVITY, \
    P_SUPPLY, P_RETURN, VALVE_GAIN = range(12)
N_ACTUATOR = 12

# --- plant array layout: the actuator's (true) parameters, then its valve ---
VALVE_LIMIT, VALVE_RATE, VALVE_OMEGA, VALVE_ZETA, DELAY, SUBSTEPS, FRICTION_COULOMB, FRICTION_STRIBECK, \
    STRIBECK_VELOCITY, FRICTION_SMOOTHING, STRUCTURE = range(N_ACTUATOR, N_ACTUATOR + 11)
N_PLANT = N_ACTUATOR + 11
#: The plant's structure (pp[STRUCTURE]), what the kernels specialise on: the
#: reference plant (ideal or first-order valve, limit: SPEC's step), a plant
#: with a second-order spool and/or a delayed command (one RK4 step a sample,
#: no friction), or any plant (friction, substeps).
STRUCTURE_REFERENCE, STRUCTURE_SPOOL, STRUCTURE_FULL = 0, 1, 2
#: The longest transport delay of the command [samples]; the kernels' ring holds DELAY_RING commands.
DELAY_MAX = 16
DELAY_RING = DELAY_MAX + 1
#: The most RK4 substeps a sample.
SUBSTEPS_MAX = 64

# --- sensor (measurement noise) array layout --------------------------------
NOISE_Y, NOISE_YDOT, NOISE_P1, NOISE_P2, RESOLUTION_Y, RESOLUTION_P, VELOCITY_DERIVED, VELOCITY_ALPHA = range(8)
N_SENSOR = 8
#: How the velocity reading is made (noise.velocity): measured, or the backward difference of the position reading.
VELOCITY_SOURCES = {"measured": 0, "derived": 1}

# --- controller (adaptation) array layout ----------------------------------
SIGMA1, SIGMA2, A1_INIT, A2_INIT, A1_MIN, A2_MIN, A1_MAX, A2_MAX, X3D_MODE = range(9)
N_CONTROLLER = 9
X3D_ANALYTIC, X3D_BACKWARD = 0, 1
X3D_MODES = {"analytic": X3D_ANALYTIC, "backward_difference": X3D_BACKWARD}
#: Where the measurement noise is added: by the controller to the true states it
#: receives (the reference), or by the plant to the states it publishes.
NOISE_ADDED_BY = {"controller": 0, "plant": 1}
#: identify's verdict on a plant as a model of a machine (plant.model_adequacy; no physics reads it).
MODEL_ADEQUACY = {"unstated": 0, "adequate": 1, "inadequate": 2}

# --- reference array layout -------------------------------------------------
REF_KIND, REF_AMPLITUDE, REF_OMEGA, REF_OFFSET, REF_T0, REF_RISE, REF_F0, \
    REF_F1, REF_SWEEP, REF_ROWS, REF_GRID_STEP, REF_TERMS, REF_FIRST, REF_BIAS = range(14)
#: Header of the reference array. A road (:mod:`has_control.core.road`) is defined on a grid of
#: REF_ROWS samples, one each REF_GRID_STEP [s], and repeats after it; it follows the header
#: with REF_TERMS components (harmonics REF_FIRST, REF_FIRST + 1, …, two numbers each) summed
#: in the kernel, or, if REF_TERMS is −1, with REF_ROWS rows of (x1d, ẋ1d, ẍ1d, x1d⁽³⁾).
N_REFERENCE = 14
REF_ZERO, REF_SINE, REF_STEP, REF_CHIRP, REF_ROAD = range(5)
REFERENCE_KINDS = {"zero": REF_ZERO, "sine": REF_SINE, "step": REF_STEP, "chirp": REF_CHIRP, "road": REF_ROAD}
#: ISO 8608 road classes: displacement PSD Gd(n0) [m³] at n0 = 0.1 cycles/m (the class's geometric mean).
ROAD_CLASSES = {"A": 16e-6, "B": 64e-6, "C": 256e-6, "D": 1024e-6, "E": 4096e-6}

# --- episode array layout ---------------------------------------------------
DT, N_SAMPLES, LAMBDA1, LAMBDA2, LAMBDA3, WIN_START, WIN_END, Y_LIMIT = range(8)
N_EPISODE = 8


@dataclass(frozen=True)
class Actuator:
    """Physical parameters of the asymmetric cylinder and servo valve (SPEC §1).

    mass [kg], areas [m²], bulk_modulus [Pa], damping [N·s/m],
    leakage [m³/(s·Pa)], volumes [m³], gravity [m/s²], pressures [Pa],
    discharge_coefficient [-], area_gradient [m], oil_density [kg/m³],
    valve_gain G [m²·√(1/kg·m)] = √2·Cd·W·√(1/ρ)·ki, with ki = 1 so the
    command u is the spool displacement in metres.
    """

    mass: float = 1500.0
    area_cap: float = 5.67e-3
    area_rod: float = 1.256e-3
    bulk_modulus: float = 7.0e8
    damping: float = 2600.0
    leakage: float = 3.0e-13
    volume_cap0: float = 1.0e-3
    volume_rod0: float = 1.0e-3
    gravity: float = 9.8
    supply_pressure: float = 1.78e7
    return_pressure: float = 0.0
    discharge_coefficient: float = 0.7
    area_gradient: float = 1.12e-2
    oil_density: float = 860.0
    valve_gain: float = 3.78e-4

    def derived_valve_gain(self) -> float:
        """√2·Cd·W/√ρ (ki = 1), for checking ``valve_gain`` against Cd, W, ρ."""
        return math.sqrt(2.0) * self.discharge_coefficient * self.area_gradient / math.sqrt(self.oil_density)

    def initial_state(self) -> np.ndarray:
        """SPEC §4: y = 0, ẏ = 0, P2 = Ps/2, P1 from the static force balance."""
        p2 = 0.5 * self.supply_pressure
        p1 = (self.mass * self.gravity + self.area_rod * p2) / self.area_cap
        return np.array([0.0, 0.0, p1, p2])

    def as_array(self) -> np.ndarray:
        return np.array([
            self.mass, self.area_cap, self.area_rod, self.bulk_modulus, self.damping,
            self.leakage, self.volume_cap0, self.volume_rod0, self.gravity,
            self.supply_pressure, self.return_pressure, self.valve_gain,
        ], dtype=np.float64)


#: The actuator parameters a plant may have apart from the controller's model.
PLANT_OVERRIDES = ("mass", "bulk_modulus", "damping", "leakage", "supply_pressure", "valve_gain")


@dataclass(frozen=True)
class Plant:
    """The simulated actuator, where it differs from the controller's model.

    Each of mass [kg], bulk_modulus [Pa], damping [N·s/m], leakage
    [m³/(s·Pa)], supply_pressure [Pa] and valve_gain [m²·√(1/kg·m)] is the
    model's (``actuator.*``) when None. valve_limit u_max [m]: the spool
    travel, |u| ≤ u_max (0: no limit); valve_time_constant τ_v [s]: a
    first-order valve, τ_v·ẋv = u − xv, stepped as a fifth state in the same
    RK4 (0: an ideal valve, xv = u).

    valve_frequency f_n [Hz] and valve_damping_ratio ζ [-]: a second-order
    spool, ẍv = ω_n²(u − xv) − 2ζω_n·ẋv with ω_n = 2π·f_n, xv and ẋv two more
    states of the same RK4 step (0: not second order; exclusive with the
    first-order lag); with a valve_limit the spool stops at ±u_max (its
    velocity zeroed there). delay d [samples, 0..DELAY_MAX]: the valve gets
    the command of d samples earlier (0 before the start); delay_fraction f
    [samples, 0 ≤ f < 1]: a further fraction of a sample, the command
    interpolated linearly between samples i − d and i − d − 1 (a delay of
    d + f samples; 0: whole samples, as before). friction_coulomb
    Fc [N], friction_stribeck Fs [N] (breakaway force), stribeck_velocity
    v_s [m/s], friction_smoothing ε [m/s]: F = (Fc + (Fs − Fc)·e^(−(ẏ/v_s)²))
    ·ẏ/√(ẏ² + ε²) against the motion. substeps: RK4 steps a sample (the
    command held). validated_band [Hz]: the band up to which identification
    validated this plant as a model of a machine (0: not stated); no physics
    reads it: ``tune`` vouches for its answer against what may lie above it
    (:mod:`has_control.tuning.vouch`). model_adequacy: identify's verdict on
    this plant as a model of a machine (``unstated``, ``adequate`` or
    ``inadequate``); no physics reads it: under ``inadequate`` ``tune`` vouches
    for nothing and leaves the choice to the deployment's measurement
    (docs/tuners.md). The defaults are the reference configuration: the plant
    is the model, the valve ideal (docs/model.md).
    """

    mass: float | None = None
    bulk_modulus: float | None = None
    damping: float | None = None
    leakage: float | None = None
    supply_pressure: float | None = None
    valve_gain: float | None = None
    valve_limit: float = 0.0
    valve_time_constant: float = 0.0
    valve_frequency: float = 0.0
    valve_damping_ratio: float = 0.7
    delay: int = 0
    delay_fraction: float = 0.0
    friction_coulomb: float = 0.0
    friction_stribeck: float = 0.0
    stribeck_velocity: float = 0.01
    friction_smoothing: float = 1.0e-4
    substeps: int = 1
    validated_band: float = 0.0
    model_adequacy: str = "unstated"

    def has_friction(self) -> bool:
        return self.friction_coulomb != 0.0 or self.friction_stribeck != 0.0

    def structure(self) -> int:
        """What the kernels specialise on (STRUCTURE_*): the simplest that holds this plant."""
        if self.has_friction() or self.substeps != 1:
            return STRUCTURE_FULL
        if self.valve_frequency > 0.0 or self.delay != 0 or self.delay_fraction != 0.0:
            return STRUCTURE_SPOOL
        return STRUCTURE_REFERENCE

    def actuator(self, model: Actuator) -> Actuator:
        """The plant's own parameters: ``model`` with this plant's overrides."""
        changes = {k: getattr(self, k) for k in PLANT_OVERRIDES if getattr(self, k) is not None}
        return dataclasses.replace(model, **changes) if changes else model

    def as_array(self, model: Actuator) -> np.ndarray:
        """The plant array: :meth:`Actuator.as_array` of :meth:`actuator`, then
        u_max [m], 1/τ_v [1/s] (0 for an ideal valve), ω_n [rad/s] (0: not
        second order), ζ, delay + delay_fraction [samples], substeps, Fc [N], Fs [N], v_s [m/s],
        ε [m/s] and the structure (STRUCTURE_*)."""
        rate = 1.0 / self.valve_time_constant if self.valve_time_constant > 0.0 else 0.0
        omega = 2.0 * math.pi * self.valve_frequency
        return np.concatenate([self.actuator(model).as_array(), [
            self.valve_limit, rate, omega, self.valve_damping_ratio, self.delay + self.delay_fraction,
            float(self.substeps),
            self.friction_coulomb, self.friction_stribeck, self.stribeck_velocity, self.friction_smoothing,
            float(self.structure())]])


@dataclass(frozen=True)
class Noise:
    """Measurement noise on what the controller reads: zero-mean Gaussian with
    standard deviations position [m] (y), velocity [m/s] (ẏ), pressure_cap and
    pressure_rod [Pa] (P1, P2), a pure function of (seed, sample, channel)
    (:mod:`has_control.core.noise`), so every path draws the same values. The
    cost and metrics use the true y. All 0 (the reference): exact states.

    added_by: 'controller' (the reference: the plant publishes its true state,
    the controller adds the noise to what it reads) or 'plant' (the plant
    publishes its sensors' readings, true state plus this noise, as a real
    machine does, and its true state beside them for tests and scoring; the
    controller adds nothing). The law reads the same values either way, so
    the episode does not depend on it."""

    position: float = 0.0
    velocity: float = 0.0
    pressure_cap: float = 0.0
    pressure_rod: float = 0.0
    seed: int = 0
    added_by: str = "controller"
    position_resolution: float = 0.0
    pressure_resolution: float = 0.0
    velocity_source: str = "measured"
    velocity_filter_frequency: float = 0.0

    def as_array(self, step: float = 3.0e-4) -> np.ndarray:
        """The sensor array: the four standard deviations, the two resolutions,
        1 for a derived velocity (else 0) and its filter's α at sample step ``step`` [s]
        (0: unfiltered, as f = 0; so the reference's sensor array is all zeros)."""
        f = self.velocity_filter_frequency
        alpha = 1.0 - math.exp(-2.0 * math.pi * f * step) if f > 0.0 else 0.0
        return np.array([self.position, self.velocity, self.pressure_cap, self.pressure_rod,
                         self.position_resolution, self.pressure_resolution,
                         float(VELOCITY_SOURCES[self.velocity_source]), alpha], dtype=np.float64)


@dataclass(frozen=True)
class Gains:
    """Back-stepping gains k1 [1/s], k2 [1/s], k3 [1/s]."""

    k1: float = 150.0
    k2: float = 158.0
    k3: float = 162.0

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.k1, self.k2, self.k3)


@dataclass(frozen=True)
class Adaptation:
    """Parameter adaptation of â = (â1, â2) ≈ (Bp, Ci) with projection (SPEC §3).

    gain = (σ1, σ2); initial, lower, upper in the units of (Bp, Ci).
    x3d_derivative: 'analytic' (reference) or 'backward_difference'.
    """

    gain: tuple[float, float] = (95000.0, 1.0e-49)
    initial: tuple[float, float] = (2600.0, 4.0e-12)
    lower: tuple[float, float] = (2600.0, 4.0e-12)
    upper: tuple[float, float] = (3000.0, 1.0e-11)
    x3d_derivative: str = "analytic"

    def as_array(self) -> np.ndarray:
        return np.array([
            self.gain[0], self.gain[1], self.initial[0], self.initial[1],
            self.lower[0], self.lower[1], self.upper[0], self.upper[1],
            float(X3D_MODES[self.x3d_derivative]),
        ], dtype=np.float64)


@dataclass(frozen=True)
class Reference:
    """Desired displacement x1d(t) [m] with analytic derivatives up to the third.

    kind 'sine': offset + amplitude·sin(omega·t)      (SPEC: 0.11·sin 2t)
    kind 'step': offset + amplitude·s((t − t0)/rise), s a septic smooth step
                 (C³, so x1d⁽³⁾ exists); rise = 0 gives a hard step.
    kind 'chirp': offset + amplitude·sin(2π(f0·t + (f1 − f0)·t²/(2·sweep)))
    kind 'zero': x1d ≡ offset.
    kind 'road': offset + an ISO 8608 road profile of class road_class (A-E)
                 driven at speed [m/s], band-limited to cutoff [Hz] (what the
                 actuator can follow), seeded (:mod:`has_control.core.road`).
    """

    kind: str = "sine"
    amplitude: float = 0.11
    omega: float = 2.0
    offset: float = 0.0
    t0: float = 0.0
    rise: float = 0.05
    f0: float = 0.1
    f1: float = 2.0
    sweep: float = 10.0
    road_class: str = "C"
    speed: float = 20.0
    cutoff: float = 2.0
    seed: int = 0

    def as_array(self) -> np.ndarray:
        """The reference array's header; a road needs its components or its
        table after it: :func:`has_control.core.reference.reference_array`."""
        return np.array([
            float(REFERENCE_KINDS[self.kind]), self.amplitude, self.omega, self.offset,
            self.t0, self.rise, self.f0, self.f1, self.sweep, 0.0, 0.0, 0.0, 0.0, 0.0,
        ], dtype=np.float64)


@dataclass(frozen=True)
class Episode:
    """Time grid, cost weights and metric window of one run (SPEC §5–6).

    step Δt [s], horizon T [s]; cost J = Σ(λ1|e1| + λ2·u² + λ3|e1|[e1<0])·Δt;
    metrics over skip_start ≤ t ≤ T − skip_end [s]; a run whose |y| exceeds
    y_limit [m] or whose state is not finite has diverged.
    """

    step: float = 3.0e-4
    horizon: float = 10.0
    lambda1: float = 0.001
    lambda2: float = 0.999
    lambda3: float = 10.0
    skip_start: float = 0.5
    skip_end: float = 0.5
    y_limit: float = 1.0

    @property
    def step_ns(self) -> int:
        """The step [ns], as message stamps count it."""
        return int(round(self.step * 1e9))

    @property
    def samples(self) -> int:
        """n = round(T/Δt)."""
        return int(round(self.horizon / self.step))

    def window(self) -> tuple[int, int]:
        """Inclusive sample range [ceil(skip_start/Δt), floor((T − skip_end)/Δt)]."""
        eps = 1e-9
        start = math.ceil(self.skip_start / self.step - eps)
        end = math.floor((self.horizon - self.skip_end) / self.step + eps)
        return start, min(end, self.samples - 1)

    def as_array(self) -> np.ndarray:
        start, end = self.window()
        return np.array([
            self.step, float(self.samples), self.lambda1, self.lambda2, self.lambda3,
            float(start), float(end), self.y_limit,
        ], dtype=np.float64)


@dataclass(frozen=True)
class Config:
    """Everything one episode needs: the reference configuration by default."""

    actuator: Actuator = field(default_factory=Actuator)
    gains: Gains = field(default_factory=Gains)
    adaptation: Adaptation = field(default_factory=Adaptation)
    reference: Reference = field(default_factory=Reference)
    episode: Episode = field(default_factory=Episode)
    plant: Plant = field(default_factory=Plant)
    noise: Noise = field(default_factory=Noise)


#: The paper's hand-set gains and its PSO+CP+TVAC result (SPEC §8).
MANUAL_GAINS = Gains(150.0, 158.0, 162.0)
PAPER_TUNED_GAINS = Gains(656.11, 656.13, 656.14)

#: The paper's Table 3: (e_max, e_μ, e_σ) [m] of |e1| over 0.5–9.5 s (SPEC §8).
PAPER_TABLE3 = {"tuned": (6.1469e-6, 3.6703e-6, 1.7773e-6),
                "manual": (6.7797e-5, 3.6823e-5, 1.9221e-5)}
