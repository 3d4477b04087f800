"""What a deployment watches on a running machine, per documented layout, and
how it reads each message's bytes (no ROS: the node subscribes raw).

* ``has_control``: the controller's command, ``sensor_msgs/JointState``
  ``valve`` [u] on ``<namespace>/command``, stamped with the sample it answers;
* ``ros2_control``: ``std_msgs/Float64MultiArray`` ``[u]`` on the
  forward_command_controller's topic (``command_topic``; no stamp: paired with
  the controller's internals in the order they arrive).

In both the controller publishes ``<controller>/controller_state`` [t, e1, …]
(its internals: the deployment turns ``publish_internals`` on) and
``<controller>/gains`` [t, k1, k2, k3] when new gains take effect. A message of
another layout reads as None.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

from has_control.wire.joint_mapping import DEFAULT_COMMAND_TOPIC, INTERFACES
from has_control.wire.topics import (COMMAND, COMMAND_LAYOUT, CONTROLLER_STATE_LAYOUT, FLOAT64_ARRAY,
                                     FORWARD_COMMAND_LAYOUT, GAINS_LAYOUT, JOINT_STATE)

#: The layouts a deployment watches (the loop's interfaces).
LAYOUTS = INTERFACES


def _f64(data: bytes, offset) -> float:
    return struct.unpack_from("<d", data, int(offset))[0]


@dataclass(frozen=True)
class Watched:
    """The topics of one running loop: ``layout`` (LAYOUTS), the loop's
    ``namespace``, the controller node's full name, the ros2_control command topic."""

    layout: str = "has_control"
    namespace: str = ""
    controller: str = "/controller"
    command_topic: str = DEFAULT_COMMAND_TOPIC

    def check(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout = {self.layout!r}: expected one of {', '.join(LAYOUTS)}")
        if not self.controller.startswith("/"):
            raise ValueError(f"controller = {self.controller!r}: a node's full name (/namespace/name)")

    @property
    def command(self) -> tuple[str, str]:
        """(topic, type) of the valve command."""
        if self.layout == "ros2_control":
            return self.command_topic, FLOAT64_ARRAY
        return f"{self.namespace.rstrip('/')}/{COMMAND}", JOINT_STATE

    @property
    def internals(self) -> str:
        return f"{self.controller}/controller_state"

    @property
    def gains(self) -> str:
        return f"{self.controller}/gains"

    def command_of(self, data: bytes, step_ns: int) -> tuple[int, float] | None:
        """(sample from the stamp, or −1 unstamped; u [m]) of a command message."""
        if self.layout == "ros2_control":
            if len(data) != FORWARD_COMMAND_LAYOUT.size:
                return None
            return -1, _f64(data, FORWARD_COMMAND_LAYOUT.values[0])
        if len(data) != COMMAND_LAYOUT.size:
            return None
        sec, nsec = struct.unpack_from("<iI", data, 4)
        ns = sec * 1_000_000_000 + nsec
        return (ns + step_ns // 2) // step_ns, _f64(data, COMMAND_LAYOUT.values[0])


def internals_of(data: bytes, step: float) -> tuple[int, float] | None:
    """(sample, e1 [m]) of a ``controller_state`` message (t [s] on the grid of ``step``)."""
    if len(data) != CONTROLLER_STATE_LAYOUT.size:
        return None
    t = _f64(data, CONTROLLER_STATE_LAYOUT.values[0])
    return int(round(t / step)), _f64(data, CONTROLLER_STATE_LAYOUT.values[1])


def gains_of(data: bytes, step: float) -> tuple[int, tuple[float, float, float]] | None:
    """(sample, (k1, k2, k3) [1/s]) of a ``gains`` message."""
    if len(data) != GAINS_LAYOUT.size:
        return None
    v = [_f64(data, off) for off in GAINS_LAYOUT.values]
    return int(round(v[0] / step)), (v[1], v[2], v[3])


class Pairing:
    """Commands and internals paired sample by sample: by the command's stamp
    (has_control), else in arrival order (ros2_control). :meth:`command` and
    :meth:`internals` return the completed (sample, u, e1) triples."""

    def __init__(self, stamped: bool):
        self.stamped = stamped
        self.u: dict[int, float] = {}
        self.e1: dict[int, float] = {}
        self.fifo_u: list[float] = []
        self.fifo_e: list[tuple[int, float]] = []

    def command(self, sample: int, u: float) -> list[tuple[int, float, float]]:
        if self.stamped and sample >= 0:
            if sample in self.e1:
                return [(sample, u, self.e1.pop(sample))]
            self.u[sample] = u
            self._trim(self.u)
            return []
        self.fifo_u.append(u)
        return self._fifo()

    def internals(self, sample: int, e1: float) -> list[tuple[int, float, float]]:
        if self.stamped:
            if sample in self.u:
                return [(sample, self.u.pop(sample), e1)]
            self.e1[sample] = e1
            self._trim(self.e1)
            return []
        self.fifo_e.append((sample, e1))
        return self._fifo()

    def _fifo(self) -> list[tuple[int, float, float]]:
        out = []
        while self.fifo_u and self.fifo_e:
            i, e1 = self.fifo_e.pop(0)
            out.append((i, self.fifo_u.pop(0), e1))
        return out

    @staticmethod
    def _trim(pending: dict) -> None:
        """Forget halves that never found their other half (a lost message)."""
        if len(pending) > 64:
            for k in sorted(pending)[:-32]:
                del pending[k]


__all__ = ["Watched", "Pairing", "internals_of", "gains_of", "LAYOUTS"]
