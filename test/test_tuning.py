"""Tuning the ABC gains: settings files, determinism, quality against a grid search."""
import itertools
import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import run_main

from has_control.core.episode import evaluate
from has_control.common.errors import ConfigError
from has_control.core.params import Config
from has_control.tuning.tuner import Tuning, load_tuning, tune


def test_shipped_tuner_file_is_the_papers_setting():
    assert load_tuning() == Tuning()


@pytest.mark.parametrize("body, culprit", [
    ("      particles: 0\n", "swarm.particles = 0"),
    ("      particles: 2.5\n", "swarm.particles = 2.5"),
    ("      variant: pso-plus\n", "swarm.variant = 'pso-plus'"),
    ("      lower: [150.0, 150.0]\n", "swarm.lower = [150.0, 150.0]"),
    ("      velocity: 3.0\n", "swarm.velocity = 3.0: unknown parameter"),
])
def test_bad_tuner_files_name_file_key_and_value(tmp_path, body, culprit):
    p = tmp_path / "t.yaml"
    p.write_text("/**:\n  ros__parameters:\n    swarm:\n" + body)
    with pytest.raises(ConfigError) as info:
        load_tuning([p])
    assert str(p) in str(info.value) and culprit in str(info.value)


@pytest.mark.slow
def test_full_tuning_beats_a_6x6x8_grid_search():
    cfg = Config()
    res = tune(cfg, Tuning().replace(variant="pso-cp-tvac", seed=1))
    lo, hi = np.array([150.0, 150.0, 150.0]), np.array([1200.0, 800.0, 800.0])
    axes = [np.linspace(lo[d], hi[d], n) for d, n in enumerate((6, 6, 8))]
    grid = np.array(list(itertools.product(*axes)))
    assert res.result.fun <= evaluate(grid, cfg).min()


def test_short_tuning_improves_on_its_first_iteration_and_beats_manual_gains():
    cfg = Config()
    res = tune(cfg, Tuning().replace(variant="pso-cp-tvac", particles=16, iterations=8, seed=2))
    best = res.result.best_costs()
    assert np.all(np.diff(best) <= 0)
    assert res.result.fun < evaluate([[150.0, 158.0, 162.0]], cfg)[0]
    assert res.result.nfev == 16 * 8


@pytest.mark.system
def test_tune_cli_json_is_reproducible_and_has_the_documented_keys():
    args = [sys.executable, "-m", "has_control.cli", "tune", "--variant", "pso-cp-tvac",
            "--seed", "1", "--particles", "8", "--iterations", "4", "--json"]
    outs = [json.loads(subprocess.run(args, capture_output=True, text=True, check=True).stdout)
            for _ in range(2)]
    assert set(outs[0]) == {"variant", "seed", "gains", "J", "iterations", "evaluations",
                            "seconds", "history", "bounds", "success", "message"}  # success, message: as OptimizeResult
    for o in outs:
        o.pop("seconds")                     # wall time: the one key that may differ
    assert outs[0] == outs[1]
    assert outs[0]["evaluations"] == 32 and len(outs[0]["history"]) == 4


def test_tune_cli_rejects_bad_numbers_in_one_line(capsys):
    r = run_main(capsys, "tune", "--particles", "0")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "--particles" in r.stderr


@pytest.mark.system
def test_reproduce_writes_every_table_and_figure(tmp_path):
    r = subprocess.run([sys.executable, "-m", "has_control.cli", "reproduce", "--seeds", "2",
                        "--particles", "6", "--iterations", "3", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    report = (tmp_path / "report.md").read_text()
    for heading in ("## Table 2", "## Table 3", "## Convergence", "## Figures", "## Where we agree"):
        assert heading in report
    assert "N = 6 particles, up to 3 iterations" in report
    tables = json.loads((tmp_path / "tables.json").read_text())
    assert set(tables["table2"]) == {"pso", "pso-cp", "pso-cp-tvac", "pso-cp, symmetric redraw",
                                     "pso-cp, rho_c = w_min*exp(-w/w_max)"}
    assert len(tables["table2"]["pso"]["J_per_seed"]) == 2
    assert tables["table3"]["manual"]["e_max"] == pytest.approx(7.957231729566194e-05, rel=1e-12)
    for fig in ("fig6_convergence.png", "fig3-5_gains_pso.png", "fig3-5_gains_pso-cp.png",
                "fig3-5_gains_pso-cp-tvac.png", "fig7-8_tracking.png"):
        assert (tmp_path / fig).read_bytes()[:4] == b"\x89PNG"
