"""Hostile input on issue #14's surfaces: scenario files, road parameters, robustness labels,
aggregates stored in a session, and the plant options reaching every node."""
from __future__ import annotations

import re

import pytest
from rclpy.parameter import Parameter

from has_control.cli import main
from has_control.config import load_config
from has_control.common.errors import ConfigError
from has_control.core.scenarios import Aggregate, parse_aggregate
from has_control.config import Scenario
from has_control.tuning.tuner import Tuning, tuning_from_json, tuning_json


@pytest.mark.parametrize("road,culprit", [
    ("{kind: road, speed: 1.0e300}", "reference.cutoff = 2.0: no road component"),
    ("{kind: road, cutoff: 1.0e20}", "reference.cutoff = 1e+20: must be below the Nyquist"),
    ("{kind: road, speed: 1.0e308, cutoff: 1.0}", "reference.cutoff = 1.0: no road component"),
])
def test_road_parameters_far_out_of_range_are_one_line(tmp_path, capsys, road, culprit):
    p = tmp_path / "p.yaml"
    p.write_text(f"/**:\n  ros__parameters:\n    reference: {road}\n    simulation: {{horizon: 1000.0}}\n")
    with pytest.raises(ConfigError, match=re.escape(culprit)):
        load_config([p])
    assert main(["simulate", "--config", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and culprit in err, err


@pytest.mark.ros
def test_controller_rejects_a_road_it_cannot_build_and_keeps_the_old_reference(context):
    from has_control.nodes.controller_node import ControllerNode
    node = ControllerNode(context=context)
    try:
        res = node.set_parameters_atomically([Parameter("reference.kind", value="road"),
                                              Parameter("reference.speed", value=1.0e300)])
        assert not res.successful and "reference.cutoff" in res.reason
        assert node.get_parameter("reference.kind").value == "sine" and node._pending is None
    finally:
        node.destroy_node()


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


def test_a_session_with_damaged_scenarios_is_one_line(tmp_path, monkeypatch):
    import has_control.tuning.session as session
    from has_control.bag import BagError
    from has_control.core.params import Config

    def damaged(t):
        return dict(tuning_json(t), scenarios=[{"name": "a", "overrides": [1, 2]}], aggregate="mean")
    monkeypatch.setattr(session, "tuning_json", damaged)
    session.Session(tmp_path / "s", Tuning(), Config()).close()
    with pytest.raises(BagError, match="cannot resume"):
        session.resume(tmp_path / "s")


@pytest.mark.ros
def test_the_tuner_node_takes_the_plant_options_and_the_noise(context):
    from has_control.config import build_config
    from has_control.nodes.stack import _overrides
    from has_control.nodes.tuner_node import TunerNode
    cfg = build_config({"plant.mass": 1700.0, "plant.valve_limit": 4e-3, "plant.valve_time_constant": 1e-3,
                        "noise.position": 1e-6, "noise.seed": 7})
    node = TunerNode(context=context, parameter_overrides=_overrides(cfg))
    try:
        assert node.cfg.noise == cfg.noise
        assert node.cfg.plant.actuator(node.cfg.actuator) == cfg.plant.actuator(cfg.actuator)
        assert (node.cfg.plant.valve_limit, node.cfg.plant.valve_time_constant) == (4e-3, 1e-3)
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_stack_tuning_with_plant_options_scores_what_the_graph_runs(domain_id):
    from has_control.config import build_config
    from has_control.config import with_horizon
    from has_control.nodes.stack import run_tuning_stack
    from has_control.tuning.tuner import load_tuning, tune
    cfg = with_horizon(build_config({"plant.mass": 1700.0, "plant.valve_limit": 4e-3, "noise.position": 1e-6,
                                     "plant.valve_time_constant": 1e-3, "noise.seed": 7}), 1.2)
    out = run_tuning_stack(cfg, {"variant": "pso-cp-tvac", "iterations": 2, "particles": 3}, evaluator="batch",
                           domain_id=domain_id)
    ref = tune(cfg, load_tuning().replace(variant="pso-cp-tvac", iterations=2, particles=3))
    assert out["gains"] == list(ref.gains) and out["J"] == ref.result.fun == out["validation"]["J"]


@pytest.mark.parametrize("command", [["robustness", "--gains", "400", "400", "400"], ["simulate"]])
def test_a_figure_format_matplotlib_cannot_write_is_one_line_before_any_run(tmp_path, capsys, command):
    p = tmp_path / "s.yaml"
    p.write_text("scenarios:\n  nominal: {}\n")
    extra = ["--scenarios", str(p)] if command[0] == "robustness" else []
    with pytest.raises(SystemExit) as status:                   # argparse: before anything runs
        main([*command, *extra, "--duration", "1.2", "--plot", str(tmp_path / "r.txt")])
    assert status.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "r.txt" in err and "png" in err, err
