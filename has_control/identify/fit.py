"""Identification: bounded nonlinear least squares on short-horizon prediction errors.

Multiple shooting: the recording is cut into short disjoint segments
(:mod:`.segments`); each is predicted by the core's plant step from its own
initial state (:mod:`.kernel`), and the residuals are the measured states
(y, ẏ, P1, P2) at every sample of every segment minus the predictions, per
channel divided by its noise level (the residual RMS). A segment's initial
state is fitted too (one Gauss-Newton step from the measured one, a
variable projection): starting from the noisy measurement instead would let
a parameter explain that noise away (damping "damps" the noise of the
initial velocity when the cylinder barely moves: errors in variables). With
the right parameters the residuals are then the sensors' white noise, and
the Gauss-Newton covariance s²·(JᵀJ)⁻¹ of the projected problem, with s²
over the residuals' degrees of freedom less 4 per segment, gives standard
errors, 95 % intervals and correlations. SciPy's ``least_squares`` (trust-region
reflective, bounds) solves it from the equation-error start
(:mod:`.equation_error`).

Identifiability: a parameter whose 95 % half-width exceeds its own size
(τ_v: 1 ms), or that ends on a bound, is *not identifiable*: it is fixed at
its prior (the model's value) and the others are fitted again without it,
so it never reaches the params file as a number the data did not give. One
whose half-width is within ``tolerance`` of its value (τ_v: ``tau_tolerance``)
is *identified*; between the two, *poorly determined* (its estimate is kept,
its interval says how little it is worth).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter

from has_control.core.params import VELOCITY_ALPHA, Config
from has_control.identify.data import Experiment, IdentificationError
from has_control.identify.equation_error import equation_error
from has_control.identify.kernel import predict_segments
from has_control.identify.parameters import (
    DEFAULT_KEYS, PARAMETERS, TAU_SCALE, default_bounds, given, plant_array, prior, scale,
)
from has_control.identify.segments import SEGMENT_SAMPLES, segment_starts
from has_control.identify.verdict import Verdict, verdict as residual_verdict

CHANNELS = ("y", "ydot", "P1", "P2")
#: 97.5 % quantile of the standard normal: 95 % two-sided intervals.
Z95 = 1.959963984540054
#: Relative step of the central differences of the covariance's Jacobian.
JAC_STEP = 1e-5
#: Usable samples needed per estimated parameter (0.2 s at the reference step).
MIN_SAMPLES_PER_PARAMETER = 660
#: Relative change of the parameters within which the initial-state sensitivities are reused.
KEEP_SENSITIVITY = 1e-4
#: Rounds of re-weighting before and after the first solve.
WEIGHT_ROUNDS = 3
#: How the intervals are made (stated in the JSON).
COVARIANCE = ("the wider, per parameter, of the Gauss-Newton covariance and the segment-clustered sandwich "
              "covariance")
#: A residual of a prediction that blew up (wild parameters): large, finite.
BLOWN_UP = 1e6


@dataclass(frozen=True)
class Estimate:
    """One parameter's result. value [unit]; std_error and the 95 % interval
    (lower, upper) from the Jacobian at the optimum (NaN when fixed before the
    last pass); status: identified | poorly determined | not identifiable;
    ``why`` for the last; prior: the model's value it falls back to."""

    key: str
    value: float
    std_error: float
    lower: float
    upper: float
    status: str
    prior: float
    start: float
    why: str = ""

    @property
    def identified(self) -> bool:
        return self.status == "identified"

    @property
    def unit(self) -> str:
        return PARAMETERS[self.key].unit

    def as_json(self) -> dict:
        f = lambda v: None if not math.isfinite(v) else v  # noqa: E731
        return {"value": self.value, "std_error": f(self.std_error), "ci95": [f(self.lower), f(self.upper)],
                "status": self.status, "identified": self.identified, "why": self.why or None,
                "prior": self.prior, "start": f(self.start), "unit": self.unit}


