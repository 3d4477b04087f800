"""Play a bag back onto the ROS graph, or replay its states to a controller.

:func:`replay` is ``ros2 bag play`` for our bags: every message is published
raw (the recorded CDR bytes) at its log time scaled by ``rate``, and ``/clock``
follows the playback so nodes with ``use_sim_time`` keep time with it.

:func:`replay_controller` feeds the recorded plant states one at a time to a
controller and compares each command it answers with the recorded one:
either a controller node already running on the graph (``node``, e.g.
``/sim0/controller``: reset through its ``~/reset`` first, then fed on its
namespace's ``state`` topic; it answers with its own parameters), or (``node``
None) a regression check of this code: a controller built in this process
with the parameters stored in the bag (and the gains in force at the start of
the recording).
"""
from __future__ import annotations

import heapq
import struct
import time
from dataclasses import dataclass

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger

from has_control.wire import cdr
from has_control.bag import CLOCK, COMMAND, FLOAT64_ARRAY, GAINS, JOINT_STATE, STATE, STRING, BagError, read_bag
from has_control.nodes.runtime import CONTROL_QOS, borrowed_context, sample_of
from has_control.config import config_parameters
from has_control.nodes.controller_node import ControllerNode

CLASSES = {JOINT_STATE: JointState, CLOCK: Clock, FLOAT64_ARRAY: Float64MultiArray, STRING: String}


