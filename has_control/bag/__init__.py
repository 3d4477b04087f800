"""rosbag2 bags in MCAP, one module per job: ``write``, ``read`` (and describe), ``recorded``
(a run's states and commands on the sample grid, either layout, as a machine records them), ``score``.

Outer layer: rosbags and the MCAP format, no rclpy. A bag is what
``ros2 bag record -s mcap`` writes: a directory with ``metadata.yaml``
(rosbag2 version 9) and one ``.mcap`` file, profile ``ros2``, schemas
``ros2msg``, messages ``cdr``, zstd-compressed chunks with their CRCs, each
channel with its ``offered_qos_profiles`` and ``topic_type_hash``. The MCAP
file is written by :mod:`~has_control.bag.mcap_writer` (batches of messages as
NumPy arrays); rosbags supplies the message definitions, their type hashes
and the QoS profiles' form. Log time is simulation time. The run's parameters
travel in the bag's ``custom_data`` (key ``has_control/parameters``, JSON),
so a bag can be scored without knowing how it was made.

Reading is our own sequential MCAP scan, so that a bag whose recorder was
killed mid-write still yields every complete chunk (with a warning saying how
much was lost), and a bare ``.mcap`` file is accepted as rosbag2 accepts it.
"""
from __future__ import annotations

from has_control.wire.topics import (  # noqa: F401  (re-exported: the bag code's vocabulary)
    CLOCK, CLOCK_TOPIC, COMMAND, COMMAND_NAMES, CONTROLLER_STATE, FLOAT64_ARRAY, GAINS, JOINT_STATE,
    REFERENCE, RUN_TOPICS, STATE, STATE_NAMES, STRING,
)
from has_control.bag.base import PARAMETERS_KEY, BagError, warn  # noqa: F401
from has_control.bag.mcap_format import MAGIC  # noqa: F401
from has_control.bag.read import Bag, describe, read_bag  # noqa: F401
from has_control.bag.score import RecordedRun, recorded_run, score_bag  # noqa: F401
from has_control.bag.write import (  # noqa: F401
    BagWriter, QosSpec, as_batch, msgdef, parameters_json, typestore, write_trace,
)
