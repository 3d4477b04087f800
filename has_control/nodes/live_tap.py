"""A node's own live view: the parameter ``foxglove_port`` and the tap that feeds the viewer."""
from __future__ import annotations

from rcl_interfaces.msg import ParameterDescriptor

from has_control.common.errors import HasControlError
from has_control.nodes.foxglove import PARAMETER, check_port
from has_control.nodes.live_process import LiveViewProcess
from has_control.nodes.runtime import tap_diagnostics, tee


def node_tap(node, tap=None):
    """Declare ``foxglove_port`` (0: off) on ``node``; when set, serve the
    node's published topics there from a viewer process
    (:class:`~has_control.nodes.live_process.LiveViewProcess`: the loop only
    copies; the node's ``/diagnostics`` too). Returns (the node's tap: ``tap`` and the view's sinks together,
    the view or None). The view closes
    when the node's context shuts down."""
    what = f"parameter {PARAMETER} ="
    port = node.declare_parameter(PARAMETER, 0, ParameterDescriptor(
        description="serve the published topics live on ws://127.0.0.1:PORT (Foxglove); 0: off",
        read_only=True)).value
    if port == 0:
        return tap, None
    try:
        check_port(port, what)
    except HasControlError as exc:
        raise ValueError(f"{exc} or 0 (off)") from None
    view = LiveViewProcess(port, name=node.get_fully_qualified_name(), what=what, warn=node.get_logger().warning)
    node.context.on_shutdown(lambda: view.close())     # a bound method would be held weakly
    tap_diagnostics(node, view.sink)                   # /diagnostics served too
    return tee(tap, view.sink), view