@dataclass
class IdentificationResult:
    """What :func:`identify` found (like ``scipy.optimize.OptimizeResult``):
    ``estimates`` by key in table order; ``correlation`` of the keys in
    ``free`` (the last pass's); ``singular_values`` of the first pass's
    weighted Jacobian (columns per unit of each parameter's scale: a tiny one
    is a combination the data cannot see); residual RMS per channel [SI];
    ``success``, ``message``, evaluations, segments and seconds."""

    estimates: dict[str, Estimate]
    free: tuple[str, ...]
    correlation: np.ndarray
    singular_values: np.ndarray
    residual_rms: dict[str, float]
    success: bool
    message: str
    evaluations: int
    segments: int
    seconds: float
    passes: int
    given: dict[str, float] = field(default_factory=dict)
    verdict: Verdict | None = None
    #: The last pass's residuals [SI], (segments, L + 1, 4) over every experiment (not in the JSON).
    residuals: np.ndarray | None = field(default=None, repr=False)

    def values(self) -> dict[str, float]:
        """The plant to write: each estimate (a not-identifiable one at its prior)."""
        return {k: e.value for k, e in self.estimates.items()}

    def as_json(self) -> dict:
        return {"estimates": {k: e.as_json() for k, e in self.estimates.items()},
                "correlation": {"keys": list(self.free), "matrix": [[v if math.isfinite(v) else None for v in row]
                                                                    for row in self.correlation.tolist()]},
                "singular_values": self.singular_values.tolist(), "residual_rms": self.residual_rms,
                "success": self.success, "message": self.message, "evaluations": self.evaluations,
                "segments": self.segments, "seconds": self.seconds, "passes": self.passes,
                "model": self.verdict.as_json() if self.verdict is not None else None,
                "covariance": COVARIANCE}


def as_read(pred: np.ndarray, exp: Experiment, s: np.ndarray) -> np.ndarray:
    """``pred`` (segments, L + 1, 4), the predicted true states of the segments
    starting at samples ``s``, as the experiment's sensors read them: with a
    derived velocity (``noise.velocity_source: derived``, a datasheet's fact
    the user declares) the velocity channel is the sensors' own filtered
    backward difference (:func:`~has_control.core.noise.sensor_readings`) of
    the predicted position, from the velocity reading at the segment's start.
    Compared with the true velocity instead, a filter's lag reads as model
    error: on a machine with 210 N of Coulomb friction the friction structure
    found the truth yet lost on BIC (docs/findings.md). Else ``pred`` as it is.
    The velocity channel is rewritten in place; ``pred`` is returned."""
    noise = exp.cfg.noise
    if noise.velocity_source != "derived":
        return pred
    alpha = noise.as_array(exp.step)[VELOCITY_ALPHA]
    d = np.diff(pred[:, :, 0], axis=1) / exp.step                     # (segments, L)
    if alpha == 0.0:
        v = d
    else:                                                             # v_i = v_{i-1} + alpha (d_i - v_{i-1})
        v = lfilter([alpha], [1.0, alpha - 1.0], d, axis=1, zi=((1.0 - alpha) * exp.x[s, 1])[:, None])[0]
    pred[:, 0, 1] = exp.x[s, 1]
    pred[:, 1:, 1] = v
    return pred


#: Samples each side of a segment's start over which a derived velocity's start is the position's slope.
SLOPE_HALF_WIDTH = 5


def initial_states(exp: Experiment, s: np.ndarray) -> np.ndarray:
    """Where each segment's initial state starts (the Gauss-Newton step of the
    variable projection moves it from there): the readings at the segment's
    start, except a derived velocity, which lags the true one by its filter;
    then the slope of the least-squares line through the position readings
    SLOPE_HALF_WIDTH samples each side (centred: no lag; over 11 samples the
    quantisation's steps average out)."""
    x0 = np.ascontiguousarray(exp.x[s])
    if exp.cfg.noise.velocity_source == "derived":
        h = SLOPE_HALF_WIDTH
        i = np.clip(s[:, None] + np.arange(-h, h + 1), 0, len(exp.x) - 1)
        t = (i - s[:, None]) * exp.step
        y = exp.x[i, 0]
        tc = t - t.mean(axis=1, keepdims=True)
        x0[:, 1] = np.sum(tc * (y - y.mean(axis=1, keepdims=True)), axis=1) / np.sum(tc * tc, axis=1)
    return x0


