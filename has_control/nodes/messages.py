"""Standard messages of the control loop, and the QoS they travel with.

State, ``sensor_msgs/JointState`` in the bond-graph reading (a hydraulic
port's effort is pressure, its displacement is volume):

=========  ================  =====================  =================
name       position          velocity               effort
=========  ================  =====================  =================
actuator   y [m]             ẏ [m/s]                F = A1·P1 − A2·P2 [N]
chamber_1  V1 [m³]           V̇1 = A1·ẏ [m³/s]       P1 [Pa]
chamber_2  V2 [m³]           V̇2 = −A2·ẏ [m³/s]      P2 [Pa]
=========  ================  =====================  =================

Command, ``sensor_msgs/JointState``: name ``[valve]``, position ``[u]``
(spool displacement [m]), stamped with the state it answers.
"""
from __future__ import annotations

from builtin_interfaces.msg import Time
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from ..params import Actuator

from ..bag import COMMAND_NAMES, STATE_NAMES

#: The control loop: reliable (lock-step must not lose a sample), keep last 1
#: (a stale sample is never worth delivering), volatile (no late-joiner replay).
CONTROL_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

#: Slow state that a late joiner needs (the gains in force): the last one kept.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


def stamp(sample: int, step_ns: int) -> Time:
    """Simulation time of sample i: i·Δt, exact in integer nanoseconds."""
    ns = sample * step_ns
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def sample_of(t: Time, step_ns: int) -> int:
    """Sample index of a stamp (inverse of :func:`stamp`)."""
    return round((t.sec * 1_000_000_000 + t.nanosec) / step_ns)


def state_message(sample: int, step_ns: int, x, a: Actuator) -> JointState:
    position, velocity, effort = a.joint_state(*(float(s) for s in x))
    msg = JointState()
    msg.header.stamp = stamp(sample, step_ns)
    msg.name = STATE_NAMES
    msg.position, msg.velocity, msg.effort = list(position), list(velocity), list(effort)
    return msg


def state_of(msg: JointState) -> tuple[float, float, float, float]:
    """(y, ẏ, P1, P2) of a state message."""
    return msg.position[0], msg.velocity[0], msg.effort[1], msg.effort[2]


def command_message(answers: JointState, u: float) -> JointState:
    msg = JointState()
    msg.header.stamp = answers.header.stamp
    msg.name = COMMAND_NAMES
    msg.position = [float(u)]
    return msg


def trigger_service(node, name: str, action, message: str):
    """A std_srvs/Trigger service ``name`` that calls ``action()`` and answers ``message``."""
    from std_srvs.srv import Trigger

    def on_call(request, response):
        action()
        response.success = True
        response.message = message
        return response
    return node.create_service(Trigger, name, on_call)
