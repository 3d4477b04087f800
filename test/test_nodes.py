"""The node graph: same trace as the library, parameters, namespaces, fail-safe."""
import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from conftest import spin_until
import rclpy
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from has_control.core.episode import simulate

from has_control.config import with_horizon
from has_control.nodes.controller_node import ControllerNode
from has_control.nodes.plant_node import PlantNode
from has_control.nodes.stack import run_stack
from has_control.core.params import Config
from has_control.common.errors import HasControlError
from has_control.nodes.runtime import CONTROL_QOS, state_message

pytestmark = [pytest.mark.ros]


def test_graph_run_equals_the_in_process_trace(context):
    cfg = with_horizon(Config(), 1.5)
    run = run_stack(cfg, context=context)
    ref = simulate(cfg)
    assert run.trace.shape == ref.data.shape == (5000, 12)
    np.testing.assert_allclose(run.trace, ref.data, rtol=1e-12, atol=0)
    assert run.score == ref.score and run.failsafe_events == 0


def test_namespaced_stack_with_other_gains(context):
    cfg = with_horizon(Config(), 1.5)
    run = run_stack(cfg, gains=(404.0, 401.0, 407.0), namespace="/sim3", context=context)
    assert run.score == simulate(cfg, (404.0, 401.0, 407.0)).score


def test_diverging_gains_score_inf_through_the_graph(context):
    run = run_stack(with_horizon(Config(), 1.5), gains=(1e4, 1e4, 1e4), context=context)
    assert run.score.diverged and math.isinf(run.score.J)


@pytest.mark.parametrize("value", [-1.0, math.nan, 0.0])
def test_invalid_gains_are_rejected_and_the_old_ones_kept(context, value):
    node = ControllerNode(context=context)
    try:
        res = node.set_parameters_atomically([Parameter("gains.k1", value=value),
                                              Parameter("gains.k2", value=500.0)])
        assert not res.successful and "gains.k1" in res.reason
        assert node.get_parameter("gains.k1").value == 150.0
        assert node.get_parameter("gains.k2").value == 158.0
        assert node.k == (150.0, 158.0, 162.0)
        ok = node.set_parameters_atomically([Parameter("gains.k1", value=300.0)])
        assert ok.successful
        node._on_state(_state_msg())            # new gains apply from the next sample
        assert node.k == (300.0, 158.0, 162.0)
        bad = node.set_parameters([Parameter("adaptation.lower", value=[3500.0, 4e-12])])
        assert not bad[0].successful and "adaptation.lower" in bad[0].reason
    finally:
        node.destroy_node()


def _state_msg():
    from has_control.nodes.runtime import state_message
    cfg = Config()
    return state_message(0, 300_000, cfg.actuator.initial_state(), cfg.actuator)


def test_plant_fail_safe_centres_the_valve_and_recovers(context):
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[Parameter("command_timeout", value=0.02)])
    ex.add_node(plant)
    plant.process.log = []
    plant.start()
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        ex.spin_once(timeout_sec=0.01)
    stalled = plant.failsafe_events
    assert stalled >= 5 and plant.sample == stalled
    assert all(row[-1] == 0.0 for row in plant.process.log)       # u = 0 while no controller
    controller = ControllerNode(context=context)             # the controller comes back
    ex.add_node(controller)
    before = plant.sample
    end = time.monotonic() + 3.0
    while time.monotonic() < end and plant.sample < before + 200:
        ex.spin_once(timeout_sec=0.01)
    assert plant.sample >= before + 200 and not plant._in_outage
    assert any(row[-1] != 0.0 for row in plant.process.log[before:])
    ex.shutdown()
    plant.destroy_node()
    controller.destroy_node()


def test_reset_services_restore_the_initial_state(context):
    from std_srvs.srv import Trigger
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context)
    controller = ControllerNode(context=context)
    client_node = rclpy.create_node("resetter", context=context)
    for n in (plant, controller, client_node):
        ex.add_node(n)
    plant.x[0] = 0.05
    plant.sample = 42
    controller.a1_hat = 2900.0
    for name in ("/plant/reset", "/controller/reset"):
        cli = client_node.create_client(Trigger, name)
        assert cli.wait_for_service(timeout_sec=5.0)
        fut = cli.call_async(Trigger.Request())
        ex.spin_until_future_complete(fut, timeout_sec=5.0)
        assert fut.result().success
    assert plant.sample == 0 and plant.x[0] == 0.0 and controller.a1_hat == 2600.0
    ex.shutdown()
    for n in (plant, controller, client_node):
        n.destroy_node()


