"""The lint gate a ROS 2 package template ships (ament_flake8's role), with the project's setup.cfg."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_flake8_passes():
    r = subprocess.run([sys.executable, "-m", "flake8", "has_control", "test", "scripts", "launch", "setup.py"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
