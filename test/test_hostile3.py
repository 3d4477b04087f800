"""Issue #19, hostile input round 3: the newer surfaces. One test (or a few)
per class of defect: outputs that are not regular files, Dask addresses that
are not schedulers, node params files, hand-edited bag metadata and session
bags, scenario ranges, roads' work and memory, signals, and the checks every
front end shares. Each hostile input ends in one line naming the culprit and
exit 2 (130 for a signal), and changes no file but the intended output."""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import socket
import stat
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from conftest import one_line, stopped_session
import yaml

from has_control.bag import PARAMETERS_KEY, BagError, BagWriter, parameters_json, read_bag, write_trace
from has_control.cli import main
from has_control.common.errors import ConfigError, HasControlError
from has_control.common.files import check_output, write_atomic
from has_control.config import with_horizon
from has_control.core.episode import evaluate_configs, simulate
from has_control.core.reference import check_road_memory
from has_control.core.params import N_REFERENCE, REF_TERMS, Config, Episode, Reference

NOM = "scenarios:\n  nominal: {}\n  heavy: {plant.mass: 1800.0}\n"


# --- 1, 12, 13: outputs -----------------------------------------------------------------------------

def test_outputs_that_are_not_regular_files_are_refused_before_the_work(capsys, tmp_path, monkeypatch):
    import has_control.cli.robustness as robustness
    import has_control.cli.simulate as simulate_cli
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    (tmp_path / "file").write_text("x")
    scen = tmp_path / "nom.yaml"
    scen.write_text(NOM)

    def no_work(*a, **k):
        raise AssertionError("the work started")
    monkeypatch.setattr(robustness, "robustness_table", no_work)
    monkeypatch.setattr(simulate_cli, "simulate", no_work)
    cases = [(["simulate", "--trace", fifo], "a FIFO"), (["simulate", "--plot", fifo], "a FIFO"),
             (["simulate", "--trace", "/dev/null"], "a device"), (["simulate", "--plot", "/dev/full"], "a device"),
             (["simulate", "--trace", tmp_path], "a directory"),
             (["simulate", "--trace", tmp_path / "file" / "t.csv"], "Not a directory"),
             (["robustness", "--gains", 400, 400, 400, "--scenarios", scen, "--markdown", fifo], "a FIFO"),
             (["robustness", "--gains", 400, 400, 400, "--scenarios", scen, "--plot", tmp_path / "file" / "p"],
              "Not a directory")]
    for argv, why in cases:
        one_line(capsys, argv, why)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and stat.S_ISCHR(os.stat("/dev/null").st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fifo", "file", "nom.yaml"]


def test_a_symlink_is_written_through_and_stays_a_link(capsys, tmp_path):
    target = tmp_path / "t.csv"
    target.write_text("old\n")
    link = tmp_path / "link.csv"
    link.symlink_to(target.name)
    assert main(["simulate", "--duration", "1.2", "--trace", str(link)]) == 0
    capsys.readouterr()
    assert link.is_symlink() and target.read_text().startswith("t [s],x1d [m],y [m]")
    assert write_atomic(link, "new\n") == link and link.is_symlink() and target.read_text() == "new\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.csv", "t.csv"]       # no temporary file left


def test_a_failed_write_names_the_users_path_not_the_temporary_file(tmp_path, monkeypatch):
    import errno

    def read_only(src, dst):
        raise OSError(errno.EROFS, "Read-only file system", str(src))
    monkeypatch.setattr(os, "replace", read_only)
    with pytest.raises(HasControlError) as info:
        write_atomic(tmp_path / "r.md", "x")
    assert str(info.value) == f"{tmp_path / 'r.md'}: cannot write: Read-only file system"
    assert list(tmp_path.iterdir()) == []


