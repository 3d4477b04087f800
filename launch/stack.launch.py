"""Plant and controller as two nodes: ``ros2 launch has_control stack.launch.py``.

Arguments: ``mode`` (lockstep | realtime), ``samples`` (0: until stopped),
``params_file`` (a ros__parameters YAML for both nodes, e.g. the
``gains.yaml`` that ``has-control tune --out DIR`` writes), ``namespace``.
For real time with a controller that cannot answer within one 0.3 ms step
across processes, prefer ``has-control stack --realtime`` (one process).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node


def generate_launch_description():
    mode, samples = LaunchConfiguration("mode"), LaunchConfiguration("samples")
    params_file, namespace = LaunchConfiguration("params_file"), LaunchConfiguration("namespace")
    has_file = PythonExpression(["'", params_file, "' != ''"])

    def node(executable, parameters):
        return [Node(package="has_control", executable=executable, name=executable, namespace=namespace,
                     output="screen", parameters=[params_file, *parameters], condition=IfCondition(has_file)),
                Node(package="has_control", executable=executable, name=executable, namespace=namespace,
                     output="screen", parameters=parameters, condition=UnlessCondition(has_file))]
    return LaunchDescription([
        DeclareLaunchArgument("mode", default_value="lockstep", description="lockstep | realtime"),
        DeclareLaunchArgument("samples", default_value="0", description="samples per episode (0: until stopped)"),
        DeclareLaunchArgument("params_file", default_value="", description="ros__parameters YAML for both nodes"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of both nodes"),
        *node("controller", []),
        *node("plant", [{"mode": mode, "samples": samples}]),
    ])
