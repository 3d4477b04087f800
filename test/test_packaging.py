"""``pip install .`` into a clean venv gives a package that can record a bag (its install_requires suffice)."""
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.install]

ROOT = Path(__file__).resolve().parent.parent

RECORD = """
import pathlib, sys
from has_control.bag import PARAMETERS_KEY, BagWriter, parameters_json, score_bag, write_trace
from has_control.core.episode import simulate
from has_control.config import with_horizon
from has_control.core.params import Config
cfg = with_horizon(Config(), 1.5)
bag = pathlib.Path(sys.argv[1]) / "run"
with BagWriter(bag, {PARAMETERS_KEY: parameters_json(cfg)}) as w:
    write_trace(w, simulate(cfg), cfg)
print(score_bag(bag)[0] == simulate(cfg).score)
"""


def test_pip_install_into_a_clean_venv_can_record_a_bag(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    r = subprocess.run([str(py), "-m", "pip", "install", "--quiet", str(ROOT)], capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    r = subprocess.run([str(py), "-c", RECORD, str(tmp_path)], cwd=tmp_path, capture_output=True, text=True,
                       timeout=600, env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)})
    assert r.returncode == 0 and r.stdout.strip() == "True", r.stdout + r.stderr[-2000:]