def test_killing_the_controller_mid_run_trips_the_fail_safe_and_a_restart_resumes(context, domain_id):
    """A controller process dies mid-run (SIGKILL): the plant centres the valve and
    runs on; a new controller process takes over."""
    import os
    import subprocess
    import sys
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    cmd = [sys.executable, "-m", "has_control.cli", "controller", "--ros-args", "-p", "publish_internals:=false"]
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[Parameter("command_timeout", value=0.05)])
    plant.process.log = []
    ex.add_node(plant)
    first = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    second = None
    try:
        assert spin_until(ex, plant.connected, 60)
        plant.start()
        assert spin_until(ex, lambda: plant.sample >= 500, 60) and plant.failsafe_events == 0
        first.kill()
        first.wait()
        killed_at = plant.sample
        assert spin_until(ex, lambda: plant.failsafe_events >= 10, 10)
        assert plant._in_outage and plant.sample > killed_at            # the run continues
        outage = [row[-1] for row in plant.process.log[killed_at + 2:]]
        assert outage and all(u == 0.0 for u in outage)                  # valve centred
        second = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        back = plant.sample
        assert spin_until(ex, lambda: plant.sample >= back + 500 and not plant._in_outage, 60)
        resumed = [row[-1] for row in plant.process.log[-100:]]
        assert all(u != 0.0 for u in resumed)                            # under control again
        assert abs(plant.x[0]) < 0.2                                     # and still sane
    finally:
        for p in (first, second):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        ex.shutdown()
        plant.destroy_node()


def _realtime_run(context, failsafe_samples: int):
    """A realtime plant fed one command (u = 1e-5 m) once: what it holds, and its reports.

    The command comes from the test, not a controller, so the outcome does not
    depend on how fast this machine answers."""
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from has_control.nodes.runtime import CONTROL_QOS
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[
        Parameter("mode", value="realtime"), Parameter("samples", value=4000),
        Parameter("failsafe_samples", value=failsafe_samples)])
    driver = rclpy.create_node("driver", context=context)
    pub = driver.create_publisher(JointState, "command", CONTROL_QOS)
    driver.create_subscription(JointState, "state", lambda m: None, CONTROL_QOS)
    reports = []
    driver.create_subscription(DiagnosticArray, "/diagnostics", reports.append, 10)
    for n in (plant, driver):
        ex.add_node(n)
    plant.process.log = []
    assert spin_until(ex, plant.connected, 10)
    pub.publish(JointState(name=["valve"], position=[1e-5]))      # stamped sample 0, before the start
    assert spin_until(ex, lambda: plant.command_sample == 0, 10)
    plant.start()
    plant.run_realtime(ex)                                       # paced on this thread, which owns ex
    assert plant.finished
    spin_until(ex, lambda: False, 0.2)
    u = np.array([row[-1] for row in plant.process.log])
    stats, events = plant.realtime_stats, plant.failsafe_events
    ex.shutdown()
    for n in (plant, driver):
        n.destroy_node()
    return u, stats, events, reports


def test_realtime_mode_holds_the_last_command_and_reports_diagnostics(context):
    u, stats, events, reports = _realtime_run(context, failsafe_samples=100_000)
    assert np.all(u == 1e-5) and events == 0                # the one command, held every sample
    assert stats["samples"] == 4000 and set(stats) >= {"rate_hz", "late_p99_us", "overruns"}
    status = reports[-1].status[0]
    assert "realtime loop" in status.name and {kv.key for kv in status.values} >= {"rate_hz", "late_p99_us"}


def test_realtime_fail_safe_centres_the_valve_after_missing_samples(context):
    u, stats, events, _ = _realtime_run(context, failsafe_samples=10)
    assert np.all(u[:11] == 1e-5) and np.all(u[11:] == 0.0)  # samples 0..10 answered by it, then centred
    assert events == 4000 - 11 and stats["failsafe_samples"] == events


def test_bad_plant_mode_is_rejected(context):
    with pytest.raises(ValueError, match="mode = 'fast'"):
        PlantNode(context=context, parameter_overrides=[Parameter("mode", value="fast")])


def test_controller_follows_sim_time_from_the_plant_clock(context):
    cfg = with_horizon(Config(), 1.5)
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[Parameter("samples", value=cfg.episode.samples)])
    controller = ControllerNode(context=context, parameter_overrides=[Parameter("use_sim_time", value=True)])
    for n in (plant, controller):
        ex.add_node(n)
    assert spin_until(ex, plant.connected, 10)
    plant.start()
    assert spin_until(ex, lambda: plant.finished, 60)
    spin_until(ex, lambda: False, 0.3)
    assert controller.get_clock().now().nanoseconds == (cfg.episode.samples - 1) * 300_000
    ex.shutdown()
    for n in (plant, controller):
        n.destroy_node()


