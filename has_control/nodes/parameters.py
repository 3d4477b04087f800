"""Declare a Config as ROS parameters and read it back, validated by the core."""
from __future__ import annotations

import sys
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from has_control.config import build_config, config_parameters, load_config, parameter_comments, parameter_kind
from has_control.core.params import PLANT_OVERRIDES, Config


def declare_config(node: Node, prefixes: tuple[str, ...], cfg: Config | None = None,
                   read_only: tuple[str, ...] = ()) -> None:
    """Declare every parameter of ``cfg`` under ``prefixes`` (e.g. 'actuator.', 'gains.').

    Defaults come from the shipped config/*.yaml; a ``--params-file`` overrides
    them. Each descriptor carries the meaning and unit (the YAML's comment),
    the range the core enforces (> 0 excludes 0), the allowed strings of an
    enumeration, and ``read_only`` for keys under ``read_only`` (read at start-up).
    """
    cfg = cfg or load_config()
    comments = parameter_comments()
    for key, value in config_parameters(cfg).items():
        if key.startswith(prefixes):
            node.declare_parameter(key, value, describe(key, comments.get(key, key), key.startswith(read_only)))


def declare_plant_overrides(node: Node) -> None:
    """Declare ``plant.<name>`` for each actuator parameter a plant may have
    apart from the model (:data:`~has_control.core.params.PLANT_OVERRIDES`),
    read-only, defaulting to the node's ``actuator.<name>``: unset, the plant
    is the model."""
    comments = parameter_comments()
    for name in PLANT_OVERRIDES:
        key = f"plant.{name}"
        model = node.get_parameter(f"actuator.{name}").value
        text = f"the plant's own {comments.get(f'actuator.{name}', name)}; default: actuator.{name}"
        node.declare_parameter(key, model, describe(key, text, read_only=True))


def describe(key: str, text: str, read_only: bool = False) -> ParameterDescriptor:
    """The descriptor of config key ``key`` with description ``text``."""
    kind, bound, upper = parameter_kind(key)
    desc = ParameterDescriptor(description=text, read_only=read_only)
    if isinstance(kind, dict):
        desc.additional_constraints = f"one of: {', '.join(kind)}"
    elif kind == "seed":
        desc.integer_range = [IntegerRange(from_value=0, to_value=upper, step=1)]
    elif bound is not None:
        lower, inclusive = bound
        if kind == "float":
            desc.floating_point_range = [FloatingPointRange(
                from_value=lower if inclusive else sys.float_info.min,
                to_value=sys.float_info.max if upper is None else upper, step=0.0)]
        else:
            desc.additional_constraints = f"each {'>=' if inclusive else '>'} {lower:g}"
    return desc


def config_from_node(node: Node, prefixes: tuple[str, ...],
                     overrides: dict[str, Any] | None = None) -> Config:
    """The node's Config (raises ConfigError naming the parameter if invalid)."""
    flat: dict[str, Any] = {}
    for prefix in prefixes:
        for name, p in node.get_parameters_by_prefix(prefix.rstrip(".")).items():
            flat[f"{prefix}{name}"] = _plain(p.value)
    flat.update({k: _plain(v) for k, v in (overrides or {}).items()})
    return build_config(flat, source=f"parameter of {node.get_fully_qualified_name()}")


def _plain(value: Any) -> Any:
    """ROS double arrays arrive as array.array; the core takes lists."""
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return value.tolist()
    return value
