"""The tuner node and tuning sessions: graph = batch, lanes, divergence, a resume without a session."""
import os
import subprocess
import sys

import pytest
from conftest import cli, run_main

from has_control.bag import read_bag, score_bag
from has_control.config import with_horizon
from has_control.nodes.stack import run_tuning_stack
from has_control.core.params import Config
from has_control.tuning.session import ITERATION, SESSION
from has_control.tuning.tuner import load_tuning, tune


@pytest.mark.ros
def test_stack_tune_sets_the_best_gains_through_parameters(domain_id):
    r = cli("stack", "--tune", "--variant", "pso-cp-tvac", "--iterations", 3, "--particles", 4, "--duration", 1.5,
            domain=domain_id)
    assert r.returncode == 0, r.stderr
    best = load_tuning().replace(variant="pso-cp-tvac", iterations=3, particles=4)
    ref = tune(with_horizon(Config(), 1.5), best)
    k = ", ".join(f"{g:.2f}" for g in ref.gains)
    assert f"best k = ({k}), J = {ref.result.fun:.6e}" in r.stdout
    assert f"controller gains now ({k})" in r.stdout
    assert f"validated through the graph: J = {ref.result.fun:.6e}" in r.stdout


@pytest.mark.ros
def test_graph_evaluation_over_two_lanes_equals_the_batch_evaluator(domain_id, tmp_path):
    cfg = with_horizon(Config(), 1.5)
    out = run_tuning_stack(cfg, {"variant": "pso-cp-tvac", "iterations": 2, "particles": 3}, evaluator="graph",
                           namespaces=["/sim0", "/sim1"], record=str(tmp_path / "rec"), domain_id=domain_id,
                           keep_episodes=True)
    ref = tune(cfg, load_tuning().replace(variant="pso-cp-tvac", iterations=2, particles=3))
    assert out["gains"] == list(ref.gains) and out["J"] == ref.result.fun
    assert out["history"] == [h.best_cost for h in ref.result.history]
    assert out["controller_gains"] == list(ref.gains)
    assert out["validation"]["J"] == ref.result.fun and out["lanes"] == ["/sim0", "/sim1"]
    episodes = sorted((tmp_path / "rec" / "episodes").iterdir())
    assert len(episodes) == 6                                   # every candidate, recorded
    assert score_bag(episodes[0])[0].J == ref.result.history[0].costs[0]
    session = read_bag(tmp_path / "rec" / SESSION)
    assert session.count(ITERATION) == 2 and session.count("/validation/sim0/state") == 5000


@pytest.mark.ros
def test_diverging_candidates_score_inf_and_the_tuner_carries_on(domain_id, tmp_path):
    cfg = with_horizon(Config(), 1.5)
    bounds = tmp_path / "wild.yaml"
    bounds.write_text("/**:\n  ros__parameters:\n    swarm:\n      lower: [9000.0, 9000.0, 9000.0]\n"
                      "      upper: [10000.0, 10000.0, 10000.0]\n")
    out = run_tuning_stack(cfg, {"variant": "pso-cp-tvac", "iterations": 2, "particles": 2}, config_files=[bounds],
                           evaluator="graph", validate_best=False, domain_id=domain_id)
    assert out["J"] == "inf" and out["evaluations"] == 4 and out["iterations"] == 2


def test_resume_without_a_session_is_one_line(tmp_path, capsys):
    r = run_main(capsys, "tune", "--resume", tmp_path)
    assert r.returncode == 2 and "no session bag to resume" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.ros
def test_bad_tuner_parameter_is_rejected_with_one_line(domain_id):
    r = subprocess.run([sys.executable, "-m", "has_control.cli", "tuner", "--ros-args", "-p", "evaluator:=fast"],
                       capture_output=True, text=True, timeout=120,
                       env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)})
    assert r.returncode == 2 and "evaluator = 'fast'" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.ros