def test_realtime_stack_runs_the_lockstep_run_until_a_command_is_late(context):
    """Paced lock-step: every sample answered in time is the library's sample, bit
    for bit; the figures say how the loop kept time."""
    cfg = with_horizon(Config(), 1.5)
    run = run_stack(cfg, context=context, realtime=True)
    ref = simulate(cfg)
    f = run.loop
    assert set(f) == {"samples_per_second", "realtime_factor", "missed_samples", "failsafe_samples", "late_p99_us"}
    assert f["missed_samples"] == len(run.missed_at) and run.trace.shape[1] == 12
    assert 0.0 < f["realtime_factor"] <= 1.0 + 1e-3          # never ahead of wall time
    first_miss = run.missed_at[0] if run.missed_at else len(ref.data)
    assert first_miss > 0                                     # sample 0 waits out the start-up
    np.testing.assert_array_equal(run.trace[:first_miss], ref.data[:first_miss])
    if not run.missed_at:
        assert run.score == ref.score


def test_killing_the_controller_mid_run_in_realtime_mode(context, domain_id):
    """The realtime plant centres the valve after failsafe_samples misses when its
    controller process dies, keeps time, and is under control again after a restart."""
    import os
    import subprocess
    import sys
    import threading
    import shutil
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    cmd = [sys.executable, "-m", "has_control.cli", "controller", "--ros-args", "-p", "publish_internals:=false"]
    # as docs/nodes.md deploys it: the controller process under SCHED_FIFO from its start, so that its DDS
    # threads inherit it (with a CPU hog beside it, 0.88-0.99 of the last 3 000 samples answered without, 1.00 with)
    chrt = ["chrt", "-f", "50"]
    if shutil.which("chrt") and subprocess.run([*chrt, "true"], capture_output=True).returncode == 0:
        cmd = chrt + cmd
    ex = EventsExecutor(context=context)
    samples = int(12.0 / 0.0003)                         # room for a restart slowed by the loaded machine
    plant = PlantNode(context=context, parameter_overrides=[
        Parameter("mode", value="realtime"), Parameter("samples", value=samples)])
    plant.process.log = []
    ex.add_node(plant)
    procs = [subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    marks = {}

    def fault():                                          # off the loop's thread: kill at ~1.5 s, restart
        while plant.sample < 5000:
            time.sleep(0.01)
        procs[0].kill()
        procs[0].wait()
        marks["killed"] = plant.sample
        time.sleep(0.5)
        marks["restarted"] = plant.sample
        procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    try:
        assert spin_until(ex, plant.connected, 60)
        threading.Thread(target=fault, daemon=True).start()
        plant.start()
        stats = plant.run_realtime(ex)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        ex.shutdown()
        plant.destroy_node()
    u = np.array([row[-1] for row in plant.process.log])
    killed, restarted = marks["killed"], marks["restarted"]
    assert stats.samples == samples and stats.failsafe > 0
    outage = u[killed + plant.failsafe_samples + 20:restarted]
    assert len(outage) > 1000 and np.all(outage == 0.0)              # valve centred while it is gone
    # under control again (across processes a rare run of late answers may still centre a sample)
    assert np.mean(u[-3000:] != 0.0) > 0.95
    assert abs(plant.x[0]) < 0.2                                      # and still sane


@pytest.mark.ros
def test_the_controller_builds_a_new_road_off_its_executor(context, monkeypatch):
    import types

    from rclpy.parameter import Parameter

    import has_control.loop.controller as controller_process     # the process builds the road, the node hosts it
    import has_control.nodes.controller_node as controller_node
    names = []

    class Recorded(threading.Thread):
        def __init__(self, *args, **kwargs):
            names.append(kwargs.get("name"))
            super().__init__(*args, **kwargs)
    monkeypatch.setattr(controller_process, "threading", types.SimpleNamespace(Thread=Recorded, Lock=threading.Lock))
    node = controller_node.ControllerNode(context=context)
    try:
        assert node.set_parameters_atomically([Parameter("reference.kind", value="road"),
                                               Parameter("reference.cutoff", value=1600.0),
                                               Parameter("reference.seed", value=987)]).successful
        assert node.set_parameters([Parameter("gains.k1", value=500.0)])[0].successful
        deadline = time.monotonic() + 60
        while (node._pending is None or node._pending[0].gains.k1 != 500.0) and time.monotonic() < deadline:
            time.sleep(0.01)
        cfg, arrays = node._pending
        assert "controller-road" in names                       # the first road was built on a thread
        assert cfg.reference.cutoff == 1600.0 and cfg.gains.k1 == 500.0     # the newest set won
        assert arrays.reference.size > 4 * cfg.episode.samples
    finally:
        node.destroy_node()


def test_malformed_and_non_finite_messages_are_counted_and_ignored(context):
    """Empty JointStates, NaN values and strangers' layouts reach neither the
    plant's state nor the controller's estimates; the loop then runs as the library's."""
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[Parameter("samples", value=2000)])
    controller = ControllerNode(context=context)
    controller.record_trace(2000)
    evil = rclpy.create_node("evil", context=context)
    to_plant = evil.create_publisher(JointState, "command", CONTROL_QOS)
    to_controller = evil.create_publisher(JointState, "state", CONTROL_QOS)
    for n in (plant, controller, evil):
        ex.add_node(n)
    assert spin_until(ex, lambda: to_plant.get_subscription_count() and to_controller.get_subscription_count(), 10)
    cfg = Config()
    nan_state = state_message(0, 300_000, [0.0, math.nan, 1e6, 1e6], cfg.actuator)
    for msg in (JointState(), JointState(name=["valve"], position=[math.nan]), JointState(name=["valve"])):
        to_plant.publish(msg)                            # keep-last 1: one at a time
        spin_until(ex, lambda: False, 0.1)
    for msg in (JointState(), nan_state, JointState(name=["x"], position=[1.0])):
        to_controller.publish(msg)
        spin_until(ex, lambda: False, 0.1)
    assert plant.malformed_commands == 3 and controller.malformed_states == 3
    assert plant.sample == 0 and np.all(np.isfinite(plant.x)) and controller.a1_hat == 2600.0
    assert spin_until(ex, plant.connected, 10)
    plant.start()
    assert spin_until(ex, lambda: plant.finished, 60)
    ref = simulate(with_horizon(cfg, 1.5))
    np.testing.assert_array_equal(controller.trace, ref.data[:2000])
    ex.shutdown()
    for n in (plant, controller, evil):
        n.destroy_node()


