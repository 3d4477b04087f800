"""Scenario sets and scenario files, the robust aggregate and robust tuning, robustness labels."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import NOM, one_line

from has_control.cli import main
from has_control.config import CONFIG_DIR, load_config
from has_control.core.episode import evaluate, evaluate_configs
from has_control.config import with_horizon
from has_control.common.errors import ConfigError
from has_control.core.scenarios import Aggregate, evaluate_scenarios, parse_aggregate
from has_control.config import Scenario, load_scenarios
from has_control.tuning.session import run_session
from has_control.tuning.tuner import Tuning, tune, tuning_from_json, tuning_json

SHIPPED = CONFIG_DIR / "scenarios.yaml"
SMALL = """
scenarios:
  nominal: {}
  heavy-laggy: {plant.mass: 1800.0, plant: {valve_time_constant: 1.0e-3}}
  road: {reference: {kind: road, road_class: D, seed: 3}}
random:
  count: 3
  seed: 5
  prefix: d
  ranges: {plant.bulk_modulus: [5.0e8, 9.0e8], noise.seed: [0, 100]}
  set: {noise.position: 1.0e-6}
"""
GAINS = np.array([[656.11, 656.13, 656.14], [150.0, 158.0, 162.0], [400.0, 300.0, 500.0]])


@pytest.fixture
def small(tmp_path):
    p = tmp_path / "small.yaml"
    p.write_text(SMALL)
    return p


def _cfg(horizon=1.5):
    return with_horizon(load_config(), horizon)


def test_named_scenarios_and_seeded_draws(small):
    sc = load_scenarios(small)
    assert [s.name for s in sc] == ["nominal", "heavy-laggy", "road", "d-0", "d-1", "d-2"]
    assert dict(sc[1].overrides) == {"plant.mass": 1800.0, "plant.valve_time_constant": 1.0e-3}
    draws = [dict(s.overrides) for s in sc[3:]]
    assert all(5.0e8 <= d["plant.bulk_modulus"] <= 9.0e8 and isinstance(d["noise.seed"], int) for d in draws)
    assert all(d["noise.position"] == 1.0e-6 for d in draws)
    assert load_scenarios(small) == sc                                       # same seed, same draws
    assert len({d["plant.bulk_modulus"] for d in draws}) == 3


def test_the_shipped_sets_load():
    assert len(load_scenarios(SHIPPED)) == 20
    assert len(load_scenarios(CONFIG_DIR / "scenarios_heldout.yaml")) == 52


@pytest.mark.parametrize("body,culprit", [
    ("scenarios:\n  a: {gains.k1: 500.0}\n", "scenario a: gains.k1: a scenario sets only"),
    ("scenarios:\n  a: {plant.mass: -3.0}\n", "scenario a: plant.mass = -3.0"),
    ("scenarios:\n  a: {plant.mass: 1.0}\nrandom: {count: 1, prefix: a}\nfoo: 1\n", "not foo"),
    ("random: {count: 0}\n", "random.count = 0"),
    ("random: {count: 2, ranges: {plant.mass: [2.0, 1.0]}}\n", "random.ranges.plant.mass"),
    ("random: {count: 2, ranges: {noise.seed: [0.5, 3]}}\n", "random.ranges.noise.seed"),
    ("random: {count: 2, sed: 3}\n", "random.sed: unknown key"),
    ("scenarios:\n  a: {}\n  b: 3\n", "scenario b: expected a mapping"),
    ("scenarios:\n  d-0: {}\nrandom: {count: 1, prefix: d}\n", "scenario d-0: named twice"),
    ("scenarios: {}\n", "no scenarios"),
    ("1: x\nfoo: y\n", "not 1, foo"),                                   # keys of mixed types
    ("random: {count: 2, 1: 2, foo: 3}\n", "random.1: unknown key"),
    ("random: {count: 2, ranges: {plant.mass: [1, " + "9" * 400 + "]}}\n", "random.ranges.plant.mass"),
    ("random: {count: 2, prefix: [a]}\n", "random.prefix = ['a']"),
    ("random: {count: 2, prefix: }\n", "random.prefix = None"),
])
def test_bad_scenario_files_are_one_line_naming_the_culprit(tmp_path, body, culprit):
    p = tmp_path / "s.yaml"
    p.write_text(body)
    with pytest.raises(ConfigError) as err:
        load_scenarios(p)
    assert "\n" not in str(err.value) and str(p) in str(err.value) and culprit in str(err.value), str(err.value)


def test_aggregates_are_their_definitions():
    c = np.array([[1.0, 5.0, 3.0, 2.0, 4.0], [1.0, math.inf, 0.5, 0.5, 0.5]])
    np.testing.assert_array_equal(parse_aggregate("mean")(c), [3.0, math.inf])
    np.testing.assert_array_equal(parse_aggregate("max")(c), [5.0, math.inf])
    np.testing.assert_array_equal(parse_aggregate("cvar:0.4")(c), [4.5, math.inf])       # worst 2 of 5
    np.testing.assert_array_equal(parse_aggregate("cvar:0.2")(c[:1]), [5.0])
    np.testing.assert_array_equal(parse_aggregate("cvar:1")(c), parse_aggregate("mean")(c))
    assert str(parse_aggregate("cvar:0.2")) == "cvar:0.2" and parse_aggregate("max") == Aggregate("max")
    for bad in ("cvar:0", "cvar:1.5", "cvar:x", "median", ""):
        with pytest.raises(ConfigError):
            parse_aggregate(bad)


def test_scenario_evaluation_is_each_scenario_evaluated_alone(small):
    cfg = _cfg()
    sc = load_scenarios(small, cfg)
    res = evaluate(GAINS, cfg, scenarios=sc, aggregate="cvar:0.5")
    assert res.names == tuple(s.name for s in sc) and res.metrics.shape == (3, 6, 4)
    for k, s in enumerate(sc):
        np.testing.assert_array_equal(res.metrics[:, k], evaluate(GAINS, s.config(cfg), metrics=True))
    np.testing.assert_array_equal(res.robust, Aggregate("cvar", 0.5)(res.costs))
    assert np.array_equal(evaluate_configs(GAINS, [cfg])[:, 0], evaluate(GAINS, cfg, metrics=True))


def test_nominal_scenario_is_the_nominal_episode():
    cfg = _cfg()
    res = evaluate_scenarios(GAINS, cfg, [Scenario("nominal")], "max", evaluate_configs)
    np.testing.assert_array_equal(res.robust, evaluate(GAINS, cfg))


def test_robust_tuning_resumes_to_the_same_result(small, tmp_path):
    cfg = _cfg(1.2)
    t = Tuning().replace(variant="pso-cp-tvac", particles=8, iterations=4, scenarios=load_scenarios(small, cfg),
                         aggregate=parse_aggregate("cvar:0.5"))
    whole = tune(cfg, t)
    assert whole.as_json()["scenarios"] == 6 and whole.as_json()["aggregate"] == "cvar:0.5"
    sc = evaluate_scenarios(np.array([whole.gains]), cfg, t.scenarios, t.aggregate, evaluate_configs)
    assert sc.robust[0] == whole.result.fun

    def stop_after_two(swarm):
        if swarm.iteration == 2:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        run_session(cfg, t, tmp_path / "s", on_iteration=stop_after_two)
    resumed = run_session(None, None, resume_dir=tmp_path / "s")
    assert resumed.result.gains == whole.gains and resumed.result.result.fun == whole.result.fun
    assert resumed.out["aggregate"] == "cvar:0.5"


def test_cli_tune_with_scenarios_equals_the_library(small, capsys):
    args = ["tune", "--variant", "pso-cp-tvac", "--particles", "8", "--iterations", "3", "--duration", "1.2",
            "--scenarios", str(small),
            "--aggregate", "max", "--json"]
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    cfg = _cfg(1.2)
    lib = tune(cfg, Tuning().replace(variant="pso-cp-tvac", particles=8, iterations=3,
                                     scenarios=load_scenarios(small, cfg), aggregate=Aggregate("max")))
    assert out["gains"] == list(lib.gains) and out["J"] == lib.result.fun and out["scenarios"] == 6


def test_cli_robustness_prints_writes_and_plots(small, tmp_path, capsys):
    args = ["robustness", "--gains", "656.11", "656.13", "656.14", "--gains", "150", "158", "162",
            "--label", "paper", "--scenarios", str(small), "--duration", "1.5"]
    assert main(args + ["--json", "--plot", str(tmp_path / "r.png"), "--markdown", str(tmp_path / "r.md")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["labels"] == ["paper", "k = (150, 158, 162)"] and len(doc["J"][0]) == 6
    res = evaluate_scenarios(GAINS[:2], _cfg(), load_scenarios(small), "cvar:0.2", evaluate_configs)
    assert doc["J"][1] == [float(v) for v in res.costs[1]]
    assert doc["summary"]["paper"]["cvar:0.2"] == res.robust[0]
    assert (tmp_path / "r.png").stat().st_size > 1000 and "| heavy-laggy |" in (tmp_path / "r.md").read_text()
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "heavy-laggy" in text and "cvar:0.2 J" in text


@pytest.mark.parametrize("extra,culprit", [
    (["--aggregate", "max"], "--aggregate max: needs --scenarios"),
    (["--scenarios", "nope.yaml"], "nope.yaml"),
])
def test_cli_tune_scenario_errors_are_one_line(capsys, extra, culprit):
    assert main(["tune", "--variant", "pso-cp-tvac", "--particles", "2", "--iterations", "1", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and culprit in err, err


@pytest.mark.parametrize("text, culprit", [
    ("random: {count: 3, ranges: {plant.mass: [-1.0e308, 1.0e308]}}\n", "random.ranges.plant.mass"),
    ("scenarios:\n  a: {plant.mass: 1500.0, plant: {mass: 1600.0}}\n", "scenario a: plant.mass: given twice"),
    ("random: {count: 2, ranges: {plant.mass: [1.0, 2.0], plant: {mass: [3.0, 4.0]}}}\n", "plant.mass: given twice"),
])
def test_scenario_files_that_overflow_or_say_a_key_twice_are_one_line(tmp_path, capsys, text, culprit):
    p = tmp_path / "s.yaml"
    p.write_text(text)
    one_line(capsys, ["robustness", "--gains", 400, 400, 400, "--duration", 1.2, "--scenarios", p], p, culprit)
    one_line(capsys, ["tune", "--duration", 1.2, "--scenarios", p], p, culprit)


@pytest.mark.ros
def test_every_front_end_checks_scenarios_and_aggregate_alike(tmp_path, capsys, context):
    from rclpy.parameter import Parameter

    from has_control.nodes.tuner_node import TunerNode
    p = tmp_path / "s.yaml"
    p.write_text(NOM)
    one_line(capsys, ["tune", "--scenarios", p, "--aggregate", ""], "--aggregate", "expected mean, max or cvar")
    one_line(capsys, ["robustness", "--gains", 400, 400, 400, "--scenarios", p, "--aggregate", ""], "aggregate ''")
    one_line(capsys, ["tune", "--aggregate", "max"], "--aggregate max: needs --scenarios")
    for params, why in (([Parameter("aggregate", value="garbage")], "parameter aggregate"),
                        ([Parameter("aggregate", value="max")], "needs parameter scenarios"),
                        ([Parameter("scenarios", value=str(p)), Parameter("aggregate", value="")],
                         "parameter aggregate")):
        with pytest.raises(ConfigError, match=why):
            TunerNode(context=context, parameter_overrides=params)


def test_robustness_refuses_one_label_for_two_gain_sets(tmp_path, capsys):
    p = tmp_path / "s.yaml"
    p.write_text("scenarios:\n  nominal: {}\n")
    args = ["robustness", "--scenarios", str(p), "--duration", "1.2", "--gains", "400", "400", "400",
            "--label", "a", "--gains", "150", "158", "162", "--label", "a"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'a'" in err, err


def test_a_stored_aggregate_is_the_aggregate_bit_for_bit():
    for agg in (Aggregate("cvar", 0.2000001), Aggregate("cvar", 0.1 + 0.2), Aggregate("cvar", 1 / 3)):
        assert parse_aggregate(str(agg)) == agg
        t = Tuning().replace(scenarios=(Scenario("a"),), aggregate=agg)
        assert tuning_from_json(tuning_json(t)).aggregate == agg
    assert str(Aggregate("cvar", 0.2)) == "cvar:0.2" and str(Aggregate("cvar", 1.0)) == "cvar:1"
