"""The ros2_control reading of the actuator's state: four ``joint/interface``
entries of a ``sensor_msgs/JointState`` for y [m], ẏ [m/s], P1 [Pa], P2 [Pa].

One definition, shared by the controller node's ``state_interfaces`` parameter
and by every reader of a recording in the ros2_control layout (docs/ros2_control.md).
"""
from __future__ import annotations

#: The interfaces a joint offers in a JointState, in (position, velocity, effort) order.
INTERFACE_KINDS = ("position", "velocity", "effort")
#: The default mapping: what the project's hardware-like node and plant publish.
DEFAULT_STATE_INTERFACES = ("actuator/position", "actuator/velocity", "chamber_1/effort", "chamber_2/effort")
#: The default topics of the ros2_control layout: joint_state_broadcaster's state and
#: a forward_command_controller's ``std_msgs/Float64MultiArray`` commands.
DEFAULT_JOINT_STATES_TOPIC = "/joint_states"
DEFAULT_COMMAND_TOPIC = "/forward_command_controller/commands"
#: The two documented layouts of a loop's topics: the project's stamped state/command
#: JointStates, and the ros2_control one (JointState in, Float64MultiArray [u] out).
INTERFACES = ("has_control", "ros2_control")


def parse_state_interfaces(entries) -> list[tuple[str, int]]:
    """``joint/interface`` × 4 → [(joint, 0 position | 1 velocity | 2 effort)]
    (ValueError naming the parameter if not so)."""
    entries = list(entries)
    if len(entries) != 4:
        raise ValueError(f"parameter state_interfaces = {entries!r}: expected 4 joint/interface entries "
                         "(y, y_dot, P1, P2)")
    out = []
    for e in entries:
        joint, _, kind = str(e).rpartition("/")
        if not joint or kind not in INTERFACE_KINDS:
            raise ValueError(f"parameter state_interfaces: {e!r}: expected JOINT/INTERFACE with INTERFACE one of "
                             f"{', '.join(INTERFACE_KINDS)}")
        out.append((joint, INTERFACE_KINDS.index(kind)))
    return out


def resolve(names, mapping) -> list[tuple[int, int]]:
    """The mapping against a JointState's ``name`` list: [(index in the arrays or
    −1 where the joint is absent, interface)] for y, ẏ, P1, P2."""
    index = {n: k for k, n in enumerate(names)}
    return [(index.get(joint, -1), kind) for joint, kind in mapping]


def read_state(arrays, resolved):
    """(y, ẏ, P1, P2) from a JointState's (position, velocity, effort) by a
    :func:`resolve`\\ d mapping, or None when a joint or interface is missing."""
    out = []
    for j, kind in resolved:
        values = arrays[kind]
        if j < 0 or j >= len(values):
            return None
        out.append(float(values[j]))
    return tuple(out)


__all__ = ["INTERFACE_KINDS", "DEFAULT_STATE_INTERFACES", "DEFAULT_JOINT_STATES_TOPIC", "DEFAULT_COMMAND_TOPIC",
           "parse_state_interfaces", "resolve", "read_state"]