def test_check_output_refuses_unwritable_places(tmp_path):
    (tmp_path / "f").write_text("x")
    assert check_output(tmp_path / "new" / "deeper" / "x.md") == tmp_path / "new" / "deeper" / "x.md"
    for path, why in ((tmp_path / "f" / "x", "Not a directory"), (tmp_path / "f", "is not a directory"),
                      ("", "empty path")):
        with pytest.raises(HasControlError, match=why):
            check_output(path, "directory" if path == tmp_path / "f" else "file")


# --- 2, 9, 12: Dask ---------------------------------------------------------------------------------

def _server(behaviour):
    """A listener on 127.0.0.1 that is not a Dask scheduler; its port."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(8)
    held = []

    def serve():
        while True:
            try:
                c, _ = s.accept()
            except OSError:
                return
            held.append(c)
            try:
                if behaviour == "garbage":
                    c.sendall(bytes(range(256)) * 16 + b"\xff" * 64)
                elif behaviour == "http":
                    c.recv(1024)
                    c.sendall(b"HTTP/1.0 400 Bad Request\r\n\r\n")
            except OSError:
                pass
    threading.Thread(target=serve, daemon=True).start()
    return s, s.getsockname()[1]


@pytest.mark.cluster
@pytest.mark.parametrize("behaviour", ["silent", "garbage", "http"])
def test_an_address_that_is_not_a_scheduler_is_one_line(behaviour, capsys):
    pytest.importorskip("distributed")
    server, port = _server(behaviour)
    old = signal.signal(signal.SIGALRM, lambda *a: pytest.fail("hangs"))
    signal.alarm(60)                                       # a hang guard, not a timing
    try:
        one_line(capsys, ["tune", "--variant", "pso-cp-tvac",
                          "--particles", "2", "--iterations", "1", "--duration", "1.2",
                          "--dask", f"tcp://127.0.0.1:{port}"], f"tcp://127.0.0.1:{port}", "scheduler")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
        server.close()


def test_a_huge_worker_count_is_cut_in_the_error(capsys):
    with pytest.raises(SystemExit):
        main(["tune", "--dask", "local:" + "9" * 5000])
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and len(err) < 300 and "1 <= N <= 1024" in err, err


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


# --- 10, 11: signals ------------------------------------------------------------------------------

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


# --- 3: node params files -------------------------------------------------------------------------

@pytest.mark.parametrize("node", ["plant", "controller", "tuner"])
def test_a_bad_params_file_at_node_start_up_is_one_line_naming_it(node, tmp_path, capsys):
    files = {"nope.yaml": None, "bad.yaml": "a: [\n", "nops.yaml": "/**:\n  gains: {k1: 1.0}\n",
             "extra.yaml": "/**:\n  ros__parameters:\n    gains: {k1: 400.0}\nextra: 1\n",
             "mixed.yaml": "/**:\n  ros__parameters:\n    gains: {k1: [1, \"x\"]}\n",
             "twice.yaml": "/**:\n  ros__parameters:\n    gains.k1: 400.0\n    gains: {k1: 500.0}\n"}
    (tmp_path / "adir").mkdir()
    for name, text in files.items():
        if text is not None:
            (tmp_path / name).write_text(text)
    for name in [*files, "adir"]:
        with pytest.raises(SystemExit) as info:
            main([node, "--ros-args", "--params-file", str(tmp_path / name)])
        err = capsys.readouterr().err
        assert info.value.code == 2 and len(err.strip().splitlines()) == 1, err
        assert str(tmp_path / name) in err and "Traceback" not in err, err


@pytest.mark.ros
@pytest.mark.parametrize("node", ["plant", "controller"])
def test_arguments_rcl_refuses_at_node_start_up_are_one_line(node, capfd):
    """rcl logs its own [ERROR] line on fd 2 before it raises: held back, so ours is the one line."""
    for ros_args in (["-p"], ["-p", "gains.k1:=["]):
        with pytest.raises(SystemExit) as info:
            main([node, "--ros-args", *ros_args])
        lines = capfd.readouterr().err.strip().splitlines()
        assert info.value.code == 2 and len(lines) == 1, lines
        assert lines[0].startswith(f"has-control {node}: error: ROS refused the arguments: "), lines


# --- 4, 5: bag metadata ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bag0(tmp_path_factory):
    cfg = with_horizon(Config(), 1.2)
    d = tmp_path_factory.mktemp("h3") / "bag0"
    w = BagWriter(d, {PARAMETERS_KEY: parameters_json(cfg)})
    write_trace(w, simulate(cfg), cfg)
    w.close()
    return d


def _edited(bag0, tmp_path, edit):
    d = tmp_path / "bag"
    shutil.copytree(bag0, d)
    doc = yaml.safe_load((d / "metadata.yaml").read_text())
    edit(doc["rosbag2_bagfile_information"])
    (d / "metadata.yaml").write_text(yaml.safe_dump(doc, width=10**9))
    return d


@pytest.mark.parametrize("value, why", [
    ("[1, 2]", "not an array"), ("5", "not a number"), ('"abc"', "not a string"), ("null", "not null"),
    ("[" * 100_000 + "]" * 100_000, "nested deeper"), ('{"a": {"b": 1}}', "a value or a list"),
    ("{", "not JSON"),
])
def test_stored_parameters_that_are_not_an_object_are_one_line(bag0, tmp_path, capsys, value, why):
    d = _edited(bag0, tmp_path, lambda info: info["custom_data"].__setitem__(PARAMETERS_KEY, value))
    one_line(capsys, ["score", d], str(d), PARAMETERS_KEY, why, warnings=True)   # and: "differs from the MCAP's"
    assert main(["bag-info", str(d)]) == 0
    assert f"{PARAMETERS_KEY} (invalid: " in capsys.readouterr().out


@pytest.mark.parametrize("custom", [[1, 2], "abc", {"k": [1, 2]}, {"k": {"a": 1}}])
def test_custom_data_that_is_not_a_map_of_strings_is_one_line(bag0, tmp_path, capsys, custom):
    d = _edited(bag0, tmp_path, lambda info: info.__setitem__("custom_data", custom))
    for cmd in ("score", "bag-info"):
        one_line(capsys, [cmd, d], "metadata.yaml: custom_data", warnings=True)


@pytest.mark.ros
def test_replay_refuses_a_step_that_does_not_fit_the_recorded_stamps_up_front(bag0, tmp_path):
    from has_control.nodes.replay import replay_controller

    def other_step(info):
        flat = json.loads(info["custom_data"][PARAMETERS_KEY])
        flat["simulation.step"] = 7e-4
        info["custom_data"][PARAMETERS_KEY] = json.dumps(flat)
    d = _edited(bag0, tmp_path, other_step)
    with pytest.raises(BagError, match=r"off the grid of simulation.step = 0.0007 s") as info:
        replay_controller(d, context=object())          # refused before any node: the context is never used
    assert "\n" not in str(info.value)


# --- 6, 13: scenario files ------------------------------------------------------------------------

@pytest.mark.parametrize("text, culprit", [
    ("random: {count: 3, ranges: {plant.mass: [-1.0e308, 1.0e308]}}\n", "random.ranges.plant.mass"),
    ("scenarios:\n  a: {plant.mass: 1500.0, plant: {mass: 1600.0}}\n", "scenario a: plant.mass: given twice"),
    ("random: {count: 2, ranges: {plant.mass: [1.0, 2.0], plant: {mass: [3.0, 4.0]}}}\n", "plant.mass: given twice"),
])
def test_scenario_files_that_overflow_or_say_a_key_twice_are_one_line(tmp_path, capsys, text, culprit):
    p = tmp_path / "s.yaml"
    p.write_text(text)
    one_line(capsys, ["robustness", "--gains", 400, 400, 400, "--duration", 1.2, "--scenarios", p], p, culprit)
    one_line(capsys, ["tune", "--duration", 1.2, "--scenarios", p], p, culprit)


@pytest.mark.ros
def test_every_front_end_checks_scenarios_and_aggregate_alike(tmp_path, capsys, context):
    from rclpy.parameter import Parameter

    from has_control.nodes.tuner_node import TunerNode
    p = tmp_path / "s.yaml"
    p.write_text(NOM)
    one_line(capsys, ["tune", "--scenarios", p, "--aggregate", ""], "--aggregate", "expected mean, max or cvar")
    one_line(capsys, ["robustness", "--gains", 400, 400, 400, "--scenarios", p, "--aggregate", ""], "aggregate ''")
    one_line(capsys, ["tune", "--aggregate", "max"], "--aggregate max: needs --scenarios")
    for params, why in (([Parameter("aggregate", value="garbage")], "parameter aggregate"),
                        ([Parameter("aggregate", value="max")], "needs parameter scenarios"),
                        ([Parameter("scenarios", value=str(p)), Parameter("aggregate", value="")],
                         "parameter aggregate")):
        with pytest.raises(ConfigError, match=why):
            TunerNode(context=context, parameter_overrides=params)


# --- 7: roads -------------------------------------------------------------------------------------

def _direct_sum(ref, ep):
    """The road as the docstring writes it: one component at a time."""
    from has_control.core.road import road_components
    n = ep.samples
    f, a, phi = road_components(ref, n * ep.step)
    t = np.arange(n) * ep.step
    out = np.zeros((n, 4))
    out[:, 0] = ref.offset
    for fk, ak, pk in zip(f, a, phi):
        w = 2 * math.pi * fk
        s, c = np.sin(w * t + pk), np.cos(w * t + pk)
        out[:, 0] += ak * (s - math.sin(pk))
        out[:, 1:] += np.column_stack([ak * w * c, -ak * w * w * s, -ak * w ** 3 * c])
    return out


@pytest.mark.parametrize("cutoff, road_class", [(2.0, "C"), (50.0, "A"), (1600.0, "E")])
def test_the_road_table_is_the_sum_of_its_components(cutoff, road_class):
    from has_control.core.road import road_table
    ep = Episode(horizon=1.5)
    ref = Reference(kind="road", road_class=road_class, cutoff=cutoff, seed=5, offset=0.02)
    fast, slow = road_table(ref, ep), _direct_sum(ref, ep)
    assert fast[0, 0] == ref.offset
    for d in range(4):
        assert np.max(np.abs(fast[:, d] - slow[:, d])) <= 1e-9 * np.max(np.abs(slow[:, d]))


def test_road_memory_beyond_the_limit_is_refused_before_any_table(tmp_path, capsys, monkeypatch):
    import has_control.core.reference as reference
    from has_control.core.road import MAX_ROAD_BYTES, SUM_TERMS_MAX, road_terms
    built = []
    monkeypatch.setattr(reference, "road_array", lambda *a: built.append(a) or pytest.fail("built a road"))
    assert road_terms(Reference(kind="road", cutoff=50.0), Episode()) > SUM_TERMS_MAX         # tabulated
    count = MAX_ROAD_BYTES // (32 * Episode().samples) + 2                   # 10 s roads just past the limit
    p = tmp_path / "roads.yaml"
    p.write_text("scenarios:\n" + "".join(f"  r{i}: {{reference: {{kind: road, cutoff: 50.0, seed: {i}}}}}\n"
                                          for i in range(count)))
    one_line(capsys, ["robustness", "--gains", 400, 400, 400, "--scenarios", p], p, "MiB of tables",
             "limit of 1,024 MiB")
    with pytest.raises(ConfigError, match="limit of 1,024 MiB"):
        evaluate_configs([[400.0, 400.0, 400.0]], [Config(reference=Reference(kind="road", cutoff=50.0, seed=i))
                                                   for i in range(count)])
    assert built == []


def test_a_road_at_the_shipped_cutoff_costs_about_what_a_sine_does_in_memory():
    """Summed in the kernel, a 10 s road at the shipped 2 Hz cutoff holds a few
    hundred bytes (a table would hold 1 MiB), and 100 of them cost about what
    100 sine scenarios do to evaluate (issue: at most ~10x)."""
    import tracemalloc

    from has_control.core.reference import reference_array
    ep = Episode()
    road = reference_array(Reference(kind="road", seed=1), ep)
    assert road.nbytes <= 10 * reference_array(Reference(), ep).nbytes < 32 * ep.samples
    gains = np.full((4, 3), 400.0)
    sines = [Config(reference=Reference(omega=2.0 + 1e-3 * i)) for i in range(100)]
    roads = [Config(reference=Reference(kind="road", seed=7000 + i)) for i in range(100)]
    evaluate_configs(gains, sines[:1] + roads[:1])                             # compile / load the cache

    def peak(cfgs):
        tracemalloc.start()
        try:
            evaluate_configs(gains, cfgs)
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert peak(roads[1:]) <= 2 * peak(sines[1:])
    many = [(Reference(kind="road", seed=i), ep) for i in range(10_000)]      # the scenario limit: accepted
    check_road_memory(many)


@pytest.mark.parametrize("cutoff", [2.0, 50.0])
def test_road_bytes_are_what_the_road_array_holds(cutoff):
    from has_control.core.road import road_array, road_bytes
    ref, ep = Reference(kind="road", cutoff=cutoff, seed=3), Episode()
    assert road_array(ref, ep).nbytes == 8 * N_REFERENCE + road_bytes(ref, ep)
    assert road_bytes(Reference(), ep) == 0


def test_the_summed_road_is_the_tabulated_one(monkeypatch):
    """The two ways a road is held give the same road: the kernel's sum
    against the inverse FFT's table, forced by lowering the threshold."""
    import has_control.core.road as road
    ep = Episode(horizon=3.0)
    ref = Reference(kind="road", road_class="B", cutoff=8.0, seed=11, offset=-0.01)
    summed = road.road_table(ref, ep)
    assert road.road_array(ref, ep)[REF_TERMS] == road.road_terms(ref, ep) > 0
    monkeypatch.setattr(road, "SUM_TERMS_MAX", 0)
    assert road.road_array(ref, ep)[REF_TERMS] == -1
    table = road.road_table(ref, ep)
    assert summed[0, 0] == table[0, 0] == ref.offset
    for d in range(4):
        assert np.max(np.abs(summed[:, d] - table[:, d])) <= 1e-12 * np.max(np.abs(table[:, d]))


