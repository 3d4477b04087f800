"""Issue #31, hostile input round 4, outside the readers and the tuner node:
planned work bounded before allocation, out of memory and a closed standard
output, the live view's arguments, replay of a damaged bag, replay waiting for
its subscribers (#30 item 4), signals to the nodes and to a Dask run. Each ends
in one line naming the culprit and exit 2 (130 for a signal, 141 quietly for a
closed standard output), in bounded time."""
from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from conftest import one_line

from has_control.bag import PARAMETERS_KEY, BagError, BagWriter, parameters_json, read_bag, write_trace
from has_control.cli import main
from has_control.config import build_config
from has_control.core.episode import simulate
from has_control.tuning.landscape import MAX_EPISODES, check_plan, planned_episodes, slices
from has_control.wire import cdr

CLI = [sys.executable, "-m", "has_control.cli"]


# --- planned work ---------------------------------------------------------------------------------

def test_the_landscape_bounds_slices_times_points_squared_times_scenarios_before_allocation(tmp_path, capsys):
    many = tmp_path / "many.yaml"
    many.write_text("random: {count: 1000, seed: 1, ranges: {plant.mass: [1200.0, 1800.0]}}\n")
    t0 = time.perf_counter()
    one_line(capsys, ["landscape", "--points", "300", "--scenarios", str(many)], "--points 300",
             "1,000 scenarios", "270,000,000 episodes", f"limit of {MAX_EPISODES:,}")
    assert time.perf_counter() - t0 < 30
    assert planned_episodes(300) == MAX_EPISODES and check_plan(300) == MAX_EPISODES      # nominal: as before
    assert check_plan(9, 1000) == 243_000

    def never(k):
        raise AssertionError("the objective was called")
    with pytest.raises(Exception, match="episodes, above the limit"):
        slices(never, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), (2.0, 2.0, 2.0), points=20, scenarios=1000)


def test_out_of_memory_is_one_line_and_exit_2_even_with_a_thread_left():
    """The shutdown after a MemoryError could wait for anything (here a thread that
    sleeps a minute); the program leaves at once."""
    code = ("import sys, threading, time\n"
            "import has_control.cli.simulate as s\n"
            "def run(args):\n"
            "    threading.Thread(target=time.sleep, args=(60,)).start()\n"
            "    raise MemoryError\n"
            "s.run = run\n"
            "sys.argv = ['has-control', 'simulate']\n"
            "from has_control.cli.main import main\n"
            "sys.exit(main())\n")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50)
    assert r.returncode == 2 and r.stderr.strip() == "has-control: error: out of memory", r.stderr
    assert time.monotonic() - t0 < 30


