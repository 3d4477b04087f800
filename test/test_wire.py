"""The loop's fast path: compiled CDR bytes are the messages rclpy and rosbags know."""
import math

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from has_control.wire import steps
from has_control.wire import topics
from has_control.core.actuator import joint_state
from has_control.bag import typestore
from has_control.core.episode import EpisodeArrays
from has_control.core.params import Config
from has_control.wire.codec import MALFORMED, NOT_FINITE, TRAILING

STEP_NS = 300_000
SAMPLE = 12_345                                       # t = 3.7035 s


def _state_bytes(x, sample=SAMPLE):
    cfg = Config()
    st, ck = topics.STATE_LAYOUT.buffer(), topics.CLOCK_LAYOUT.buffer()
    steps.encode_state(np.asarray(x, dtype=float), cfg.actuator.as_array(), sample, STEP_NS, st, ck, steps.scratch())
    return st.tobytes(), ck.tobytes()


def _controller_answer(state: bytes):
    cfg = Config()
    arr = EpisodeArrays.from_config(cfg)
    mem = np.zeros(steps.CONTROLLER_MEMORY)
    mem[steps.A1_HAT], mem[steps.A2_HAT] = cfg.adaptation.initial
    bufs = [topics.COMMAND_LAYOUT.buffer(), topics.CONTROLLER_STATE_LAYOUT.buffer(), topics.REFERENCE_LAYOUT.buffer()]
    i = steps.controller_sample(state, mem, np.array(cfg.gains.as_tuple()), arr.actuator, arr.adaptation,
                                arr.reference, arr.sensor, arr.seed, cfg.episode.step, STEP_NS, *bufs,
                                np.zeros((0, 12)))
    return i, [b.tobytes() for b in bufs]


def _equal_but_padding(ours: bytes, theirs: bytes, layout) -> None:
    """rclpy leaves CDR alignment bytes uninitialised (and may append up to
    TRAILING of them after the last field); every other byte must match."""
    assert len(ours) <= len(theirs) <= len(ours) + TRAILING
    a, b = np.frombuffer(ours, np.uint8), np.frombuffer(theirs[:len(ours)], np.uint8)
    np.testing.assert_array_equal(a[~layout.padding], b[~layout.padding])
    assert not a[layout.padding].any()                # ours are zero, as rosbags writes them


@pytest.mark.ros
def test_state_bytes_are_what_rclpy_and_rosbags_serialize():
    cfg = Config()
    x = cfg.actuator.initial_state() + np.array([0.0123, -0.045, 1e5, -2e5])
    state, clock = _state_bytes(x)
    v = [float(s) for s in joint_state(*x, cfg.actuator.as_array())]
    msg = JointState(name=topics.STATE_NAMES, position=v[0:3], velocity=v[3:6], effort=v[6:9])
    msg.header.stamp.sec, msg.header.stamp.nanosec = 3, 703_500_000
    _equal_but_padding(state, serialize_message(msg), topics.STATE_LAYOUT)
    ts = typestore()
    assert bytes(ts.serialize_cdr(ts.deserialize_cdr(state, topics.JOINT_STATE), topics.JOINT_STATE)) == state
    assert clock == serialize_message(Clock(clock=msg.header.stamp))
    _, (command, internals, reference) = _controller_answer(state)
    u = deserialize_message(command, JointState).position[0]
    again = JointState(name=topics.COMMAND_NAMES, position=[u])
    again.header.stamp = msg.header.stamp
    _equal_but_padding(command, serialize_message(again), topics.COMMAND_LAYOUT)
    for data, layout, columns in ((internals, topics.CONTROLLER_STATE_LAYOUT, topics.CONTROLLER_STATE_COLUMNS),
                                  (reference, topics.REFERENCE_LAYOUT, topics.REFERENCE_COLUMNS)):
        values = list(deserialize_message(data, Float64MultiArray).data)
        labelled = Float64MultiArray(data=values)
        labelled.layout.dim = [MultiArrayDimension(label=",".join(columns), size=len(columns), stride=len(columns))]
        _equal_but_padding(data, serialize_message(labelled), layout)


@pytest.mark.ros
def test_rclpy_and_rosbags_decode_the_same_messages():
    cfg = Config()
    x = cfg.actuator.initial_state() + np.array([0.0123, -0.045, 1e5, -2e5])
    state, _ = _state_bytes(x)
    i, (command, internals, reference) = _controller_answer(state)
    assert i == SAMPLE
    ts = typestore()
    for data, cls, msgtype in ((state, JointState, topics.JOINT_STATE), (command, JointState, topics.JOINT_STATE),
                               (internals, Float64MultiArray, topics.FLOAT64_ARRAY),
                               (reference, Float64MultiArray, topics.FLOAT64_ARRAY)):
        a, b = deserialize_message(data, cls), ts.deserialize_cdr(data, msgtype)
        if cls is JointState:
            assert list(a.name) == list(b.name)
            assert (a.header.stamp.sec, a.header.stamp.nanosec) == (b.header.stamp.sec, b.header.stamp.nanosec)
            for field in ("position", "velocity", "effort"):
                np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        else:
            np.testing.assert_array_equal(a.data, b.data)
    got = deserialize_message(state, JointState)
    assert got.position[0] == x[0] and got.velocity[0] == x[1] and list(got.effort[1:]) == list(x[2:])
    cmd = deserialize_message(command, JointState)
    assert list(cmd.name) == ["valve"] and (cmd.header.stamp.sec, cmd.header.stamp.nanosec) == (3, 703_500_000)
    t = SAMPLE * cfg.episode.step
    assert deserialize_message(internals, Float64MultiArray).data[0] == t
    assert deserialize_message(reference, Float64MultiArray).data[1] == pytest.approx(0.11 * math.sin(2 * t))
    assert steps.command_of(command, STEP_NS, steps.scratch()) == (SAMPLE, cmd.position[0])


@pytest.mark.ros
def test_messages_of_another_layout_or_value_are_refused():
    scr = steps.scratch()
    good = JointState(name=["valve"], position=[1e-4])
    assert steps.command_of(serialize_message(good), STEP_NS, scr) == (0, 1e-4)
    for bad in (JointState(), JointState(name=["valve"]), JointState(name=["spool"], position=[1e-4]),
                JointState(name=["valve", "x"], position=[1e-4, 0.0])):
        assert steps.command_of(serialize_message(bad), STEP_NS, scr)[0] == MALFORMED
    off_grid = JointState(name=["valve"], position=[1e-4])
    off_grid.header.stamp.nanosec = 150_000
    assert steps.command_of(serialize_message(off_grid), STEP_NS, scr)[0] == MALFORMED
    assert steps.command_of(b"\x00\x01\x00\x00", STEP_NS, scr)[0] == MALFORMED
    assert steps.command_of(serialize_message(JointState(name=["valve"], position=[math.nan])),
                            STEP_NS, scr)[0] == NOT_FINITE
    state, _ = _state_bytes(Config().actuator.initial_state())
    assert _controller_answer(state)[0] == SAMPLE
    assert _controller_answer(serialize_message(JointState()))[0] == MALFORMED
    inf_state, _ = _state_bytes([0.0, math.inf, 1e6, 1e6])
    assert _controller_answer(inf_state)[0] == NOT_FINITE
