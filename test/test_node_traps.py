"""What a new user runs into first: node --help, --version, namespaces, a missing rclpy."""
import os
import subprocess
import sys

import pytest

from has_control.config import with_horizon
from has_control.core.params import Config

pytestmark = [pytest.mark.ros]

CLI = [sys.executable, "-m", "has_control.cli"]


@pytest.mark.parametrize("node", ["plant", "controller", "tuner"])
def test_node_help_prints_usage_and_every_parameter_without_starting_a_node(node, domain_id):
    r = subprocess.run(CLI + [node, "--help"], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)})
    assert r.returncode == 0 and r.stderr == "", r.stderr
    assert r.stdout.startswith(f"usage: has-control {node}")
    params = [line for line in r.stdout.splitlines() if line.startswith("  ") and " = " in line]
    assert any(line.startswith("  actuator.mass = 1500.0: ") for line in params)
    undescribed = [p for p in params if p.rstrip().endswith(":") and not p.startswith("  use_sim_time")]
    assert undescribed == []                                  # every parameter says what it is
    assert "ready" not in r.stdout
    if node != "tuner":                                       # the true default, not the help's own override
        assert any(line.startswith("  autostart = True: ") for line in params)
    else:                                                     # real descriptions and the true choices
        variant = next(line for line in params if line.startswith("  swarm.variant = "))
        assert "cma-restarts" in variant and "one of: cma-restarts, pso, pso-cp, pso-cp-tvac" in variant
        assert not any(line.split(" = ")[0].strip() == line.rsplit(": ", 1)[-1].strip() for line in params)
        assert "restarts.evaluations = 4000: cma-restarts: the budget" in r.stdout


def test_version():
    import re
    from pathlib import Path
    import has_control
    r = subprocess.run(CLI + ["--version"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("has-control ")
    setup = (Path(__file__).resolve().parent.parent / "setup.py").read_text()
    assert has_control.__version__ == re.search(r'version="([^"]+)"', setup).group(1)     # one home: setup.py
    assert r.stdout.strip() == f"has-control {has_control.__version__}"


def test_an_unconfigured_controller_says_it_waits_for_configuration(domain_id):
    p = subprocess.Popen(CLI + ["controller", "--ros-args", "-p", "autostart:=false"], stderr=subprocess.PIPE,
                         stdout=subprocess.DEVNULL, text=True, env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)})
    try:
        line = p.stderr.readline()
        while line and "unconfigured" not in line:
            line = p.stderr.readline()
        assert "unconfigured: waiting for lifecycle transitions" in line and "configure" in line
    finally:
        p.terminate()
        p.wait(timeout=30)


def test_a_missing_rclpy_is_one_line_naming_what_to_install(tmp_path):
    (tmp_path / "rclpy.py").write_text("raise ModuleNotFoundError(\"No module named 'rclpy'\", name='rclpy')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    for args in (["stack", "--duration", "0.1"], ["controller"]):
        r = subprocess.run(CLI + args, capture_output=True, text=True, timeout=120, env=env)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert "rclpy not found" in r.stderr and "setup.bash" in r.stderr


def test_a_relative_namespace_records_under_its_absolute_name(context, tmp_path):
    from has_control.bag import read_bag
    from has_control.nodes.stack import run_stack
    run = run_stack(with_horizon(Config(), 1.5), namespace="sim0", record=tmp_path / "run", context=context)
    bag = read_bag(run.bag)
    assert bag.count("/sim0/state") == 5000 and bag.count("/sim0/command") >= 4999


def test_replay_controller_tests_the_running_node_it_names(context, domain_id, tmp_path):
    """--controller NODE feeds the running node (a controller with other gains
    mismatches); --check-code is the in-process regression check."""
    import time
    from has_control.nodes.stack import run_stack
    bag = run_stack(with_horizon(Config(), 1.5), record=tmp_path / "run", context=context).bag
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    for gains, expected in (("300.0", 1), ("150.0", 0)):
        node = subprocess.Popen(CLI + ["controller", "--ros-args", "-r", "__ns:=/live", "-p", f"gains.k1:={gains}",
                                       "-p", "publish_internals:=false"], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(1.0)
            r = subprocess.run(CLI + ["replay", str(bag), "--controller", "/live/controller"], env=env,
                               capture_output=True, text=True, timeout=300)
        finally:
            node.terminate()
            node.wait(timeout=30)
        assert r.returncode == expected, r.stderr
        assert "states to the controller node /live/controller: " in r.stdout
        assert (": 0 mismatches" in r.stdout) == (expected == 0)
    r = subprocess.run(CLI + ["replay", str(bag), "--controller", "/nobody/controller"], env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "/nobody/controller" in r.stderr


@pytest.mark.parametrize("node, args, culprit", [
    ("controller", ["-p", "gains.k1:=-1.0"], "gains.k1"),
    ("plant", ["-p", "samples:=-5"], "samples = -5"),
    ("plant", ["-p", "command_timeout:=-1.0"], "command_timeout = -1.0"),
    ("plant", ["-p", "mode:=fast"], "mode = 'fast'"),
])
def test_bad_start_up_parameters_end_in_one_line(node, args, culprit, domain_id):
    import os
    r = subprocess.run([sys.executable, "-m", "has_control.cli", node, "--ros-args", *args],
                       env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and culprit in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
