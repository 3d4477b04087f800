"""Dependencies point inward: the numerical core imports no ROS."""
import subprocess
import sys

CORE = ["jit", "params", "config", "actuator", "reference", "abc_controller", "cost", "episode",
        "swarm", "tuning", "baselines", "cdr", "cli", "wire", "topics", "loop", "mcap_writer", "json_numbers"]
BAGS = ["bag", "session"]          # rosbags and MCAP, but no rclpy


def _imported(modules, banned) -> str:
    code = ("import sys\n"
            + "".join(f"import has_control.{m}\n" for m in modules)
            + f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {banned!r})\n"
            + "print(','.join(bad))")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def test_core_modules_import_no_ros():
    assert _imported(CORE, ("rclpy", "rosbags", "mcap", "sensor_msgs", "std_msgs", "rosgraph_msgs")) == ""


def test_bag_modules_import_no_rclpy():
    assert _imported(BAGS, ("rclpy", "sensor_msgs", "std_msgs", "rosgraph_msgs")) == ""


def test_editing_a_callee_module_recompiles_the_kernels(tmp_path):
    """numba alone would keep episode's cached kernel after actuator.py changes."""
    import shutil
    from pathlib import Path

    import has_control
    pkg = tmp_path / "has_control"
    shutil.copytree(Path(has_control.__file__).parent, pkg,
                    ignore=shutil.ignore_patterns("__pycache__"))
    code = ("import has_control.episode as e; e.simulate(e.with_horizon(e.Config(), 1.5));"
            "print(e._episode._cache._cache_path)")
    env = {"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"}

    def cache_path():
        return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                              capture_output=True, text=True, check=True).stdout.strip()
    first = cache_path()
    assert first == cache_path()                       # unchanged sources: the cache is reused
    with open(pkg / "actuator.py", "a") as f:
        f.write("\n# an edit to the physics\n")
    assert cache_path() != first
