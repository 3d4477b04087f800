"""Interrupts (has_control.common.interrupts): SIGINT or SIGTERM to a command, a node or a Dask run ends in
one line, "has-control: interrupted", and exit 130, at any moment; what was stored before it (a session, a
bag) stays usable."""
import os
import re
import signal
import subprocess
import sys
import time

import pytest

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
