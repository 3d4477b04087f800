"""Tuning the ABC gains: settings files, determinism, quality against a grid search."""
import itertools
import json
import subprocess
import sys

import numpy as np
import pytest

from has_control.episode import evaluate
from has_control.errors import ConfigError
from has_control.params import Config
from has_control.tuning import Tuning, load_tuning, tune


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
    res = tune(cfg, Tuning().replace(particles=16, iterations=8, seed=2))
    best = res.result.best_costs()
    assert np.all(np.diff(best) <= 0)
    assert res.result.fun < evaluate([[150.0, 158.0, 162.0]], cfg)[0]
    assert res.result.nfev == 16 * 8


def test_tune_cli_json_is_reproducible_and_has_the_documented_keys():
    args = [sys.executable, "-m", "has_control.cli", "tune", "--variant", "pso-cp-tvac",
            "--seed", "1", "--particles", "8", "--iterations", "4", "--json"]
    outs = [json.loads(subprocess.run(args, capture_output=True, text=True, check=True).stdout)
            for _ in range(2)]
    assert set(outs[0]) == {"variant", "seed", "gains", "J", "iterations", "evaluations",
                            "seconds", "history"}
    for o in outs:
        o.pop("seconds")                     # wall time: the one key that may differ
    assert outs[0] == outs[1]
    assert outs[0]["evaluations"] == 32 and len(outs[0]["history"]) == 4


def test_tune_cli_rejects_bad_numbers_in_one_line():
    r = subprocess.run([sys.executable, "-m", "has_control.cli", "tune", "--particles", "0"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "--particles" in r.stderr
