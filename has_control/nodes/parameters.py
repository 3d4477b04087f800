"""Declare a component's parameter table (:class:`~has_control.config.table.Param`)
as ROS parameters, check changes against it, and read a Config back, validated by the core.

Every descriptor derives from the table: the meaning and unit, the range
in ``additional_constraints`` and, where its bounds are closed, as a
``FloatingPointRange``/``IntegerRange`` (rclpy then refuses a value outside
with "out of range Min: …, Max: …"; an open bound such as ``> 0`` has no
such range, which could only say it with a subnormal bound: the node's
set-time check refuses it with the range in words), the choices, and
``read_only``. A whole number given for a double parameter
(``gains.k1:=300``, at start-up or at set time) is taken as that double.
"""
from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

from has_control.common.errors import ConfigError
from has_control.config import CONFIG_TABLE, Param, build_config, config_parameters, load_config, refusal
from has_control.core.params import PLANT_OVERRIDES, Config
from has_control.wire.joint_mapping import DEFAULT_COMMAND_TOPIC, DEFAULT_JOINT_STATES_TOPIC, INTERFACES

_INT64_MAX = 2 ** 63 - 1


def interface_parameters(side: str) -> tuple[Param, ...]:
    """The ``interface``, ``joint_states_topic`` and ``command_topic`` rows of
    the node on ``side`` of a ros2_control loop: the ``controller`` reads the
    JointState and writes the command, the ``plant`` (a hardware driver's
    place) writes the JointState and reads the command."""
    reads = side == "controller"
    layouts = ("has_control (the plant's state/command JointStates) | ros2_control (JointState from "
               "joint_states_topic, Float64MultiArray [u] on command_topic)" if reads else
               "has_control (state/command JointStates) | ros2_control (JointState on joint_states_topic, "
               "Float64MultiArray [u] from command_topic, as a hardware driver)")
    return (
        Param("interface", "str", "has_control", text=layouts, choices=INTERFACES, read_only=True),
        Param("joint_states_topic", "str", DEFAULT_JOINT_STATES_TOPIC, read_only=True,
              text=f"ros2_control: the sensor_msgs/JointState topic {'read' if reads else 'written'}"),
        Param("command_topic", "str", DEFAULT_COMMAND_TOPIC, read_only=True,
              text="ros2_control: the std_msgs/Float64MultiArray topic the valve command u [m] is written to"
              if reads else "ros2_control: the std_msgs/Float64MultiArray [u] topic read"),
    )


def descriptor(p: Param, read_only: bool | None = None) -> ParameterDescriptor:
    """The ROS descriptor of ``p`` (``read_only`` overrides the table's)."""
    desc = ParameterDescriptor(description=p.comment(), read_only=p.read_only if read_only is None else read_only)
    desc.additional_constraints = p.constraint()
    closed = not (p.lower_open or p.upper_open)
    if p.type in ("double", "double[]") and closed and (p.lower is not None or p.upper is not None):
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(p.lower) if p.lower is not None else -math.inf,
            to_value=float(p.upper) if p.upper is not None else math.inf, step=0.0)]
    elif p.type == "int" and (p.lower is not None or p.upper is not None):
        desc.integer_range = [IntegerRange(from_value=int(p.lower) if p.lower is not None else -_INT64_MAX - 1,
                                           to_value=int(p.upper) if p.upper is not None else _INT64_MAX, step=1)]
    return desc


def declare_table(node: Node, params: Iterable[Param], values: Mapping[str, Any] | None = None,
                  read_only: bool | None = None) -> None:
    """Declare each of ``params`` on ``node`` with its default (or ``values[name]``)
    and its descriptor; a start-up override of a whole number for a double is taken as the double.
    Install :func:`accept_whole_numbers` once, so set time does the same."""
    params = list(params)
    coerce_overrides(node, params)
    for p in params:
        value = (values or {}).get(p.name, p.default)
        node.declare_parameter(p.name, p.coerce(value), descriptor(p, read_only))
    accept_whole_numbers(node)


