"""The managed-node (``rclpy.lifecycle``) conventions the plant and controller share.

unconfigured → ``configure`` (validate the parameters, build the tables, create
the topics) → inactive → ``activate`` (start answering / start the loop) →
active; ``deactivate`` centres the valve and stops; ``cleanup`` and
``shutdown`` release the topics and tables. The transitions are the standard
``lifecycle_msgs`` services (``~/change_state``, ``~/get_state``: what
``ros2 lifecycle set`` calls). With the parameter ``autostart`` (default
true) a node configures and activates itself at start-up, today's
one-command behaviour; with ``autostart: false`` it waits, unconfigured, for
an operator, a launch file's lifecycle manager or ``has-control stack``.
"""
from __future__ import annotations

from rclpy.lifecycle import TransitionCallbackReturn

from has_control.config.table import Param

#: A managed node's ``autostart`` (in the plant's and the controller's tables).
AUTOSTART = Param("autostart", "bool", True, text="configure and activate at start-up (false: wait unconfigured "
                  "for lifecycle transitions, e.g. ros2 lifecycle set NODE configure)", read_only=True)


def bring_up(node) -> None:
    """Configure and activate ``node`` in this thread; a configuration it
    refuses raises ValueError with its reason (one line; the node does not log it as well)."""
    node.bringing_up = True
    try:
        configured = node.trigger_configure()
    finally:
        node.bringing_up = False
    if configured != TransitionCallbackReturn.SUCCESS:
        raise ValueError(node.configure_error or f"{node.get_fully_qualified_name()}: configure failed")
    if node.trigger_activate() != TransitionCallbackReturn.SUCCESS:
        raise ValueError(f"{node.get_fully_qualified_name()}: activate failed")


def autostart(node) -> None:
    """``bring_up`` in the node's constructor: a refusal destroys the half-made node
    (its handles must not outlive the error, e.g. into a forked bag writer) and raises."""
    try:
        bring_up(node)
    except ValueError:
        node.destroy_node()
        raise


def refuse(node, exc: Exception) -> TransitionCallbackReturn:
    """``configure`` refused for ``exc``: its first line kept as ``node.configure_error``,
    logged unless :func:`bring_up` raises it anyway."""
    node.configure_error = str(exc).splitlines()[0]
    if not getattr(node, "bringing_up", False):
        node.get_logger().error(f"configure refused: {node.configure_error}")
    return TransitionCallbackReturn.FAILURE


def state_label(node) -> str:
    """The node's lifecycle state: 'unconfigured', 'inactive', 'active', 'finalized'."""
    return node._state_machine.current_state[1]
