"""Declare a Config as ROS parameters and read it back, validated by the core."""
from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.node import Node

from ..config import build_config, config_parameters, load_config
from ..params import Config


def declare_config(node: Node, prefixes: tuple[str, ...], cfg: Config | None = None) -> None:
    """Declare every parameter of ``cfg`` under ``prefixes`` (e.g. 'actuator.', 'gains.').

    Defaults come from the shipped config/*.yaml; a ``--params-file`` overrides
    them. Gains carry a range descriptor (> 0 is enforced by the core as well).
    """
    cfg = cfg or load_config()
    for key, value in config_parameters(cfg).items():
        if not key.startswith(prefixes):
            continue
        desc = ParameterDescriptor(description=f"has_control {key} (SI units)")
        if key.startswith("gains."):
            desc.floating_point_range = [FloatingPointRange(from_value=0.0, to_value=1.0e6, step=0.0)]
            desc.description = f"back-stepping gain {key[-2:]} [1/s], > 0"
        node.declare_parameter(key, value, desc)


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
