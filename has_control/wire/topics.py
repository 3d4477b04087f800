"""The control loop's topics: names, types, joints, columns and wire layouts, in one place.

Names are relative to the run's namespace. State and command are
``sensor_msgs/JointState`` in the bond-graph reading (a hydraulic port's
effort is pressure, its displacement is volume):

=========  ================  =====================  =================
joint      position          velocity               effort
=========  ================  =====================  =================
actuator   y [m]             ẏ [m/s]                F = A1·P1 − A2·P2 [N]
chamber_1  V1 [m³]           V̇1 = A1·ẏ [m³/s]       P1 [Pa]
chamber_2  V2 [m³]           V̇2 = −A2·ẏ [m³/s]      P2 [Pa]
=========  ================  =====================  =================

The command is joint ``valve``, position ``[u]`` (spool displacement [m]),
stamped with the state it answers. The controller's internals are
``std_msgs/Float64MultiArray`` whose columns lead with the sample's time t
(the type has no header); the layout's one dimension is labelled with the
column names. No ROS import: the nodes turn these into
publishers, the bag code into channels.
"""
from __future__ import annotations

from has_control.wire import codec

JOINT_STATE = "sensor_msgs/msg/JointState"
CLOCK = "rosgraph_msgs/msg/Clock"
FLOAT64_ARRAY = "std_msgs/msg/Float64MultiArray"
STRING = "std_msgs/msg/String"

STATE, COMMAND, CLOCK_TOPIC = "state", "command", "clock"
#: The plant's true state, published beside its sensors' readings on ``state``
#: when the plant adds the measurement noise (``noise.added_by: plant``).
TRUE_STATE = "true_state"
REFERENCE, CONTROLLER_STATE, GAINS = "controller/reference", "controller/controller_state", "controller/gains"
#: The samples a plant ran without their command (the last one held, or the valve centred), as the plant
#: reports them to in-process observers (:attr:`~has_control.loop.plant.PlantProcess.on_unanswered`;
#: recorded by ``stack --realtime --record``).
MISSED = "plant/missed"

STATE_NAMES = ["actuator", "chamber_1", "chamber_2"]
COMMAND_NAMES = ["valve"]

#: Columns of the Float64MultiArray topics (units: s, then SI).
CONTROLLER_STATE_COLUMNS = ("t", "e1", "e2", "e3", "a1_hat", "a2_hat", "x1d")
REFERENCE_COLUMNS = ("t", "x1d", "x1d_dot", "x1d_ddot", "x1d_dddot")
GAINS_COLUMNS = ("t", "k1", "k2", "k3")
#: One message per missed sample: its t [s], the command the plant ran with [m]
#: (the last one held, or 0 on the fail-safe), and 1.0 if on the fail-safe, else 0.0.
MISSED_COLUMNS = ("t", "u", "failsafe")

#: What each run topic is offered with: (history depth, transient local). All
#: are reliable. The loop's state and command keep the last one (lock-step
#: must not lose a sample, and a stale one is never worth delivering); the
#: gains in force are kept for late joiners.
QOS = {STATE: (1, False), TRUE_STATE: (1, False), COMMAND: (1, False), CLOCK_TOPIC: (10, False),
       REFERENCE: (10, False), CONTROLLER_STATE: (10, False), GAINS: (1, True)}

#: The history the writers of the per-sample topics keep [messages], so that a
#: reader outside the loop (a recorder in another process) that falls behind by
#: up to this many samples still receives every one (reliable delivery resends
#: from the writer's history). The loop's own readers keep the last one
#: (:data:`QOS`): a stale state is never worth answering.
RECORD_DEPTH = 1000
#: The topics written every sample, offered with :data:`RECORD_DEPTH` (the
#: ros2_control layout's JointState and command topics too).
PER_SAMPLE = (STATE, TRUE_STATE, COMMAND, CLOCK_TOPIC, REFERENCE, CONTROLLER_STATE)
#: **The recording QoS**: what an external recorder subscribes with to receive
#: every sample of a run: reliable, keep-last :data:`RECORD_DEPTH`, volatile
#: (docs/nodes.md, "Recording"). ``ros2 bag record`` takes it through
#: ``--qos-profile-overrides-path`` (its default depth is 10).
RECORDING_QOS = (RECORD_DEPTH, False)


def offered(relative: str) -> tuple[int, bool]:
    """(history depth, transient local) the writers of run topic ``relative`` offer
    (reliable): :data:`QOS`, with :data:`RECORD_DEPTH` for the per-sample topics."""
    depth, latched = QOS[relative]
    return (max(depth, RECORD_DEPTH), latched) if relative in PER_SAMPLE else (depth, latched)


#: Topics of a recorded run and their types.
RUN_TOPICS = {STATE: JOINT_STATE, COMMAND: JOINT_STATE, CLOCK_TOPIC: CLOCK,
              REFERENCE: FLOAT64_ARRAY, CONTROLLER_STATE: FLOAT64_ARRAY, GAINS: FLOAT64_ARRAY}
#: ... and of a run whose plant publishes measured states (``noise.added_by: plant``).
MEASURED_RUN_TOPICS = {**RUN_TOPICS, TRUE_STATE: JOINT_STATE}

#: Wire layouts of the messages the loop exchanges every sample.
STATE_LAYOUT = codec.joint_state_layout(STATE_NAMES, 3, 3, 3)
COMMAND_LAYOUT = codec.joint_state_layout(COMMAND_NAMES, 1, 0, 0)
CLOCK_LAYOUT = codec.clock_layout()
CONTROLLER_STATE_LAYOUT = codec.float64_array_layout(CONTROLLER_STATE_COLUMNS)
REFERENCE_LAYOUT = codec.float64_array_layout(REFERENCE_COLUMNS)
GAINS_LAYOUT = codec.float64_array_layout(GAINS_COLUMNS)
MISSED_LAYOUT = codec.float64_array_layout(MISSED_COLUMNS)
#: The tuner's ~/progress: iteration, best J, gains [1/s], evaluations, elapsed [s], ETA [s].
PROGRESS_COLUMNS = ("iteration", "best_J", "k1", "k2", "k3", "evaluations", "elapsed_s", "eta_s")
PROGRESS_LAYOUT = codec.float64_array_layout(PROGRESS_COLUMNS)
#: ros2_control: the valve command ``[u]`` [m] a forward_command_controller takes.
FORWARD_COMMAND_LAYOUT = codec.float64_array_layout(tuple(COMMAND_NAMES))

#: The layout of each run topic (by relative name).
LAYOUTS = {STATE: STATE_LAYOUT, TRUE_STATE: STATE_LAYOUT, COMMAND: COMMAND_LAYOUT, CLOCK_TOPIC: CLOCK_LAYOUT,
           CONTROLLER_STATE: CONTROLLER_STATE_LAYOUT, REFERENCE: REFERENCE_LAYOUT, GAINS: GAINS_LAYOUT}