def test_a_second_controller_on_the_command_topic_fails_the_run_loudly(domain_id):
    """Another controller answers the same states with other gains: the stack
    refuses to report a number instead of scoring a mixture."""
    cmd = [sys.executable, "-m", "has_control.cli", "controller", "--ros-args", "-p", "publish_internals:=false",
           "-p", "gains.k1:=400.0"]
    import os
    other = subprocess.Popen(cmd, env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        probe_ctx = rclpy.Context()
        rclpy.init(context=probe_ctx, domain_id=domain_id)
        probe = rclpy.create_node("probe", context=probe_ctx)
        end = time.monotonic() + 60
        while time.monotonic() < end and not probe.count_publishers("/command"):
            time.sleep(0.05)                             # it is up and on the graph
        assert probe.count_publishers("/command")
        probe.destroy_node()
        rclpy.try_shutdown(context=probe_ctx)
        with pytest.raises(HasControlError, match="another node publishes on this loop's topics"):
            run_stack(with_horizon(Config(), 120.0), domain_id=domain_id)   # long enough to meet it; ends at it
    finally:
        other.kill()
        other.wait()


def test_runtime_changes_the_loop_cannot_take_are_refused(context):
    controller = ControllerNode(context=context)
    plant = PlantNode(context=context)
    try:
        res = controller.set_parameters([Parameter("simulation.step", value=1e-12)])[0]
        assert not res.successful and "simulation.step" in res.reason and controller.dt == 3e-4
        for name, value in (("samples", -5), ("command_timeout", -1.0), ("realtime_priority", 200)):
            res = plant.set_parameters([Parameter(name, value=value)])[0]
            assert not res.successful and name in res.reason
        assert plant.samples == 0 and plant.timeout == 0.5
    finally:
        controller.destroy_node()
        plant.destroy_node()


def test_a_command_of_another_layout_is_read_by_name_only_on_the_sample_grid(context):
    """A valve JointState with a frame_id and extra joints is still a command; off the grid it is refused."""
    from rclpy.serialization import serialize_message
    plant = PlantNode(context=context)
    try:
        other = JointState(name=["spool_temperature", "valve"], position=[300.0, 2e-5])
        other.header.frame_id = "base"
        other.header.stamp.nanosec = 600_000                  # sample 2
        plant._on_command(serialize_message(other))
        assert (plant.command_sample, plant.command_u, plant.malformed_commands) == (2, 2e-5, 0)
        other.header.stamp.nanosec = 750_000                  # between samples 2 and 3
        plant._on_command(serialize_message(other))
        assert plant.command_sample == 2 and plant.malformed_commands == 1
    finally:
        plant.destroy_node()


@pytest.mark.ros
def test_controller_rejects_a_road_it_cannot_build_and_keeps_the_old_reference(context):
    from has_control.nodes.controller_node import ControllerNode
    node = ControllerNode(context=context)
    try:
        res = node.set_parameters_atomically([Parameter("reference.kind", value="road"),
                                              Parameter("reference.speed", value=1.0e300)])
        assert not res.successful and "reference.cutoff" in res.reason
        assert node.get_parameter("reference.kind").value == "sine" and node._pending is None
    finally:
        node.destroy_node()
