"""cma-restarts, the default tuning method: the same bits for a seed, resumable
bit for bit (from a state, and after SIGKILL through the CLI), the same on Dask;
and the bound diagnostics of a tuning result."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import cli

from has_control.bag import BagError, read_bag, score_bag
from has_control.config import CONFIG_DIR, Scenario, load_scenarios, with_horizon
from has_control.core.scenarios import parse_aggregate
from has_control.core.episode import evaluate
from has_control.core.params import Config
from has_control.tuning.bounds import diagnose
from has_control.tuning.methods import minimize, restore
from has_control.tuning.restarts import Restarts, RestartSettings
from has_control.tuning.session import ITERATION, SESSION
from has_control.tuning.swarm import SwarmError, record_dict
from has_control.tuning.tuner import Tuning, tune

BOX = ([150.0, 150.0, 150.0], [1200.0, 800.0, 800.0])
SHORT = with_horizon(Config(), 1.5)
#: A valve with lag and sensors with noise: the world where high gain costs something.
LAGGY = (("plant.valve_time_constant", 1.0e-3), ("noise.position", 1.0e-6), ("noise.velocity", 1.0e-4),
         ("noise.pressure_cap", 1.0e4), ("noise.pressure_rod", 1.0e4), ("noise.seed", 7))


def short(k):
    return evaluate(k, SHORT)


def _same(a, b) -> bool:
    return (len(a.history) == len(b.history)
            and all(np.array_equal(x.positions, y.positions) and np.array_equal(x.costs, y.costs)
                    for x, y in zip(a.history, b.history))
            and np.array_equal(a.x, b.x) and a.fun == b.fun and a.nfev == b.nfev)


def test_the_same_seed_gives_the_same_bits_and_another_seed_another_search():
    a = minimize(short, BOX, seed=3, evaluations=420)
    b = minimize(short, BOX, seed=3, evaluations=420)
    c = minimize(short, BOX, seed=4, evaluations=420)
    assert _same(a, b)
    assert not np.array_equal(a.history[0].positions, c.history[0].positions)


def test_candidates_stay_in_the_box_and_the_budget_is_kept():
    s = RestartSettings(evaluations=420)
    r = minimize(short, BOX, seed=5, evaluations=420)
    x = np.vstack([h.positions for h in r.history])
    assert np.all(x >= BOX[0]) and np.all(x <= BOX[1])
    assert r.nfev == x.shape[0] <= s.evaluations + s.population
    assert np.all(np.diff(r.best_costs()) <= 0) and r.fun == min(h.costs.min() for h in r.history)
    # several searches side by side: whole populations in one batch
    assert r.history[0].positions.shape[0] == s.side_by_side * s.population


def test_a_restored_run_continues_with_the_same_bits():
    whole = minimize(short, BOX, seed=11, evaluations=600)
    run = Restarts(BOX, RestartSettings(evaluations=600), seed=11)
    for _ in range(4):
        run.tell(short(run.ask()))
    state = json.loads(json.dumps(run.state_dict(history=False)))      # what the session bag stores
    state["history"] = [json.loads(json.dumps(record_dict(h))) for h in run.history]
    again = restore(state)
    assert again.iteration == 4 and again.evaluations == run.evaluations and again.gbest_f == run.gbest_f
    while not again.done:
        again.tell(short(again.ask()))
    assert _same(again.result(), whole)


def test_a_record_the_replay_does_not_ask_for_is_refused():
    run = Restarts(BOX, RestartSettings(evaluations=300), seed=2)
    for _ in range(2):
        run.tell(short(run.ask()))
    state = run.state_dict()
    state["history"][1]["positions"][0][0] += 1e-9
    with pytest.raises(SwarmError, match="other candidates than recorded"):
        restore(state)


@pytest.mark.system
def test_a_session_killed_mid_way_resumes_to_the_same_result(tmp_path):
    args = ["tune", "--evaluations", 2500, "--duration", 1.5, "--json"]
    full = cli(*args)
    assert full.returncode == 0, full.stderr
    d = tmp_path / "session"
    p = subprocess.Popen([sys.executable, "-m", "has_control.cli", *map(str, args), "--out", d],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    done = 0
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.02)
        try:
            done = read_bag(d / SESSION, topics=[ITERATION], on_warning=lambda m: None).count(ITERATION)
        except BagError:
            continue
        if done >= 5:
            break
    assert p.poll() is None, "the session ended before it could be killed"
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    resumed = cli("tune", "--resume", d, "--json")
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming" in resumed.stderr
    a, b = json.loads(full.stdout), json.loads(resumed.stdout)
    a.pop("seconds"), b.pop("seconds")
    assert a["variant"] == "cma-restarts" and a == b                  # the same answer, bit for bit
    assert read_bag(d / SESSION).count(ITERATION) == a["iterations"] > done
    bag = read_bag(d / SESSION)
    assert bag.complete
    assert score_bag(d / SESSION)[0].J == a["J"]           # the validation run of the best gains
    again = cli("tune", "--resume", d)
    assert again.returncode == 2 and "finished already" in again.stderr


@pytest.mark.cluster
def test_tuning_on_dask_gives_the_local_bits():
    pytest.importorskip("distributed")
    from has_control.tuning.dask_evaluator import dask_batch
    t = Tuning().replace(evaluations=300, scenarios=(Scenario("nominal"), Scenario("laggy", LAGGY)))
    local = tune(SHORT, t)
    with dask_batch("local:2") as batch:
        remote = tune(SHORT, t, batch=batch)
    assert remote.variant == "cma-restarts" and _same(local.result, remote.result)
    assert remote.as_json()["bounds"] == local.as_json()["bounds"]


# --- bound diagnostics ---------------------------------------------------------------------------

@pytest.mark.system
def test_the_nominal_optimum_is_the_bounds_and_the_cli_says_so(tmp_path):
    """Around the best gains in the box, k1 ends on its upper bound 1200, and J
    still falls beyond it: the bound warning, in the text and the JSON."""
    box = tmp_path / "box.yaml"
    box.write_text("/**:\n  ros__parameters:\n    swarm:\n      lower: [800.0, 150.0, 150.0]\n"
                   "      upper: [1200.0, 400.0, 400.0]\n")
    r = cli("tune", "--config", box, "--evaluations", 700, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["gains"][0] == pytest.approx(1200.0, abs=0.5)
    (check,) = [c for c in out["bounds"]["on_bound"] if c["gain"] == "k1"]
    assert check["side"] == "upper" and check["falls"] and check["J_beyond"] < check["J_bound"]
    assert check["slope"] < 0 and out["bounds"]["evaluations"] >= 1
    assert ("k1 = 1200 is the upper bound and J still falls beyond it: the cost rewards gain without limit "
            "on this model; widen the bound, or tune over scenarios with valve lag and sensor noise"
            ) in out["bounds"]["warnings"]
    text = cli("tune", "--config", box, "--evaluations", 700)
    assert "warning: k1 = 1200 is the upper bound and J still falls beyond it" in text.stdout


@pytest.mark.system
def test_over_the_shipped_scenarios_the_optimum_is_inside_and_nothing_is_said():
    """The robust objective (CVaR 0.2 over config/scenarios.yaml: drifting
    plants with valve lag and sensor noise; 2 s episodes) has its optimum inside the
    box (k ~ 370 each): no gain ends on a bound, no probe is spent, no warning."""
    cfg = with_horizon(Config(), 2.0)
    t = Tuning().replace(evaluations=500, scenarios=load_scenarios(CONFIG_DIR / "scenarios.yaml", cfg),
                         aggregate=parse_aggregate("cvar:0.2"))
    res = tune(cfg, t)
    assert res.bounds is not None and res.bounds.checks == () and res.bounds.warnings == []
    assert res.bounds.evaluations == 0
    assert np.all(np.array(res.gains) > 250.0) and np.all(np.array(res.gains) < 500.0)


def test_diagnose_probes_outward_once_per_gain_on_a_bound():
    calls = []

    def bowl(k, centre=np.array([1300.0, 400.0, 140.0])):          # minimum outside: k1 high, k3 low
        calls.append(np.array(k))
        return np.sum(((np.asarray(k) - centre) / 100.0) ** 2, axis=1)
    lo, hi = np.array(BOX[0]), np.array(BOX[1])
    x = np.array([1200.0, 400.0, 150.0])
    d = diagnose(bowl, x, float(bowl(x[None])[0]), lo, hi)
    assert [(c.gain, c.side) for c in d.checks] == [("k1", "upper"), ("k3", "lower")]
    assert d.evaluations == 2 and len(calls) == 2 and len(calls[1]) == 2         # one batch of two probes
    assert all(c.falls and c.slope < 0 for c in d.checks)
    assert d.checks[0].step == pytest.approx(10.5) and d.checks[1].step == pytest.approx(6.5)
    assert d.warnings[1].startswith("k3 = 150 is the lower bound and J still falls below it")


def test_diagnose_is_quiet_inside_and_where_J_rises_outward():
    def bowl(k, centre=np.array([1000.0, 400.0, 400.0])):
        return np.sum(((np.asarray(k) - centre) / 100.0) ** 2, axis=1)
    lo, hi = np.array(BOX[0]), np.array(BOX[1])
    inside = diagnose(bowl, [1000.0, 400.0, 400.0], 0.0, lo, hi)
    assert inside.checks == () and inside.evaluations == 0 and inside.warnings == []
    near = np.array([1000.0, 400.0, 150.5])                   # within 0.1 % of the range: on the bound
    d = diagnose(bowl, near, float(bowl(near[None])[0]), lo, hi)
    (c,) = d.checks
    assert c.gain == "k3" and c.side == "lower" and d.evaluations == 2     # on the bound, and beyond
    assert not c.falls and c.slope > 0 and d.warnings == []


@pytest.mark.ros
def test_the_tuner_node_runs_cma_restarts_as_the_library_does_and_warns(domain_id, tmp_path):
    from has_control.nodes.stack import run_tuning_stack
    from has_control.tuning.tuner import load_tuning
    box = tmp_path / "box.yaml"
    box.write_text("/**:\n  ros__parameters:\n    swarm:\n      lower: [800.0, 150.0, 150.0]\n"
                   "      upper: [1200.0, 400.0, 400.0]\n")
    cfg = Config()
    out = run_tuning_stack(cfg, {"evaluations": 700}, config_files=[box], validate_best=False, domain_id=domain_id)
    ref = tune(cfg, load_tuning([box]).replace(evaluations=700))
    assert out["variant"] == ref.variant == "cma-restarts"
    assert out["gains"] == list(ref.gains) and out["J"] == ref.result.fun
    assert out["history"] == [h.best_cost for h in ref.result.history]
    assert out["bounds"] == ref.as_json()["bounds"]
    assert any(w.startswith("k1 = 1200 is the upper bound") for w in out["bounds"]["warnings"])
