"""Interrupts (has_control.common.interrupts): SIGINT or SIGTERM to a command, a node or a Dask run ends in
one line, "has-control: interrupted", and exit 130, at any moment; what was stored before it (a session, a
bag) stays usable."""
import os
import re
import signal
import socket
import subprocess
import sys
import time

import pytest
from conftest import CLI

from has_control.bag import read_bag


def _signalled(argv, sig, delay, group=False, ready=lambda: True):
    """``sig`` to a command ``delay`` seconds after ``ready()`` (to its process group: as a terminal sends
    Ctrl-C); its status and stderr."""
    p = subprocess.Popen([sys.executable, "-m", "has_control.cli", *map(str, argv)], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while not ready() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(delay)
    os.killpg(p.pid, sig) if group else p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    return p.returncode, err


@pytest.mark.cluster
def test_ctrl_c_at_the_terminal_while_dask_gathers_is_one_line(tmp_path):
    pytest.importorskip("distributed")
    many = tmp_path / "many.yaml"
    many.write_text("random: {count: 6000, seed: 1, ranges: {plant.mass: [1200.0, 1800.0]}}\n")
    rc, err = _signalled(["robustness", "--gains", 400, 400, 400, "--scenarios", many, "--dask", "local:1"],
                         signal.SIGINT, 20.0, group=True)                   # the whole group, as a terminal does
    assert rc == 130 and err.strip().splitlines() == ["has-control: interrupted"], err[:3000]


@pytest.mark.parametrize("argv, delay", [
    (["tune", "--variant", "pso-cp-tvac", "--particles", "80", "--iterations", "2000"], 0.3),      # while loading
    (["tune", "--variant", "pso-cp-tvac", "--particles", "80", "--iterations", "2000"], 6.0),      # while tuning
])
@pytest.mark.system
def test_sigterm_is_one_line_and_130(argv, delay):
    rc, err = _signalled(argv, signal.SIGTERM, delay)
    assert rc == 130 and err.strip().splitlines() == ["has-control: interrupted"], err


@pytest.mark.system
def test_sigterm_leaves_a_session_that_resumes(tmp_path):
    out = tmp_path / "t"
    rc, err = _signalled(["tune", "--variant", "pso-cp-tvac",
                          "--particles", "80", "--iterations", "100", "--out", out], signal.SIGTERM, 1.0,
                         ready=lambda: any(out.glob("session/*.mcap")))
    assert rc == 130, err
    from has_control.tuning.session import SESSION, restore
    bag = read_bag(out / SESSION)
    tuning, _, _, k, swarm = restore(bag.messages, out)
    assert tuning.swarm.particles == 80 and (swarm is None or swarm.iteration == k)


#: What a realtime run may log while it runs: a fail-safe outage (a stall of the shared machine) and its
#: end. These come before the signal: the paced loop runs on the main thread, where Ctrl-C ends it at
#: once, so no sample goes unanswered after it. Not a summary, not a traceback.
RUN_EVENTS = re.compile(r"^\[(WARN|INFO)\] \[[0-9.]+\] \[plant\]: (no command for \d+ samples at sample \d+: "
                        r"valve centred \(u = 0\) until commands return|commands are back at sample \d+)$")


@pytest.mark.ros
def test_ctrl_c_during_a_realtime_stack_is_one_line():
    rc, err = _signalled(["stack", "--realtime", "--duration", "20"], signal.SIGINT, 9.0)
    lines = [line for line in err.strip().splitlines() if not RUN_EVENTS.match(line)]
    assert rc == 130 and lines == ["has-control: interrupted"], err


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


@pytest.mark.ros
@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_a_signal_during_a_recorded_stack_leaves_a_clean_bag(tmp_path, signame, domain_id):
    import os
    import signal
    from has_control.bag import read_bag
    bag = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "has_control.cli", "stack", "--duration", "600", "--record", bag],
                         env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    end = time.monotonic() + 120
    while time.monotonic() < end and not (bag / "run.mcap").exists():
        time.sleep(0.1)
    time.sleep(1.5)                                       # mid-run
    p.send_signal(getattr(signal, signame))
    err = p.communicate(timeout=60)[1]
    assert p.returncode == 130 and err.strip() == "has-control: interrupted", (p.returncode, err[-3000:])
    b = read_bag(bag)
    assert b.complete and (bag / "metadata.yaml").exists()
    n = b.count("/state")
    assert n > 1000 and b.count("/command") in (n - 1, n)  # every sample taken before the signal


@pytest.mark.ros
def test_ctrl_c_in_the_first_second_is_one_line_and_130():
    for args in (["tune", "--variant", "pso-cp-tvac", "--iterations", "1", "--particles", "2"],
                 ["stack", "--duration", "2"]):
        p = subprocess.Popen([sys.executable, "-m", "has_control.cli", *args],
                             stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
        time.sleep(0.4)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
        assert p.returncode == 130 and "Traceback" not in err, (args[0], err)
        assert err.strip().splitlines() == ["has-control: interrupted"], err