class _Problem:
    """Output-error residuals of ``keys`` (in units of their scales) over
    experiments, each segment from its own best initial state (see the module)."""

    def __init__(self, exps: list[Experiment], keys: tuple[str, ...], scales: np.ndarray,
                 fixed: dict[str, float], length: int):
        self.exps, self.keys, self.scales, self.length = exps, keys, scales, length
        self.starts = [segment_starts(e, length) for e in exps]
        self.bases = [plant_array(e.cfg.plant.as_array(e.cfg.actuator), list(fixed), list(fixed.values()))
                      for e in exps]
        rows = np.arange(length + 1)
        self.meas = [e.x[s[:, None] + rows] for e, s in zip(exps, self.starts)]     # (segments, L + 1, 4)
        self.x0 = [initial_states(e, s) for e, s in zip(exps, self.starts)]
        self.weights = np.ones(4)
        self.evaluations = 0
        self._sens_at: dict = {}

    @property
    def segments(self) -> int:
        return int(sum(len(s) for s in self.starts))

    @property
    def nuisance(self) -> int:
        """Initial states fitted with the parameters: 4 per segment."""
        return 4 * self.segments

    def raw(self, z: np.ndarray) -> list[np.ndarray]:
        """(segments, L + 1, 4) output errors [SI] of each experiment at z, each
        segment from the initial state that fits it best (one Gauss-Newton step
        from the measured one: the prediction is nearly linear in it)."""
        self.evaluations += 1
        values = z * self.scales
        out = []
        for k, (exp, base, s, meas) in enumerate(zip(self.exps, self.bases, self.starts, self.meas)):
            x0 = self.x0[k]
            pred = self._predict(exp, base, s, values, x0)
            w = self.weights
            jw, inv = self._projector(k, exp, base, s, values, x0, pred, z)
            rw = ((pred - meas) * w).reshape(len(s), -1)
            step = -np.einsum("nij,nj->ni", inv, np.einsum("nki,nk->ni", jw, rw))
            step = np.where(np.isfinite(step), step, 0.0)
            out.append(self._predict(exp, base, s, values, x0 + step) - meas)
        return out

    def _projector(self, k, exp, base, s, values, x0, pred, z):
        """Each segment's weighted sensitivity of its prediction to its initial
        state, and the inverse of its normal matrix. Kept while z stays within
        KEEP_SENSITIVITY of where they were computed (the solver's and the
        covariance's difference steps, the last small steps): the sensitivities
        barely change there, and the projection's derivative with them held is
        Kaufman's approximation of variable projection."""
        key = self._sens_at.get(k)
        if key is not None and np.all(np.abs(z - key[0]) <= KEEP_SENSITIVITY * np.maximum(np.abs(key[0]), 1.0)) \
                and np.array_equal(key[1], self.weights):
            return key[2], key[3]
        w = self.weights
        sens = np.empty(pred.shape + (4,))
        for j in range(4):
            h = _STATE_STEP[j]
            xj = x0.copy()
            xj[:, j] += h
            sens[..., j] = (self._predict(exp, base, s, values, xj) - pred) / h
        jw = (sens * w[None, None, :, None]).reshape(len(s), -1, 4)
        jtj = np.einsum("nki,nkj->nij", jw, jw) + 1e-12 * np.eye(4)
        with np.errstate(all="ignore"):
            inv = np.linalg.inv(jtj)
        self._sens_at[k] = (z.copy(), self.weights.copy(), jw, inv)
        return jw, inv

    def _predict(self, exp, base, s, values, x0):
        dt = exp.step
        tau = dict(zip(self.keys, values)).get("valve_time_constant")
        if tau is not None and 0.0 < tau < dt:
            # A lag shorter than one step (not a plant the config accepts): a smooth
            # blend of the ideal valve and the one-step lag, so the solver sees a slope.
            w = tau / dt
            return (w * self._run(exp, plant_array(base, self.keys, _with(self.keys, values, dt)), s, x0)
                    + (1.0 - w) * self._run(exp, plant_array(base, self.keys, _with(self.keys, values, 0.0)), s,
                                            x0))
        return self._run(exp, plant_array(base, self.keys, values), s, x0)

    def _run(self, exp, pp, s, x0):
        out = np.empty((len(s), self.length + 1, 4))
        predict_segments(pp, exp.step, np.ascontiguousarray(x0), exp.u, s, self.length, out)
        return as_read(out, exp, s)

    def __call__(self, z: np.ndarray) -> np.ndarray:
        r = (np.concatenate(self.raw(z)) * self.weights).ravel()
        bad = ~np.isfinite(r)
        if bad.any():
            r[bad] = BLOWN_UP
        return r

    def set_weights(self, z: np.ndarray) -> dict[str, float]:
        """Weights 1/RMS per channel from the residuals at z (the sensors' noise,
        independent per channel and sample); returns the RMS [SI]."""
        r = np.concatenate(self.raw(z)).reshape(-1, 4)
        sig = _rms(np.concatenate([e.x for e in self.exps]), centred=True)
        rms = np.maximum(_rms(r), 1e-12 * np.maximum(sig, 1e-300))
        self.weights = 1.0 / rms
        return dict(zip(CHANNELS, map(float, rms)))

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        cols = []
        for k in range(len(z)):
            h = JAC_STEP * max(abs(z[k]), 1.0)
            zp, zm = z.copy(), z.copy()
            zp[k] += h
            zm[k] -= h
            cols.append((self(zp) - self(zm)) / (2 * h))
        return np.column_stack(cols)