def test_a_closed_standard_output_ends_quietly_with_141():
    """As ``yes | head`` does: no "(path unknown): Broken pipe", no traceback; status 128 + SIGPIPE."""
    p = subprocess.Popen(CLI + ["simulate", "--duration", "2", "--json"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.close()                                         # the reader is gone before the answer
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141 and err == "", err


# --- the live view's arguments --------------------------------------------------------------------

@pytest.mark.parametrize("value", ["nan", "inf", "1e308", "-1", "3601"])
def test_foxglove_wait_is_a_bounded_number(capsys, value):
    with pytest.raises(SystemExit) as e:
        main(["stack", "--foxglove", "--foxglove-wait", value])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1
    assert "--foxglove-wait" in err and repr(value) in err and "0 .. 3600" in err


def test_foxglove_wait_without_foxglove_is_refused(capsys):
    one_line(capsys, ["stack", "--foxglove-wait", "3"], "--foxglove-wait 3", "only with --foxglove")


# --- replay of a damaged bag; replay waiting for its subscribers ----------------------------------

@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """(clean, truncated, NaN) bags of a 2 s run; the damage at state 1234."""
    d = tmp_path_factory.mktemp("replay")
    cfg = build_config({"simulation.horizon": 2.0})
    w = BagWriter(d / "clean", {PARAMETERS_KEY: parameters_json(cfg)})
    write_trace(w, simulate(cfg), cfg)
    w.close()
    bag = read_bag(d / "clean")
    msgs = {t: list(m) for t, m in bag.messages.items()}
    lay = cdr.parse_joint_state_layout(msgs["/state"][0][1])

    def damaged(name, change):
        m = {t: list(v) for t, v in msgs.items()}
        lt, b = m["/state"][1234]
        m["/state"][1234] = (lt, change(b))
        w = BagWriter(d / name, dict(bag.custom_data))
        for t in m:
            w.add_topic(t, bag.types[t])
        w.write_batches({t: (np.array([x for x, _ in v], dtype=np.int64), [y for _, y in v]) for t, v in m.items()})
        w.close()
        return d / name

    def nan(b):
        bb = bytearray(b)
        struct.pack_into("<d", bb, lay.position[0], float("nan"))
        return bytes(bb)
    return d / "clean", damaged("truncated", lambda b: b[:-20]), damaged("nan", nan)


def test_replay_of_a_truncated_or_non_finite_state_is_one_line_and_exit_2(bags, capsys):
    _, truncated, nan = bags
    one_line(capsys, ["replay", str(truncated), "--check-code"], str(truncated), "/state: message 1234: truncated")
    one_line(capsys, ["replay", str(nan), "--check-code"], str(nan), "/state: message 1234", "not finite")


@pytest.mark.ros
def test_replay_waits_for_a_subscriber_started_before_and_it_gets_the_first_state(bags, context):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from has_control.nodes.replay import replay
    clean = bags[0]
    first = int(cdr.stamps_ns([read_bag(clean).messages["/state"][0][1]])[0])
    node = rclpy.create_node("early_subscriber", context=context)
    got = []
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    node.create_subscription(JointState, "/state", lambda m: got.append(
        m.header.stamp.sec * 10**9 + m.header.stamp.nanosec), QoSProfile(depth=10000,
                                                                         reliability=ReliabilityPolicy.RELIABLE))
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)])
    spinner.start()
    try:
        time.sleep(1.0)                                       # started well before the replay
        n, _ = replay(clean, rate=5.0, topics=["/state"], context=context, subscribers=1)
        time.sleep(1.0)
    finally:
        stop.set()
        spinner.join()
        node.destroy_node()
    assert n == 6667 and got and got[0] == first, got[:3]


@pytest.mark.ros
def test_replay_without_its_subscribers_is_one_line(bags, context):
    from has_control.nodes.replay import replay
    with pytest.raises(BagError, match=r"--wait-for-subscribers 2: not 2 subscribers on one topic within 0.5 s"):
        replay(bags[0], topics=["/state"], context=context, subscribers=2, subscriber_timeout=0.5)


def test_wait_for_subscribers_is_not_for_a_controller_replay(bags, capsys):
    one_line(capsys, ["replay", str(bags[0]), "--check-code", "--wait-for-subscribers"], "--wait-for-subscribers")


# --- signals: the nodes -----------------------------------------------------------------------------

def _node(domain_id, *argv):
    return subprocess.Popen(CLI + list(argv), env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait_for(p, text: str, timeout: float = 120.0) -> list[str]:
    """stderr lines of ``p`` until one holds ``text``."""
    lines, end = [], time.monotonic() + timeout
    while time.monotonic() < end:
        line = p.stderr.readline()
        if not line:
            break
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"no {text!r} in {lines}")