def _qos(offered: str) -> QoSProfile:
    """The recorded publisher's reliability and durability (rosbag2's metadata)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                      reliability=ReliabilityPolicy.BEST_EFFORT if "best_effort" in offered
                      else ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if "transient_local" in offered
                      else DurabilityPolicy.VOLATILE)


SUBSCRIBER_TIMEOUT = 60.0            # [s] the longest wait for subscribers


def replay(path, rate: float = 1.0, topics: list[str] | None = None,
           context: rclpy.Context | None = None, wait_for_subscribers: float = 0.5,
           subscribers: int = 0, subscriber_timeout: float = SUBSCRIBER_TIMEOUT) -> tuple[int, float]:
    """Publish the bag's messages with their timing scaled by ``rate``; returns
    (messages published, wall seconds).

    ``subscribers`` N > 0: the first message goes out once one of the replayed topics
    has N matched subscriptions (a subscriber started before gets the first state),
    a BagError after ``subscriber_timeout`` s without; 0: after a fixed
    ``wait_for_subscribers`` s for discovery."""
    bag = read_bag(path, topics=topics)
    if topics:
        missing = sorted(set(topics) - set(bag.types))
        if missing:
            raise BagError(f"{path}: no topic {', '.join(missing)}; topics: {', '.join(sorted(bag.types))}")
    unknown = {t: ty for t, ty in bag.types.items() if ty not in CLASSES and bag.messages.get(t)}
    if unknown:
        t, ty = next(iter(unknown.items()))
        raise BagError(f"{path}: topic {t} has type {ty}, which replay does not know")
    with borrowed_context(context) as context:
        node = rclpy.create_node("replay", context=context)
        pubs = {t: node.create_publisher(CLASSES[bag.types[t]], t, _qos(bag.qos.get(t, "")))
                for t in bag.types if bag.messages.get(t)}
        own_clock = "/clock" not in pubs
        clock = node.create_publisher(Clock, "/clock", 10) if own_clock else None
        if subscribers > 0:
            _wait_for(pubs, subscribers, subscriber_timeout)
        else:
            time.sleep(wait_for_subscribers)             # let subscribers discover us
        stream = heapq.merge(*[[(t_ns, topic, data) for t_ns, data in msgs]
                               for topic, msgs in bag.messages.items() if topic in pubs])
        t0_bag = bag.start_ns
        t0 = time.perf_counter()
        count = 0
        for t_ns, topic, data in stream:
            due = (t_ns - t0_bag) / 1e9 / rate
            wait = due - (time.perf_counter() - t0)
            if wait > 0:
                time.sleep(wait)
            if own_clock:
                clock.publish(Clock(clock=_time(t_ns)))
            pubs[topic].publish(data)
            count += 1
        seconds = time.perf_counter() - t0
        node.destroy_node()
        return count, seconds


def _wait_for(pubs: dict, n: int, timeout: float) -> None:
    """Until one of ``pubs`` has ``n`` matched subscriptions; a BagError after ``timeout`` s."""
    end = time.monotonic() + timeout
    while max(p.get_subscription_count() for p in pubs.values()) < n:
        if time.monotonic() > end:
            counts = ", ".join(f"{t} {p.get_subscription_count()}" for t, p in sorted(pubs.items()))
            raise BagError(f"replay --wait-for-subscribers {n}: not {n} subscriber{'s' if n > 1 else ''} on one "
                           f"topic within {timeout:g} s (matched: {counts})")
        time.sleep(0.01)


def _time(ns: int):
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


@dataclass
class ReplayCheck:
    samples: int
    mismatches: int
    max_abs_diff: float                 # [m]
    first_mismatch: int | None


def replay_controller(path, tolerance: float = 0.0, context: rclpy.Context | None = None,
                      timeout: float = 5.0, node: str | None = None) -> ReplayCheck:
    """Feed the recorded states to the running controller node ``node`` (its
    fully qualified name) or, None, to a controller built here from the bag's
    parameters; compare its commands with the recorded ones."""
    bag = read_bag(path)
    cfg = bag.config()
    st, cm = bag.find(STATE, JOINT_STATE), bag.find(COMMAND, JOINT_STATE)
    states, commands = bag.messages[st], bag.messages[cm]
    if not states or not commands:
        raise BagError(f"{path}: no messages on {st if not states else cm}")
    _check_joint_states(path, st, states)
    _check_joint_states(path, cm, commands)
    _, recorded_u, _, _ = cdr.joint_states([d for _, d in commands], cm)
    recorded_u = recorded_u[:, 0]
    params = config_parameters(cfg)
    try:
        gains_topic = bag.find(GAINS, FLOAT64_ARRAY)
        g = cdr.float64_arrays([bag.messages[gains_topic][0][1]])[0]
        params.update({"gains.k1": g[1], "gains.k2": g[2], "gains.k3": g[3]})
    except (BagError, IndexError):
        pass                                          # the stored parameters' gains
    n = min(len(states), len(recorded_u))
    step_ns = cfg.episode.step_ns
    stamps = cdr.stamps_ns([d for _, d in states[:n]])
    off = np.flatnonzero(stamps % step_ns)
    if off.size:                      # the controller would refuse each one and time out on it
        k = int(off[0])
        raise BagError(f"{path}: state {k} is stamped {int(stamps[k])} ns, off the grid of simulation.step = "
                       f"{cfg.episode.step:g} s the bag's parameters give ({off.size} of {n} states off it): "
                       "metadata.yaml edited, or recorded with another step")
    with borrowed_context(context) as context:
        if node is None:
            ns = "/replay"
            controller = ControllerNode(namespace=ns, context=context, parameter_overrides=[
                Parameter(k, value=v) for k, v in params.items()] + [Parameter("publish_internals", value=False)])
        else:
            node = "/" + node.strip("/")
            ns, controller = node.rsplit("/", 1)[0], None
        driver = rclpy.create_node("replay_driver", namespace=ns or "/", context=context)
        answers: dict[int, float] = {}
        pub = driver.create_publisher(JointState, "state", CONTROL_QOS)
        driver.create_subscription(JointState, "command",
                                   lambda m: answers.__setitem__(sample_of(m.header.stamp, step_ns),
                                                                 m.position[0]), CONTROL_QOS)
        ex = EventsExecutor(context=context)
        if controller is not None:
            ex.add_node(controller)
        ex.add_node(driver)
        if node is not None:
            _reset(ex, driver, node)
        end = time.monotonic() + 10.0
        while not (pub.get_subscription_count() and driver.count_publishers(f"{ns}/command")):
            if time.monotonic() > end:
                raise BagError(f"replay: the controller {node or 'built from the bag'} did not connect within 10 s")
            ex.spin_once(timeout_sec=0.01)
        idx = stamps // step_ns
        diffs = np.full(n, np.inf)
        for k in range(n):
            i = int(idx[k])
            pub.publish(states[k][1])
            deadline = time.monotonic() + timeout
            while i not in answers and time.monotonic() < deadline:
                ex.spin_once(timeout_sec=0.01)
            if i in answers:
                diffs[k] = abs(answers.pop(i) - recorded_u[k])
        ex.shutdown()
        if controller is not None:
            controller.destroy_node()
        driver.destroy_node()
    bad = np.flatnonzero(~(diffs <= tolerance))
    return ReplayCheck(n, int(bad.size), float(diffs.max()) if n else 0.0,
                       int(bad[0]) if bad.size else None)


def _check_joint_states(path, topic: str, messages: list) -> None:
    """Before any is replayed: every JointState of ``topic`` is whole (the first one's
    size and layout) and finite, else a BagError naming the bag, topic and message
    (a damaged recording is bad input, exit 2, never a count of mismatches)."""
    datas = [d for _, d in messages]
    try:
        cdr.parse_joint_state_layout(datas[0])
    except (cdr.CdrError, struct.error, IndexError, UnicodeDecodeError) as exc:
        raise BagError(f"{path}: {topic}: message 0: not a readable JointState ({exc})") from None
    size = len(datas[0])
    for k, d in enumerate(datas):
        if len(d) != size:
            raise BagError(f"{path}: {topic}: message {k}: {'truncated' if len(d) < size else 'longer than the first'} "
                           f"({len(d)} bytes, the first has {size}): a damaged recording")
    try:
        _, position, velocity, effort = cdr.joint_states(datas, topic)
    except cdr.CdrError as exc:
        raise BagError(f"{path}: {exc}") from None
    finite = np.isfinite(position).all(axis=1) & np.isfinite(velocity).all(axis=1) & np.isfinite(effort).all(axis=1)
    bad = np.flatnonzero(~finite)
    if bad.size:
        raise BagError(f"{path}: {topic}: message {int(bad[0])}: a value is not finite (NaN or inf; {bad.size} such "
                       f"message{'s' if bad.size > 1 else ''}): a damaged recording cannot be replayed to a controller")


def _reset(ex, driver, node: str) -> None:
    """The running controller ``node`` back to â(0) through its ``~/reset``
    (BagError, one line, when there is no such node)."""
    client = driver.create_client(Trigger, f"{node}/reset")
    end = time.monotonic() + 10.0
    while not client.service_is_ready():
        if time.monotonic() > end:
            raise BagError(f"replay: no controller node {node} (no {node}/reset service within 10 s)")
        ex.spin_once(timeout_sec=0.05)
    future = client.call_async(Trigger.Request())
    while not future.done():
        if time.monotonic() > end + 10.0:
            raise BagError(f"replay: {node}/reset did not answer")
        ex.spin_once(timeout_sec=0.05)