def coerce_overrides(node: Node, params: Iterable[Param]) -> None:
    """The node's start-up overrides (``-p k:=v``, a params file) before they are
    declared: one outside a range the descriptor carries (which rclpy would refuse
    with its own exception) is one ConfigError line naming the parameter (others are
    checked at configure, where a managed node stays unconfigured); a whole number
    for a double parameter is made that double."""
    overrides = node._parameter_overrides          # rclpy keeps them here until declared
    for p in params:
        given = overrides.get(p.name)
        ranged = descriptor(p).floating_point_range or descriptor(p).integer_range
        reason = refusal({p.name: p}, p.name, given.value) if given is not None and ranged else None
        if reason is not None:
            raise ConfigError(f"parameter of {node.get_fully_qualified_name()}: {reason}")
        if given is not None and p.type in ("double", "double[]"):
            value = p.coerce(given.value)
            if value != given.value or type(value) is not type(given.value):
                overrides[p.name] = Parameter(p.name, value=value)


def accept_whole_numbers(node: Node) -> None:
    """A pre-set callback (once per node): a whole number set on a double
    parameter (``ros2 param set /controller gains.k1 300``) is set as that double."""
    if getattr(node, "_whole_numbers_accepted", False):
        return
    node._whole_numbers_accepted = True

    def pre_set(parameters: list[Parameter]) -> list[Parameter]:
        out = []
        for p in parameters:
            kind = node._descriptors.get(p.name)
            want = kind.type if kind is not None else None
            if want == Parameter.Type.DOUBLE.value and p.type_ == Parameter.Type.INTEGER:
                p = Parameter(p.name, value=float(p.value))
            elif want == Parameter.Type.DOUBLE_ARRAY.value and p.type_ == Parameter.Type.INTEGER_ARRAY:
                p = Parameter(p.name, value=[float(v) for v in p.value])
            out.append(p)
        return out
    node.add_pre_set_parameters_callback(pre_set)


def check_changes(params: Mapping[str, Param], changes: Iterable[Parameter]) -> str | None:
    """The first of ``changes`` the table refuses (``name = value: why``), or None."""
    for p in changes:
        reason = refusal(params, p.name, p.value)
        if reason is not None:
            return reason
    return None


def declare_config(node: Node, prefixes: tuple[str, ...], cfg: Config | None = None,
                   read_only: tuple[str, ...] = ()) -> None:
    """Declare every parameter of ``cfg`` under ``prefixes`` (e.g. 'actuator.', 'gains.'),
    described by :data:`~has_control.config.schema.CONFIG_TABLE`.

    Defaults come from the shipped config/*.yaml; a ``--params-file`` overrides
    them. Keys under ``read_only`` are read at start-up only.
    """
    cfg = cfg or load_config()
    values = {k: v for k, v in config_parameters(cfg).items() if k.startswith(prefixes)}
    coerce_overrides(node, (CONFIG_TABLE[k] for k in values))
    for key, value in values.items():
        node.declare_parameter(key, value, descriptor(CONFIG_TABLE[key], key.startswith(read_only)))
    accept_whole_numbers(node)


def declare_plant_overrides(node: Node) -> None:
    """Declare ``plant.<name>`` for each actuator parameter a plant may have
    apart from the model (:data:`~has_control.core.params.PLANT_OVERRIDES`),
    read-only, defaulting to the node's ``actuator.<name>``: unset, the plant
    is the model."""
    params = [CONFIG_TABLE[f"plant.{name}"] for name in PLANT_OVERRIDES]
    coerce_overrides(node, params)
    for p in params:
        model = node.get_parameter(f"actuator.{p.name.split('.', 1)[1]}").value
        node.declare_parameter(p.name, model, descriptor(p, read_only=True))


def config_from_node(node: Node, prefixes: tuple[str, ...],
                     overrides: dict[str, Any] | None = None) -> Config:
    """The node's Config (raises ConfigError naming the parameter if invalid)."""
    flat: dict[str, Any] = {}
    for prefix in prefixes:
        for name, p in node.get_parameters_by_prefix(prefix.rstrip(".")).items():
            flat[f"{prefix}{name}"] = plain(p.value)
    flat.update({k: plain(v) for k, v in (overrides or {}).items()})
    return build_config(flat, source=f"parameter of {node.get_fully_qualified_name()}")


def plain(value: Any) -> Any:
    """ROS arrays arrive as array.array; the core takes lists."""
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return value.tolist()
    return value