def test_the_road_cache_holds_more_than_32_roads():
    from has_control.core.reference import road_cached
    cfgs = [with_horizon(Config(reference=Reference(kind="road", seed=1000 + i)), 1.2) for i in range(40)]
    evaluate_configs([[400.0, 400.0, 400.0]], cfgs)
    assert all(road_cached(c.reference, c.episode) for c in cfgs)


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


# --- 8: sessions ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def session3(tmp_path_factory):
    """A session of 3 iterations of 4 particles, stopped (bag closed) after 2."""
    return stopped_session(tmp_path_factory.mktemp("sessions") / "s", particles=4, iterations=3)


def _rewrite(src, dst, topic, index, edit, copy=False):
    """A copy of the session ``src`` in ``dst`` with message ``index`` of
    ``topic`` (a JSON object) edited by ``edit`` (returning an object or JSON
    text), its CRCs valid: as a hand edit would leave it."""
    from has_control.bag import STRING, QosSpec
    from has_control.tuning.session import ITERATION, RESULT, SESSION, SETTINGS, SWARM, _json, _string
    bag = read_bag(src / SESSION)
    if copy:
        shutil.copytree(src, dst)
        shutil.rmtree(dst / SESSION)
    else:
        dst.mkdir()
    w = BagWriter(dst / SESSION, dict(bag.custom_data))
    for t in (SETTINGS, ITERATION, SWARM, RESULT):
        w.add_topic(t, STRING, QosSpec(depth=10, transient_local=t == SETTINGS))
    seen = {}
    for t_ns, t, data in sorted((t_ns, t, data) for t in (SETTINGS, ITERATION, SWARM, RESULT)
                                for t_ns, data in bag.messages.get(t, [])):
        i = seen[t] = seen.get(t, -1) + 1
        if t == topic and i == index:
            new = edit(_json(data))
            data = _string(new if isinstance(new, str) else json.dumps(new))
        w.write(t, t_ns, data)
    w.close()
    return dst


