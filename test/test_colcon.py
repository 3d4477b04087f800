"""colcon builds the ament_python package; its plant and controller run as two processes."""
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.install]

ROOT = Path(__file__).resolve().parent.parent
COLCON = Path(sys.executable).parent / "colcon"


@pytest.fixture(scope="module")
def install(tmp_path_factory):
    if not COLCON.exists():
        pytest.fail(f"colcon is not installed beside {sys.executable} (scripts/test installs it)")
    ws = tmp_path_factory.mktemp("ws")
    src = ws / "src" / "has_control"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "install", "log", "out", "__pycache__", "*.egg-info"))
    r = subprocess.run([str(COLCON), "build", "--base-paths", "src"], cwd=ws,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return ws / "install"


def _env(install: Path, domain: int) -> dict:
    prefix = install / "has_control"
    site = next(prefix.glob("lib/python3*/site-packages"))
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = f"{prefix}{os.pathsep}{env.get('AMENT_PREFIX_PATH', '')}".rstrip(os.pathsep)
    env["PYTHONPATH"] = f"{site}{os.pathsep}{env.get('PYTHONPATH', '')}".rstrip(os.pathsep)
    env["ROS_DOMAIN_ID"] = str(domain)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return env


def test_ros2_run_finds_the_package_and_its_executables(install, domain_id):
    env = _env(install, domain_id)
    code = ("from ament_index_python.packages import get_package_prefix, get_package_share_directory;"
            "print(get_package_prefix('has_control'));"
            "print(get_package_share_directory('has_control'))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out[0] == str(install / "has_control")
    assert (Path(out[1]) / "config" / "actuator.yaml").is_file()
    for exe in ("plant", "controller", "tuner"):
        p = install / "has_control" / "lib" / "has_control" / exe
        assert p.is_file() and os.access(p, os.X_OK)


def test_plant_and_controller_as_two_processes_track_for_one_second(install, domain_id):
    env = _env(install, domain_id)
    lib = install / "has_control" / "lib" / "has_control"
    controller = subprocess.Popen([str(lib / "controller")], env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        plant = subprocess.run(
            [str(lib / "plant"), "--ros-args", "-p", "samples:=3334", "-p", "command_timeout:=5.0"],
            env=env, capture_output=True, text=True, timeout=300)
    finally:
        controller.terminate()
        controller.wait(timeout=30)
    log = plant.stdout + plant.stderr
    assert plant.returncode == 0, log
    m = re.search(r"finished (\d+) samples at t = ([\d.]+) s: y = (\S+) m, fail-safe events = (\d+)", log)
    assert m, log
    samples, t, y, events = int(m.group(1)), float(m.group(2)), float(m.group(3)), int(m.group(4))
    assert samples == 3334 and events == 0
    assert abs(y - 0.11 * math.sin(2 * t)) < 1e-4        # tracking the sine to 0.1 mm


def test_colcon_installs_the_launch_file(install):
    """``ros2 launch has_control stack.launch.py`` finds it in share/; it names
    executables that the install has (launch itself need not be installed here)."""
    import ast
    launch = install / "has_control" / "share" / "has_control" / "launch" / "stack.launch.py"
    assert launch.is_file()
    tree = ast.parse(launch.read_text())
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description" for n in tree.body)
    named = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value in ("plant", "controller")}
    assert named == {"plant", "controller"}
    for exe in named:
        assert (install / "has_control" / "lib" / "has_control" / exe).is_file()
