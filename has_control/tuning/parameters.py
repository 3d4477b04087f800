"""The tuning settings' table: every ``swarm.*`` and ``restarts.*`` key of
``config/tuner.yaml`` as a :class:`~has_control.config.table.Param` (type,
unit, meaning, range, choices).

Defaults come from ``config/tuner.yaml`` (:func:`~has_control.tuning.tuner.load_tuning`);
the relations between keys (``swarm.lower`` below ``swarm.upper``, particles ×
iterations within the budget, ...) are checked by
:func:`~has_control.tuning.tuner.tuning_from_parameters`, the one check every
front end (``tune``, the tuner node) passes.
"""
from __future__ import annotations

from has_control.config import GAIN_MAX, SEED_LIMIT, SEED_RANGE, Param, table
from has_control.tuning.methods import METHODS
from has_control.tuning.restarts import MAX_EVALUATIONS, SCALES
from has_control.tuning.swarm import CRAZY_PROBABILITIES, CRAZY_REDRAWS, MAX_PARTICLES

_BOX = dict(lower=0.0, lower_open=True, upper=GAIN_MAX)


def _d(name: str, text: str, unit: str = "", **rng) -> Param:
    return Param(name, "double", unit=unit, text=text, **rng)


def _i(name: str, text: str, lower: int, upper: int | None = None, unit: str = "") -> Param:
    return Param(name, "int", unit=unit, text=text, lower=lower, upper=upper)


#: ``swarm.*`` and ``restarts.*``: the tuning settings' table.
TUNING_TABLE: dict[str, Param] = table((
    Param("swarm.variant", "str", text="the method: " + " | ".join(METHODS), choices=tuple(METHODS)),
    Param("swarm.seed", "int", text="fixes every random draw", lower=0, upper=SEED_LIMIT - 1,
          range_words=f"in {SEED_RANGE}"),
    _i("swarm.particles", "N, particles per iteration (pso, pso-cp, pso-cp-tvac)", 1, MAX_PARTICLES),
    _i("swarm.iterations", "MAXITER, iterations (pso, pso-cp, pso-cp-tvac)", 1, MAX_EVALUATIONS),
    _d("swarm.target", "stop when the best J <= target"),
    Param("swarm.lower", "double[]", unit="1/s", text="x_min for (k1, k2, k3)", length=3, **_BOX),
    Param("swarm.upper", "double[]", unit="1/s", text="x_max for (k1, k2, k3)", length=3, **_BOX),
    _d("swarm.velocity_limit", "v_max of a particle per iteration (v_min = -v_max)", "1/s", lower=0.0,
       lower_open=True),
    _d("swarm.inertia_max", "omega_max, inertia weight at the first iteration"),
    _d("swarm.inertia_min", "omega_min, inertia weight at the last iteration"),
    _d("swarm.c1", "cognitive acceleration c1 (PSO, PSO+CP)"),
    _d("swarm.c2", "social acceleration c2 (PSO, PSO+CP)"),
    _d("swarm.c1_start", "TVAC: c1 at the first iteration"),
    _d("swarm.c1_end", "TVAC: c1 at the last iteration"),
    _d("swarm.c2_start", "TVAC: c2 at the first iteration"),
    _d("swarm.c2_end", "TVAC: c2 at the last iteration"),
    Param("swarm.crazy_redraw", "str", text="positive: U(0, v_max) (paper Eq. 37) | symmetric: U(-v_max, v_max)",
          choices=CRAZY_REDRAWS),
    Param("swarm.crazy_probability", "str", text="exp-difference: w_min*exp(w - w_max) (SPEC) | exp-ratio: "
          "w_min*exp(-w/w_max)", choices=CRAZY_PROBABILITIES),
    _i("restarts.evaluations", "cma-restarts: the budget, every candidate scored counts one", 1, MAX_EVALUATIONS),
    _i("restarts.population", "lambda of each CMA-ES search (pycma's default for 3 gains: 7)", 2),
    _i("restarts.side_by_side", "searches whose candidates go to the evaluator in one batch (2 x 7: two "
       "blocks of 8 lanes, both cores busy)", 1),
    _d("restarts.sigma", "initial step, a fraction of the box", lower=0.0, lower_open=True, upper=1.0),
    _d("restarts.tolerance", "a search has converged when its best J spans < tolerance * J over the window",
       lower=0.0, lower_open=True),
    _i("restarts.window", "generations of that window", 1),
    _i("restarts.polish", "evaluations kept for the polish", 0),
    _i("restarts.polish_starts", "distinct best points polished side by side", 1),
    _d("restarts.polish_sigma", "the polish's initial step, a fraction of the box", lower=0.0, lower_open=True,
       upper=1.0),
    Param("restarts.scale", "str", text="search the box in log k (the valley k1*k2*k3 ~ const is straight) "
          "or k (linear)", choices=SCALES),
))