def _deep(n=100_000):
    return "[" * n + "]" * n


@pytest.mark.parametrize("edit, culprit", [
    (lambda s: dict(s, parameters=[1, 2]), "parameters = [1, 2]"),
    (lambda s: dict(s, parameters="abc"), "parameters = 'abc'"),
    (lambda s: dict(s, tuning=dict(s["tuning"], seed=-1)), "swarm.seed"),
    (lambda s: dict(s, tuning=dict(s["tuning"], lower=[-5.0, 150.0, 150.0])), "swarm.lower"),
    (lambda s: dict(s, tuning=dict(s["tuning"], particles=6)), "'particles': unknown key"),
    (lambda s: dict(s, tuning=dict(s["tuning"], scenarios=[{"name": "a", "overrides": {"adaptation.gain": 1.0}}],
                                   aggregate="mean")), "adaptation.gain"),
    (lambda s: dict(s, tuning=dict(s["tuning"], scenarios=[{"name": "a", "overrides": {}}], aggregate="")),
     "aggregate"),
    (lambda s: dict(s, evaluator=["x"]), "evaluator"),
    (lambda s: json.dumps(dict(s, parameters="DEEP")).replace('"DEEP"', _deep()), "no readable"),
])
def test_hand_edited_session_settings_are_one_line(session3, tmp_path, capsys, edit, culprit):
    from has_control.tuning.session import SETTINGS
    d = _rewrite(session3, tmp_path / "s", SETTINGS, 0, edit)
    one_line(capsys, ["tune", "--resume", d], culprit, "cannot resume")


