"""Dependencies point inward: the numerical core imports no ROS."""
import subprocess
import sys

CORE = ["params", "config", "actuator", "reference", "abc_controller", "cost", "episode",
        "swarm", "tuning", "baselines", "cli"]


def test_core_modules_import_no_ros():
    code = ("import sys\n"
            + "".join(f"import has_control.{m}\n" for m in CORE)
            + "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
              "('rclpy', 'rosbags', 'mcap', 'sensor_msgs', 'std_msgs', 'rosgraph_msgs'))\n"
            + "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
