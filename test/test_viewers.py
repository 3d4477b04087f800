"""Viewers that show the run, and a live view whose viewer failing costs nothing.

The shipped Foxglove layout reads only channels the live view serves (the run
topics, each Float64MultiArray topic by name on ``TOPIC/named``, ``/diagnostics``),
with header-stamp time and one scale per axis; every one of its panels receives
data from ``stack --foxglove``, read by a WebSocket client. The PlotJuggler
layout names the controller's columns. Killing the viewer process keeps the
run's result; the rings have no name in /dev/shm; Ctrl-C is one line."""
import asyncio
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from has_control.nodes.foxglove import NAMED, _COLUMNS
from has_control.wire.topics import (CONTROLLER_STATE, CONTROLLER_STATE_COLUMNS, GAINS, GAINS_COLUMNS, RUN_TOPICS,
                                     STATE_NAMES)
from test_foxglove import _connect, _message_data

pytestmark = [pytest.mark.ros]

ROOT = Path(__file__).resolve().parent.parent
FOXGLOVE_LAYOUT = ROOT / "config/foxglove/has_control.json"
PLOTJUGGLER_LAYOUT = ROOT / "config/plotjuggler/has_control.xml"
JOINT_FIELDS = {"position": 3, "velocity": 3, "effort": 3}


def _served() -> dict[str, str]:
    """{channel: what it carries} as ``stack --foxglove`` serves it in the root namespace."""
    out = {f"/{rel}": "joint_state" if ty.endswith("JointState") else "cdr" for rel, ty in RUN_TOPICS.items()}
    out.update({f"/{rel}{NAMED}": "named" for rel in RUN_TOPICS if rel.rsplit("/", 1)[-1] in _COLUMNS})
    out["/diagnostics"] = "diagnostics"
    return out


def _path(value: str) -> tuple[str, str, int | None]:
    """A Foxglove message path ``/topic.field[i]`` -> (topic, field, index or None)."""
    m = re.fullmatch(r"(/[A-Za-z0-9_/]+)\.([A-Za-z0-9_]+)(?:\[(\d+)\])?", value)
    assert m, value
    return m.group(1), m.group(2), None if m.group(3) is None else int(m.group(3))


def _panels() -> dict[str, list]:
    """{panel id: [(topic, field, index), ...]}; a diagnostics panel reads its topic whole."""
    layout = json.loads(FOXGLOVE_LAYOUT.read_text())
    out = {}
    for pid, panel in layout["configById"].items():
        if pid.startswith("Plot!"):
            out[pid] = [_path(p["value"]) for p in panel["paths"]]
        else:
            out[pid] = [(panel["topicToRender"], None, None)]
    return out


def test_the_foxglove_layout_reads_only_what_the_live_view_serves():
    """Every panel a Plot of existing named fields or a diagnostics summary of a
    served channel; no Parameters panel (the server has no parameters capability);
    header-stamp time; a unit in every label; the controller's columns by name."""
    layout = json.loads(FOXGLOVE_LAYOUT.read_text())
    served = _served()
    kinds = {pid.split("!")[0] for pid in layout["configById"]}
    assert kinds == {"Plot", "DiagnosticSummary"}                  # no Parameters, no unknown panel
    named = set()
    for pid, reads in _panels().items():
        for topic, field, index in reads:
            assert topic in served, (pid, topic)
            if served[topic] == "joint_state":
                assert field in JOINT_FIELDS and index is not None and index < JOINT_FIELDS[field]
            elif served[topic] == "named":
                rel = topic.removesuffix(NAMED).rsplit("/", 1)[-1]
                assert field in _COLUMNS[rel] and index is None
                named.add(field)
            else:
                assert served[topic] == "diagnostics" and pid.startswith("DiagnosticSummary!")
    for panel in layout["configById"].values():
        for p in panel.get("paths", []):
            assert p["timestampMethod"] == "headerStamp" and "[" in p["label"]
    assert {"e1", "x1d", "a1_hat", "a2_hat"} <= named and "data" not in json.dumps(layout)
    # e1 (µm) apart from y (0.1 m); â1 (~2.6e3) apart from â2 (~4e-12)
    for reads in _panels().values():
        fields = {f for _, f, _ in reads}
        assert not ({"e1"} <= fields and fields & {"x1d", "position"})
        assert not {"a1_hat", "a2_hat"} <= fields