def _rms(a: np.ndarray, centred: bool = False) -> np.ndarray:
    """Each column's RMS (``centred``: its standard deviation) [its unit], the
    plain formula unless a square overflows; then scaled by the column's
    largest magnitude, so a 1e300 sample gives 1e300-ish, never inf or 0 (a
    channel weight 1/RMS must not vanish or explode on one wild sample)."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = a.std(axis=0) if centred else np.sqrt(np.mean(a * a, axis=0))
    if np.isfinite(out).all():
        return out
    m = np.maximum(np.max(np.abs(a), axis=0), 1e-300)
    b = a / m
    return m * (b.std(axis=0) if centred else np.sqrt(np.mean(b * b, axis=0)))


#: Steps of the initial state's sensitivities: y [m], ẏ [m/s], P1, P2 [Pa].
_STATE_STEP = np.array([1e-6, 1e-4, 1e3, 1e3])


def _with(keys, values, tau):
    return [tau if k == "valve_time_constant" else v for k, v in zip(keys, values)]


def identify(experiments: list[Experiment], estimate=DEFAULT_KEYS, bounds: dict | None = None,
             tolerance: float = 0.02, tau_tolerance: float = 5e-5, max_evaluations: int = 200,
             length: int = SEGMENT_SAMPLES, start: dict | None = None) -> IdentificationResult:
    """Estimate ``estimate`` (keys of :data:`~.parameters.PARAMETERS`) from the
    experiments; see the module. ``bounds``: key -> (lower, upper) [SI]
    (default: :func:`~.parameters.default_bounds` of the prior); the prior
    (the model's value, :func:`~.parameters.prior`) must lie within them.
    ``tolerance``: relative 95 % half-width of an identified parameter;
    ``tau_tolerance`` [s]: the same for τ_v. Raises IdentificationError (one
    line) on bad input and on a fit that does not converge within
    ``max_evaluations`` residual evaluations per pass. ``start``: key -> where
    the solver starts (default: the equation-error estimate, else the prior)."""
    t0 = time.perf_counter()
    keys = tuple(k for k in PARAMETERS if k in set(estimate))
    unknown = [k for k in estimate if k not in PARAMETERS]
    if unknown:
        raise IdentificationError(f"--estimate {unknown[0]}: not an estimable parameter; "
                                  f"one of {', '.join(PARAMETERS)}")
    if not keys:
        raise IdentificationError("--estimate: nothing to estimate")
    if not experiments:
        raise IdentificationError("no experiment to identify from")
    cfg0 = experiments[0].cfg
    priors = {k: prior(cfg0, k) for k in keys}
    bnds = {k: default_bounds(k, priors[k]) for k in keys}
    for k, (lo, hi) in (bounds or {}).items():
        if k not in keys:
            raise IdentificationError(f"--bound {k}: not among the estimated parameters ({', '.join(keys)})")
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise IdentificationError(f"--bound {k} {lo:g} {hi:g}: expected finite LOWER < UPPER")
        bnds[k] = (float(lo), float(hi))
    for k in keys:
        lo, hi = bnds[k]
        if not lo <= priors[k] <= hi:
            raise IdentificationError(f"--bound {k} {lo:g} {hi:g}: excludes the start, the model's "
                                      f"{k} = {priors[k]:g}")
    probe = _Problem(experiments, keys, np.ones(len(keys)), {}, length)
    usable = probe.segments * (length + 1)
    need = MIN_SAMPLES_PER_PARAMETER * len(keys)
    if usable < need:
        raise IdentificationError(
            f"{experiments[0].name}: {usable} usable samples (in segments of {length} steps with the pressures off "
            f"their bounds); estimating {len(keys)} parameters needs at least {need}: record a longer run")
    ee = equation_error(experiments, probe.starts, length)
    given_start = dict(start or {})
    start = {}
    for k in keys:
        v = given_start.get(k, ee.get(k, priors[k]))
        lo, hi = bnds[k]
        start[k] = float(np.clip(v, lo, hi)) if math.isfinite(v) and v >= 0 else priors[k]
    free, fixed, why = list(keys), {}, {}
    first_sv = None
    evaluations, passes = 0, 0
    while True:
        passes += 1
        fit = _fit(experiments, tuple(free), start, bnds, {**fixed}, max_evaluations, length)
        evaluations += fit["evaluations"]
        if first_sv is None:
            first_sv = fit["singular_values"]
        dropped = {}
        for i, k in enumerate(free):
            reason = _unidentifiable(k, fit["values"][i], fit["se"][i], fit["at_bound"][i], bnds[k])
            if reason:
                dropped[k] = reason
        if not fit["converged"] and (not dropped or len(dropped) == len(free)):
            # a parameter the data cannot see can keep the solver wandering: dropped, the rest may
            # converge; with nothing to drop, the fit failed
            raise IdentificationError(f"the fit did not converge within {max_evaluations} evaluations "
                                      f"({fit['message']}); no parameters written")
        if not dropped or len(dropped) == len(free):
            break
        for i, k in enumerate(fit["keys"]):
            start[k] = priors[k] if k in dropped else fit["values"][i]
        for k, reason in dropped.items():
            why[k] = reason
            fixed[k] = priors[k]
        free = [k for k in free if k not in dropped]
    estimates = {}
    for k in keys:
        if k in fixed:
            estimates[k] = Estimate(k, priors[k], math.nan, math.nan, math.nan, "not identifiable", priors[k],
                                    ee.get(k, math.nan), why[k])
            continue
        i = free.index(k)
        v, se = fit["values"][i], fit["se"][i]
        reason = _unidentifiable(k, v, se, fit["at_bound"][i], bnds[k])
        if reason:
            estimates[k] = Estimate(k, priors[k], math.nan, math.nan, math.nan, "not identifiable",
                                    priors[k], ee.get(k, math.nan), reason)
            continue
        half = Z95 * se
        ok = half <= (tau_tolerance if k == "valve_time_constant" else tolerance * abs(v))
        estimates[k] = Estimate(k, v, se, v - half, v + half, "identified" if ok else "poorly determined",
                                priors[k], ee.get(k, math.nan))
    result = IdentificationResult(
        estimates, tuple(free), fit["correlation"], first_sv, fit["rms"], True, fit["message"], evaluations,
        fit["segments"], time.perf_counter() - t0, passes,
        {**{k: given(cfg0, k) for k in PARAMETERS if k not in keys}, "delay": int(cfg0.plant.delay),
         "friction_stribeck": float(cfg0.plant.friction_stribeck)},
        residuals=np.concatenate(fit["raw"]) if fit["raw"] else None)
    corner = valve_corner_hz({**result.given, **result.values()})
    return apply_verdict(result, residual_verdict(experiments, fit["raw"], fit["starts"], length, corner))


def valve_corner_hz(values: dict[str, float]) -> float:
    """The valve's corner frequency [Hz]: the natural frequency of a
    second-order spool, 1/(2π·τ_v) of a first-order lag, inf for an ideal valve."""
    if values.get("valve_frequency", 0.0) > 0.0:
        return float(values["valve_frequency"])
    tau = values.get("valve_time_constant", 0.0)
    return 1.0 / (2.0 * math.pi * tau) if tau > 0.0 else math.inf


#: The spool's own parameters, which only an excitation reaching its corner determines.
SPOOL_KEYS = ("valve_frequency", "valve_damping_ratio")


def apply_verdict(result: IdentificationResult, v: Verdict) -> IdentificationResult:
    """``result`` judged by ``v``: with an INADEQUATE model no estimate stays
    "identified" (its interval measures the noise, not the model's error).
    A valve whose dynamics the band does not reach keeps its τ_v (the
    low-frequency lag, which the data do determine): the verdict's line says
    that its order is not seen; a second-order spool's ω_n and ζ are then at
    most "poorly determined" (the low-frequency phase gives 2ζ/ω_n; a limit
    cycle gives one gain and one phase, see :mod:`.verdict`)."""
    estimates = {}
    for k, e in result.estimates.items():
        if e.status == "identified" and not v.adequate:
            e = dataclasses.replace(e, status="poorly determined",
                                    why="the model is INADEQUATE: the interval holds for the model, not the machine")
        elif e.status == "identified" and k in SPOOL_KEYS and not v.valve_determined:
            e = dataclasses.replace(e, status="poorly determined",
                                    why="the valve's dynamics are not determined by the command's broadband band: "
                                        "the interval rests on the model's exact form")
        estimates[k] = e
    return dataclasses.replace(result, estimates=estimates, verdict=v)


def _unidentifiable(key: str, value: float, se: float, at_bound: bool, bound) -> str:
    if at_bound:
        return f"ends on its bound {value:g} (the data push it beyond [{bound[0]:g}, {bound[1]:g}])"
    half = Z95 * se
    if not math.isfinite(half):
        return "the data do not determine it (the Jacobian is singular in it)"
    if key == "valve_time_constant":
        if half > TAU_SCALE:
            return f"95 % half-width {half * 1e3:.3g} ms exceeds 1 ms"
        return ""
    if half > abs(value):
        return f"95 % half-width {half / abs(value) * 100 if value else math.inf:.3g} % of its value"
    return ""


def _fit(exps, keys, start, bnds, fixed, max_evaluations, length) -> dict:
    """One least-squares pass over ``keys`` with ``fixed`` held; its statistics."""
    scales = np.array([scale(k, start[k]) for k in keys])
    prob = _Problem(exps, keys, scales, fixed, length)
    z0 = np.array([start[k] for k in keys]) / scales
    lo = np.array([bnds[k][0] for k in keys]) / scales
    hi = np.array([bnds[k][1] for k in keys]) / scales
    z0 = np.clip(z0, lo, hi)
    for _ in range(WEIGHT_ROUNDS):           # the initial states' fit depends on the weights, and back
        prob.set_weights(z0)
    res = least_squares(prob, z0, bounds=(lo, hi), method="trf", x_scale=1.0, diff_step=1e-6,
                        max_nfev=max_evaluations, xtol=1e-8, ftol=1e-8, gtol=1e-8)
    converged = res.status > 0 and bool(np.isfinite(res.cost))
    if converged:
        for _ in range(WEIGHT_ROUNDS):           # final weights: the channels' own residual RMS
            rms = prob.set_weights(res.x)
        res = least_squares(prob, res.x, bounds=(lo, hi), method="trf", x_scale=1.0, diff_step=1e-6,
                            max_nfev=max_evaluations, xtol=1e-8, ftol=1e-8, gtol=1e-8)
        converged = res.status > 0 and bool(np.isfinite(res.cost))
    rms = prob.set_weights(res.x)
    raw = prob.raw(res.x)
    r = prob(res.x)
    jac = prob.jacobian(res.x)
    dof = max(len(r) - len(keys) - prob.nuisance, 1)
    s2 = float(r @ r) / dof
    u_, sv, vt = np.linalg.svd(jac, full_matrices=False)
    tiny = sv <= sv[0] * 1e-10
    inv = np.where(tiny, np.inf, 1.0 / np.where(tiny, 1.0, sv) ** 2)
    cov_z = (vt.T * inv) @ vt * s2 if not tiny.any() else _cov_with_null(vt, sv, tiny, s2)
    sandwich = _sandwich(jac, r, prob.segments, cov_z, s2)
    se = np.maximum(np.sqrt(np.abs(np.diag(cov_z))), np.sqrt(np.abs(np.diag(sandwich)))) * scales
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(np.abs(np.diag(cov_z)))
        corr = cov_z / np.outer(d, d)
    span = hi - lo
    at_bound = (res.active_mask != 0) | (np.minimum(res.x - lo, hi - res.x) < 1e-9 * np.maximum(span, 1.0))
    return {"keys": keys, "converged": converged, "message": res.message, "values": res.x * scales, "se": se,
            "correlation": corr, "singular_values": sv,
            "at_bound": at_bound, "rms": rms, "segments": prob.segments,
            "evaluations": prob.evaluations, "raw": raw, "starts": prob.starts}


def _sandwich(jac, r, segments, cov_z, s2):
    """The segment-clustered sandwich covariance B·(Σ_s g_s g_sᵀ)·B, g_s = J_sᵀ r_s
    over the rows of segment s and B = cov_z/s² = (JᵀJ)⁻¹: what the
    residuals' own spread from segment to segment says, where the
    Gauss-Newton covariance assumes them white (it is not, for a model that
    misses part of the physics)."""
    if segments == 0 or len(r) % segments or not np.all(np.isfinite(cov_z)):
        return cov_z
    g = np.einsum("nrk,nr->nk", jac.reshape(segments, -1, jac.shape[1]), r.reshape(segments, -1))
    bread = cov_z / max(s2, 1e-300)
    return bread @ (g.T @ g) @ bread


def _cov_with_null(vt, sv, tiny, s2):
    """Covariance when the Jacobian is singular: infinite along the null directions."""
    ok = ~tiny
    cov = (vt[ok].T / sv[ok] ** 2) @ vt[ok] * s2
    null = np.abs(vt[tiny]).max(axis=0) > 1e-3
    cov[null, :] = np.inf
    cov[:, null] = np.inf
    return cov


def identified_config(cfg: Config, result: IdentificationResult) -> Config:
    """``cfg`` with its plant (``plant.*``) set to the identified values, in
    the identified structure (valve, delay, friction)."""
    structural = ("valve_time_constant", "valve_frequency", "valve_damping_ratio", "friction_coulomb",
                  "friction_stribeck", "delay")
    changes = {**{k: v for k, v in result.given.items() if k in structural}, **result.values()}
    if "friction_coulomb" in result.estimates:                       # identified without a Stribeck peak
        changes["friction_stribeck"] = changes["friction_coulomb"]
    tau = changes.get("valve_time_constant")
    if tau is not None and 0.0 < tau < cfg.episode.step:       # the plant takes 0 or >= one step
        changes["valve_time_constant"] = 0.0 if tau < 0.5 * cfg.episode.step else cfg.episode.step
    return dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, **changes))