def test_graph_lanes_in_separate_processes_equal_the_batch_evaluator(domain_id, tmp_path):
    """Two plant and two controller processes in /sim0 and /sim1 (as ros2 run starts
    them), the tuner a process of its own: the session gives the batch result."""
    import json
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    cli_ = [sys.executable, "-m", "has_control.cli"]
    procs = []
    try:
        for ns in ("/sim0", "/sim1"):
            procs.append(subprocess.Popen(cli_ + ["plant", "--ros-args", "-r", f"__ns:={ns}", "-p", "autostart:=false",
                                                  "-p", "keep_alive:=true"], env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            procs.append(subprocess.Popen(cli_ + ["controller", "--ros-args", "-r", f"__ns:={ns}"], env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        rec = tmp_path / "rec"
        r = subprocess.run(cli_ + ["tuner", "--ros-args", "-p", "evaluator:=graph", "-p", "lanes:=['/sim0','/sim1']",
                                   "-p", "swarm.variant:=pso-cp-tvac",
                                   "-p", "swarm.iterations:=2", "-p", "swarm.particles:=3",
                                   "-p", "simulation.horizon:=1.5", "-p", f"record:={rec}",
                                   "-p", "keep_episodes:=true"],
                           env=env, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(timeout=30)
    out = json.loads((rec / "tune.json").read_text())
    ref = tune(with_horizon(Config(), 1.5), load_tuning().replace(variant="pso-cp-tvac", iterations=2, particles=3))
    assert out["gains"] == list(ref.gains) and out["J"] == ref.result.fun
    assert out["history"] == [h.best_cost for h in ref.result.history]
    assert len(list((rec / "episodes").iterdir())) == 6                 # every candidate ran through a lane


@pytest.mark.ros
def test_the_tuner_node_tunes_on_scenarios_as_the_library_does(domain_id, tmp_path):
    from has_control.config import CONFIG_DIR
    from has_control.core.scenarios import parse_aggregate
    from has_control.config import load_scenarios
    cfg = with_horizon(Config(), 1.5)
    path = CONFIG_DIR / "scenarios.yaml"
    out = run_tuning_stack(cfg, {"variant": "pso-cp-tvac", "iterations": 2, "particles": 8}, validate_best=False,
                           domain_id=domain_id, scenarios=str(path), aggregate="cvar:0.2")
    ref = tune(cfg, load_tuning().replace(variant="pso-cp-tvac", iterations=2, particles=8,
                                          scenarios=load_scenarios(path, cfg), aggregate=parse_aggregate("cvar:0.2")))
    assert out["gains"] == list(ref.gains) and out["J"] == ref.result.fun and out["scenarios"] == 20


@pytest.mark.parametrize("params,culprit", [
    (["-p", "scenarios:=/nonexistent.yaml"], "/nonexistent.yaml"),
    (["-p", "scenarios:=" + "config/scenarios.yaml", "-p", "aggregate:=cvar:2"], "cvar:2"),
    (["-p", "scenarios:=config/scenarios.yaml", "-p", "evaluator:=graph"], "needs evaluator batch"),
])
@pytest.mark.ros
def test_bad_tuner_scenarios_are_one_line(domain_id, params, culprit):
    r = subprocess.run([sys.executable, "-m", "has_control.cli", "tuner", "--ros-args", *params],
                       capture_output=True, text=True, timeout=120,
                       env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)})
    assert r.returncode == 2 and culprit in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_the_validation_block_agrees_only_within_the_tolerance():
    """The validation block without ROS: graph = library agrees; a 70x gap (a reported 2.03e-3 against
    2.91e-5) disagrees and names the lane parameter that differs; inf against inf agrees."""
    from has_control.tuning.validation import (disagreement_status, lane_differences, validation_block,
                                               validation_line)
    mine = {"actuator.mass": 1500.0, "gains.k1": 150.0, "adaptation.lower": [0.0, 0.0]}
    lanes = [{"lane": "/", "controller": {"actuator.mass": 1700.0, "gains.k1": 900.0,
                                          "adaptation.lower": [0.0, 0.0]}, "plant": {"actuator.mass": 1500.0}}]
    differ = lane_differences(mine, lanes)
    assert differ == ["/ controller: actuator.mass = 1700.0 (the tuner's 1500.0)"]     # gains are the candidate's
    same = validation_block({"J": 2.9e-5}, 2.9e-5, 2.9e-5, [])
    assert same["agrees"] and same["relative_difference"] == 0.0 and "more than" not in validation_line(same, (1, 2, 3))
    gap = validation_block({"J": 2.033186e-03}, 2.033186e-03, 2.905778e-05, differ)
    assert not gap["agrees"] and gap["relative_difference"] > 60 and gap["tolerance"] == 1e-6
    assert "actuator.mass = 1700.0" in validation_line(gap, (1, 2, 3))
    assert disagreement_status((1, 2, 3), 2.9e-5, gap).startswith("disagrees")
    assert not validation_block({"J": 1.0}, 1.0 + 1e-5, 1.0, [])["agrees"]
    assert validation_block({"J": "inf"}, float("inf"), float("inf"), [])["agrees"]
    assert not validation_block({"J": "inf"}, float("inf"), 1e-4, [])["agrees"]


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