def test_the_plotjuggler_layout_names_the_controller_columns_from_topics_that_exist():
    root = ET.parse(PLOTJUGGLER_LAYOUT).getroot()
    topics = {t.get("name") for t in root.iter("topic")}
    assert topics <= {f"/{rel}" for rel in RUN_TOPICS} and {"/state", "/controller/controller_state"} <= topics
    snippets = {s.get("name"): s.findtext("linked_source") for s in root.iter("snippet")}
    columns = {"/controller/controller_state": CONTROLLER_STATE_COLUMNS, "/controller/gains": GAINS_COLUMNS}
    for name, source in snippets.items():
        topic, index = re.fullmatch(r"(/\S+)/data\[(\d+)\]", source).groups()
        assert topic in topics and name.split(" ")[0] == columns[topic][int(index)], (name, source)
    curves = {c.get("name") for c in root.iter("curve")}
    joints = {f"/state/{j}/{f}" for j in STATE_NAMES for f in JOINT_FIELDS} | {"/command/valve/position"}
    assert curves and all(c in snippets or c in joints for c in curves), curves - set(snippets) - joints
    assert {"e1", "x1d", "a1_hat", "a2_hat"} <= {c.split(" ")[0] for c in curves}       # plotted by name


def _stack(port: int, domain_id: int, *extra, stdout=subprocess.PIPE):
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    return subprocess.Popen([sys.executable, "-m", "has_control.cli", "stack", "--foxglove", str(port), *extra],
                            env=env, stdout=stdout, stderr=subprocess.PIPE, text=True)


async def _read_every_panel(port: int, timeout: float) -> dict:
    """Subscribe to every channel the layout reads as it is advertised; collect
    {topic: [(log time, decoded)]} until each has messages or the run ends."""
    wanted = {topic for reads in _panels().values() for topic, _, _ in reads}
    kinds = _served()
    deadline = time.monotonic() + timeout
    got: dict[str, list] = {t: [] for t in wanted}
    info = {}
    async with await _connect(port, deadline) as ws:
        subs, next_id = {}, 1
        try:
            while min(len(v) for v in got.values()) < 3:
                msg = await asyncio.wait_for(ws.recv(), max(deadline - time.monotonic(), 0.01))
                if isinstance(msg, str):
                    m = json.loads(msg)
                    if m["op"] == "serverInfo":
                        info = m
                    elif m["op"] == "advertise":
                        for c in m["channels"]:
                            if c["topic"] in wanted and c["topic"] not in subs.values():
                                subs[next_id] = c["topic"]
                                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                                    {"id": next_id, "channelId": c["id"]}]}))
                                next_id += 1
                    continue
                sub, log_time, payload = _message_data(msg)
                topic = subs[sub]
                if kinds[topic] == "joint_state":
                    decoded = deserialize_message(payload, JointState)
                elif kinds[topic] == "named":
                    decoded = json.loads(payload)
                else:
                    decoded = payload
                got[topic].append((log_time, decoded))
        except Exception:           # noqa: BLE001  the run ended (server closed) or the time is up: judge what came
            pass
    return {"info": info, "got": got}


def _values(messages, field, index):
    out = []
    for _, m in messages:
        if isinstance(m, dict):
            out.append(m[field])
        else:
            out.append(list(getattr(m, field))[index])
    return out