@pytest.mark.parametrize("topic, edit", [
    ("/tuner/swarm", lambda x: dict(x, x=x["x"][:2], v=x["v"][:2], pbest_x=x["pbest_x"][:2],
                                    pbest_f=x["pbest_f"][:2])),              # 2 particles in a swarm of 4
    ("/tuner/swarm", lambda x: dict(x, seed=-1)),
    ("/tuner/swarm", lambda x: dict(x, settings=dict(x["settings"], particles=2))),
    ("/tuner/iteration", lambda r: dict(r, positions=r["positions"][:2], costs=r["costs"][:2])),
    ("/tuner/iteration", lambda r: json.dumps(dict(r, costs="DEEP")).replace('"DEEP"', _deep())),
])
@pytest.mark.system
def test_stored_iterations_that_do_not_fit_the_session_are_damaged_ones(session3, tmp_path, capsys, topic, edit):
    d = _rewrite(session3, tmp_path / "s", topic, 1, edit)           # the second iteration's
    rc = main(["tune", "--resume", str(d), "--json"])
    err = capsys.readouterr().err
    assert rc == 0 and "Traceback" not in err, err
    assert "resuming from iteration 1, the last good one" in err, err


@pytest.mark.system
def test_a_stored_result_without_its_keys_is_not_used(tmp_path, capsys):
    from has_control.tuning.session import RESULT, RESULT_FILE
    done = tmp_path / "done"
    assert main(["tune", "--variant", "pso-cp-tvac",
                 "--particles", "2", "--iterations", "2", "--duration", "1.2", "--out", str(done)]) == 0
    (done / RESULT_FILE).unlink()
    d = _rewrite(done, tmp_path / "s", RESULT, 0, lambda r: {}, copy=True)
    capsys.readouterr()
    rc = main(["tune", "--resume", str(d), "--json"])
    cap = capsys.readouterr()
    assert rc == 0 and "Traceback" not in cap.err, cap.err
    assert json.loads(cap.out)["variant"] and (d / RESULT_FILE).exists()