@pytest.mark.ros
def test_a_controller_interrupted_while_its_services_are_called_ends_in_one_line(domain_id, context):
    """SIGINT while a client calls ~/reset in a loop (rclpy raised KeyboardInterrupt inside
    the service handler: C++ terminate, exit 134, about one time in eight): always 130 and
    "interrupted", the ready line before it."""
    import rclpy
    from std_srvs.srv import Trigger
    client_node = rclpy.create_node("reset_caller", context=context)
    client = client_node.create_client(Trigger, "/controller/reset")
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(client_node)
    try:
        for delay in (0.05, 0.2, 0.35, 0.5):
            p = _node(domain_id, "controller")
            _wait_for(p, "ready:")
            end = time.monotonic() + 30
            while not client.service_is_ready() and time.monotonic() < end:
                ex.spin_once(timeout_sec=0.05)
            calls, t_signal = 0, time.monotonic() + 1.0 + delay
            while time.monotonic() < t_signal:              # a call in flight most of the time
                future = client.call_async(Trigger.Request())
                ex.spin_until_future_complete(future, timeout_sec=0.2)
                calls += 1
            p.send_signal(signal.SIGINT)
            err = p.communicate(timeout=60)[1]
            assert calls > 5
            assert p.returncode == 130 and err.strip().splitlines() == ["has-control: interrupted"], (delay, err)
    finally:
        client_node.destroy_node()


@pytest.mark.ros
def test_a_plant_interrupted_during_its_run_ends_in_one_line(domain_id):
    """SIGINT to a plant mid-episode (rclpy's handler shut the context down under the
    loop: "sample not published", "publisher's context is invalid", or its FATAL
    stack): the episode ends at the next sample, one line, 130."""
    controller = _node(domain_id, "controller")
    try:
        _wait_for(controller, "ready:")
        plant = _node(domain_id, "plant", "--ros-args", "-p", "samples:=2000000")
        _wait_for(plant, "starting the run")
        time.sleep(2.0)
        plant.send_signal(signal.SIGINT)
        err = plant.communicate(timeout=60)[1]
        assert plant.returncode == 130 and err.strip().splitlines() == ["has-control: interrupted"], err
        controller.send_signal(signal.SIGTERM)
        err = controller.communicate(timeout=60)[1]
        assert controller.returncode == 130 and err.strip().splitlines() == ["has-control: interrupted"], err
    finally:
        controller.kill()


@pytest.mark.ros
@pytest.mark.parametrize("moment", ["ready:", "iteration"])
def test_a_tuner_interrupted_during_its_session_ends_in_one_line(domain_id, moment):
    """SIGINT while the tuner's session thread works: no "tuning session failed:
    InvalidHandle" as the node closes under it; its progress lines, then one line, 130."""
    tuner = _node(domain_id, "tuner", "--ros-args", "-p", "swarm.iterations:=2000")
    _wait_for(tuner, moment)
    tuner.send_signal(signal.SIGINT)
    err = tuner.communicate(timeout=60)[1]
    lines = [line for line in err.strip().splitlines() if not line.startswith("[INFO]")]
    assert tuner.returncode == 130 and lines == ["has-control: interrupted"], err[-2000:]


# --- signals: a Dask run -----------------------------------------------------------------------------

@pytest.mark.cluster
@pytest.mark.parametrize("sig, group, delay", [("SIGINT", True, 4.0), ("SIGINT", True, 7.0), ("SIGTERM", False, 9.0)])
def test_a_signal_to_a_dask_run_is_one_line_while_another_program_holds_port_8787(tmp_path, sig, group, delay):
    """Dask's "port 8787 in use" warning, a worker's traceback when the terminal's
    Ctrl-C reaches it in its imports, a cancelled task's warning: none of them; one
    line, 130, at any moment of the run."""
    pytest.importorskip("distributed")
    many = tmp_path / "many.yaml"
    many.write_text("random: {count: 3000, seed: 1, ranges: {plant.mass: [1200.0, 1800.0]}}\n")
    holder = socket.socket()
    try:
        holder.bind(("127.0.0.1", 8787))
        holder.listen()
    except OSError:
        pass                                              # someone holds it already: the same situation
    try:
        p = subprocess.Popen(CLI + ["robustness", "--gains", "400", "400", "400", "--scenarios", str(many),
                                    "--dask", "local:2"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             text=True, start_new_session=True)
        time.sleep(delay)
        os.killpg(p.pid, getattr(signal, sig)) if group else p.send_signal(getattr(signal, sig))
        err = p.communicate(timeout=120)[1]
    finally:
        holder.close()
    assert p.returncode == 130 and err.strip().splitlines() == ["has-control: interrupted"], err[:3000]