def test_every_panel_of_the_shipped_layout_receives_data_from_stack_foxglove(domain_id):
    port = free_port()
    stack = _stack(port, domain_id, "--duration", "20", "--foxglove-wait", "90")   # several wall seconds of reports
    try:
        read = asyncio.run(_read_every_panel(port, 150))
        out, err = stack.communicate(timeout=120)
    finally:
        stack.kill()
    assert stack.returncode == 0, err
    caps = read["info"].get("capabilities", [])
    assert "parameters" not in caps and "parametersSubscribe" not in caps   # so the layout has no Parameters panel
    got = read["got"]
    for pid, reads in _panels().items():
        for topic, field, index in reads:
            assert got[topic], (pid, topic, "no data")
            if field is None:
                continue
            values = _values(got[topic], field, index)
            assert all(v is not None and math.isfinite(v) for v in values), (pid, topic, field)
    for topic, messages in got.items():
        if topic.endswith(NAMED):                     # header-stamp time = the log time = the sample's time t
            for log_time, m in messages:
                stamp = m["header"]["stamp"]
                assert stamp["sec"] * 10**9 + stamp["nsec"] == log_time
                assert abs(m["t"] - log_time / 1e9) < 1e-9
    # one scale per axis: the series of a panel within three decades of each other
    for pid, reads in _panels().items():
        scales = [np.median(np.abs(_values(got[t], f, i))) for t, f, i in reads if f is not None]
        scales = [s for s in scales if s > 0]
        if len(scales) > 1:
            assert max(scales) / min(scales) < 1e3, (pid, scales)
    state = f"/{CONTROLLER_STATE}{NAMED}"
    assert got[state][0][1]["x1d"] is not None and got[f"/{GAINS}{NAMED}"][0][1]["k1"] > 0


def _viewer_pid(stack_pid: int) -> int:
    for task in Path(f"/proc/{stack_pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            if b"has_control.nodes.live_process" in Path(f"/proc/{child}/cmdline").read_bytes():
                return int(child)
    raise AssertionError("no viewer process")


def _wait_serving(stack) -> None:
    line = stack.stdout.readline()
    assert line.startswith("serving live on"), line


def test_a_killed_viewer_costs_the_run_nothing_and_no_ring_has_a_name(domain_id):
    """SIGKILL to the viewer mid-run: exit 0, the JSON result, one warning line;
    the rings are memfd (nothing under /dev/shm in either process's maps)."""
    port = free_port()
    stack = _stack(port, domain_id, "--duration", "8", "--json")
    try:
        _wait_serving(stack)
        viewer = _viewer_pid(stack.pid)
        maps = Path(f"/proc/{stack.pid}/maps").read_text() + Path(f"/proc/{viewer}/maps").read_text()
        assert "has_control_live" not in maps.replace("/memfd:has_control_live (deleted)", "")   # no file by name
        assert maps.count("/memfd:has_control_live (deleted)") >= 4         # both rings in both processes
        time.sleep(1.0)
        os.kill(viewer, signal.SIGKILL)
        out, err = stack.communicate(timeout=120)
    finally:
        stack.kill()
    assert stack.returncode == 0, err
    result = json.loads(out.strip().splitlines()[-1])
    assert result["samples"] == 26667 and math.isfinite(result["J"])
    assert err.strip().splitlines() == [
        "live view: the live view's viewer process ended early (signal 9); the run went on without it"], err


def test_a_killed_stack_takes_its_viewer_and_leaves_no_shared_memory(domain_id):
    port = free_port()
    stack = _stack(port, domain_id, "--duration", "60")
    try:
        _wait_serving(stack)
        viewer = _viewer_pid(stack.pid)
        os.kill(stack.pid, signal.SIGKILL)
        stack.wait(timeout=30)
        end = time.monotonic() + 20
        while Path(f"/proc/{viewer}").exists() and time.monotonic() < end:
            try:                                          # reap nothing: it is not our child; just wait it out
                if Path(f"/proc/{viewer}/stat").read_text().split()[2] == "Z":
                    break
            except OSError:
                break
            time.sleep(0.1)
        alive = Path(f"/proc/{viewer}/stat").exists() and Path(f"/proc/{viewer}/stat").read_text().split()[2] != "Z"
        assert not alive, "the viewer outlived its stack"
    finally:
        stack.kill()


def test_ctrl_c_during_a_served_stack_is_one_line_and_130(domain_id):
    """SIGINT to the stack's process group (as a terminal sends it) mid-run: the viewer
    is in a session of its own, the stack closes it: "interrupted", 130."""
    port = free_port()
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    stack = subprocess.Popen([sys.executable, "-m", "has_control.cli", "stack", "--duration", "60", "--foxglove",
                              str(port)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)
    try:
        _wait_serving(stack)
        time.sleep(2.0)
        os.killpg(stack.pid, signal.SIGINT)
        out, err = stack.communicate(timeout=120)
    finally:
        stack.kill()
    assert stack.returncode == 130 and err.strip().splitlines() == ["has-control: interrupted"], err
