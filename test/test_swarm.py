"""The particle swarm (SPEC §7): convergence, determinism, checkpoints, validation."""
import json
import math

import numpy as np
import pytest

from has_control.tuning.methods import minimize
from has_control.tuning.swarm import Swarm, SwarmError, SwarmSettings, crazy_probability


def sphere(x):
    return np.sum(x * x, axis=1)


BOX5 = ([-5.0] * 5, [5.0] * 5)


def test_pso_reaches_1e_6_on_a_5d_sphere_within_its_budget():
    # CEC-style budget 10 000·D = 50 000 evaluations: 50 particles x 1000 iterations
    r = minimize(sphere, BOX5, method="pso", particles=50, iterations=1000, seed=1,
                 velocity_limit=1.0)
    assert r.fun < 1e-6 and r.nfev <= 50_000


@pytest.mark.parametrize("variant", ["pso-cp", "pso-cp-tvac"])
@pytest.mark.parametrize("redraw", ["positive", "symmetric"])
def test_crazy_variants_converge_but_stall_above_1e_6_under_the_papers_probability(variant, redraw):
    """Measured finding (README): ρc = ω_min·exp(ω − ω_max) redraws 33–60 % of velocity
    components every iteration, so the CP variants approach the optimum but keep
    being kicked off it: on the 5-D sphere they reach ~1e-4, not 1e-6."""
    r = minimize(sphere, BOX5, method=variant, particles=50, iterations=1000, seed=1,
                 velocity_limit=0.15, crazy_redraw=redraw)
    start = r.history[0].best_cost
    assert r.fun < 1e-2 < start
    assert r.fun > 1e-6


def test_crazy_probability_readings():
    s = SwarmSettings()
    assert crazy_probability(1.2, s) == pytest.approx(0.6)
    assert crazy_probability(0.6, s) == pytest.approx(0.6 * math.exp(-0.6))
    alt = SwarmSettings(crazy_probability="exp-ratio")
    assert crazy_probability(1.2, alt) == pytest.approx(0.6 * math.exp(-1.0))


@pytest.mark.parametrize("variant", ["pso", "pso-cp", "pso-cp-tvac"])
def test_same_seed_same_result_bit_for_bit(variant):
    a = minimize(sphere, BOX5, method=variant, particles=20, iterations=50, seed=42)
    b = minimize(sphere, BOX5, method=variant, particles=20, iterations=50, seed=42)
    c = minimize(sphere, BOX5, method=variant, particles=20, iterations=50, seed=43)
    assert np.array_equal(a.x, b.x) and a.fun == b.fun
    assert np.array_equal(a.best_costs(), b.best_costs())
    assert not np.array_equal(a.x, c.x)


@pytest.mark.parametrize("variant", ["pso", "pso-cp-tvac"])
def test_checkpoint_restore_gives_the_uninterrupted_result(variant):
    full = minimize(sphere, BOX5, method=variant, particles=15, iterations=40, seed=5)
    sw = Swarm(BOX5, SwarmSettings(variant=variant, particles=15, iterations=40), seed=5)
    for _ in range(17):
        sw.tell(sphere(sw.ask()))
    saved = json.dumps(sw.state_dict())            # through text, as on disk
    del sw
    resumed = minimize(sphere, None, optimiser=Swarm.from_state(json.loads(saved)))
    assert np.array_equal(resumed.x, full.x) and resumed.fun == full.fun
    assert resumed.nit == full.nit == 40 and resumed.nfev == full.nfev
    assert np.array_equal(resumed.best_costs(), full.best_costs())


def test_positions_stay_in_bounds_and_velocities_within_limits():
    sw = Swarm(([150, 150, 150], [1200, 800, 800]), SwarmSettings(particles=30, iterations=30), 3)
    rng = np.random.default_rng(0)
    while not sw.done:
        x = sw.ask()
        assert np.all(x >= sw.lower) and np.all(x <= sw.upper)
        assert np.all(np.abs(sw.v) <= 15.0)
        sw.tell(rng.random(len(x)))


def test_nan_costs_count_as_inf():
    calls = []

    def objective(x):
        f = sphere(x)
        f[0] = np.nan
        calls.append(1)
        return f
    r = minimize(objective, BOX5, method="pso-cp-tvac", particles=10, iterations=5, seed=0)
    assert r.nan_costs == 5 and math.isfinite(r.fun)
    assert all(h.costs[0] == math.inf for h in r.history)


def test_early_stop_at_target():
    r = minimize(lambda x: np.zeros(len(x)), BOX5, method="pso-cp-tvac", particles=5, iterations=100, seed=0)
    assert r.nit == 1 and "target" in r.message


@pytest.mark.parametrize("kwargs, culprit", [
    (dict(method="pso-xx"), "swarm.variant = 'pso-xx'"),
    (dict(particles=0), "swarm.particles = 0"),
    (dict(iterations=0), "swarm.iterations = 0"),
    (dict(velocity_limit=0.0), "swarm.velocity_limit = 0.0"),
    (dict(velocity_limit=-1.0), "swarm.velocity_limit = -1.0"),
    (dict(bounds=([1.0, 2.0], [1.0, 3.0])), "bounds[0]: lower 1 must be below upper 1"),
    (dict(crazy_redraw="wild"), "swarm.crazy_redraw = 'wild'"),
])
def test_invalid_settings_are_rejected_in_one_line(kwargs, culprit):
    bounds = kwargs.pop("bounds", BOX5)
    kwargs.setdefault("method", "pso-cp-tvac")
    with pytest.raises(SwarmError) as info:
        minimize(sphere, bounds, **kwargs)
    assert culprit in str(info.value) and "\n" not in str(info.value)


@pytest.mark.system
def test_bench_swarm_protocol_runs_resumes_and_reports(tmp_path):
    """scripts/bench_swarm.py in small: a run appends JSON lines, a second run
    with the same settings adds nothing, and the report has the table."""
    import subprocess
    import sys
    from pathlib import Path
    script = Path(__file__).resolve().parents[1] / "has_control" / "bench" / "swarm_peers.py"
    out = tmp_path / "ours.jsonl"
    run = [sys.executable, str(script), "--run", "ours", "--functions", "sphere", "rastrigin",
           "--dims", "2", "--seeds", "2", "--optimisers", "pso", "--out", str(out)]
    subprocess.run(run, check=True, capture_output=True)
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == 4 and {r["evaluations"] for r in rows} == {20_000}
    # a CEC-style checkpoint never gets worse as the budget grows
    assert all(r["errors"] == sorted(r["errors"], reverse=True) for r in rows)
    subprocess.run(run, check=True, capture_output=True)
    assert len(out.read_text().splitlines()) == 4
    bad = subprocess.run(run[:-4] + ["--optimisers", "nope"], capture_output=True, text=True)
    assert bad.returncode == 2 and "unknown 'nope'" in bad.stderr
    subprocess.run([sys.executable, str(script), "--report", str(tmp_path)], check=True,
                   capture_output=True)
    report = (tmp_path / "report.md").read_text()
    assert "## sphere, D = 2" in report and "| pso | 2 |" in report
