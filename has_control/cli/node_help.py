"""``has-control plant|controller|tuner --help``: the node's usage and every
parameter with its default and description, without starting the node.

The node is built in a context that discovers nothing (no participant is
found, nothing is published or spun), with ``autostart: false``, so it is
never configured; its declared parameters and their descriptors are read
back and printed.
"""
from __future__ import annotations

import os
import sys
from importlib import import_module

#: Node subcommands: the node's module under has_control.nodes and its class.
NODES = {"plant": ("plant_node", "PlantNode"), "controller": ("controller_node", "ControllerNode"),
         "tuner": ("tuner_node", "TunerNode")}

USAGE = """usage: has-control {name} [--ros-args -p NAME:=VALUE ... -r __ns:=/NS ...]
       ros2 run has_control {name} [--ros-args ...]

Runs the {name} node{managed}. Everything after the node's name goes to ROS.

parameters (name = default: description):
"""


def wants_help(ros_args: list[str]) -> bool:
    """``-h`` or ``--help`` before any ``--ros-args``."""
    head = ros_args[:ros_args.index("--ros-args")] if "--ros-args" in ros_args else ros_args
    return "-h" in head or "--help" in head


def node_help(name: str) -> str:
    """The usage of node ``name`` and its parameters."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"      # this process only: the node meets nobody
    # lazy: rclpy takes ~1 s to load and only node commands need it
    import rclpy
    from rclpy.parameter import Parameter
    from has_control.nodes.managed import AUTOSTART      # lazy: imports rclpy
    module, cls = NODES[name]
    node_class = getattr(import_module(f"has_control.nodes.{module}"), cls)
    context = rclpy.Context()
    rclpy.init(args=[], context=context)
    try:
        overrides = [Parameter(AUTOSTART.name, value=False)] if name != "tuner" else []
        node = node_class(context=context, parameter_overrides=overrides, start_parameter_services=False,
                          enable_rosout=False)
        try:
            names = sorted(node._parameters)
            descriptors = node.describe_parameters(names)
            lines = []
            for key, desc in zip(names, descriptors):
                # the node was made with autostart false (so it stays unconfigured): print the true default
                value = AUTOSTART.default if key == AUTOSTART.name else node.get_parameter(key).value
                value = list(value) if hasattr(value, "tolist") or isinstance(value, (list, tuple)) else value
                # the descriptor derives from the component's table (has_control.config.table)
                extra = [desc.additional_constraints] if desc.additional_constraints else []
                if desc.read_only:
                    extra.append("read at start-up")
                text = desc.description + (f" ({'; '.join(extra)})" if extra else "")
                lines.append(f"  {key} = {value!r}: {text}")
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    managed = (" as a managed (lifecycle) node: autostart (default true) configures and activates it"
               if name != "tuner" else "; its settings are checked when set and read at each ~/start")
    return USAGE.format(name=name, managed=managed) + "\n".join(lines)


def print_help(name: str) -> int:
    print(node_help(name), file=sys.stdout)
    return 0
