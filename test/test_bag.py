"""MCAP bags: what the recorder writes, scoring from it, other readers, bad files, replay."""
import json
import shutil
import struct
import threading
import time

import numpy as np
import pytest
from conftest import cli, one_line, run_main
import rclpy
import yaml

from has_control.wire import cdr
from has_control.bag import (PARAMETERS_KEY, BagError, BagWriter, parameters_json, read_bag, score_bag, typestore,
                             write_trace)
from has_control.cli import main
from has_control.config import build_config, with_horizon
from has_control.core.episode import simulate
from has_control.core.params import Config

HORIZON = 1.5
N = 5000


# ``recorded``: conftest's one recorded run of the session (1.5 s, HORIZON) and its StackRun.


def test_one_state_and_one_command_per_sample(recorded):
    d, _, run = recorded
    bag = read_bag(d)
    assert bag.complete
    counts = {t: bag.count(t) for t in bag.types}
    assert counts == {"/state": N, "/command": N, "/clock": N, "/controller/reference": N,
                      "/controller/controller_state": N, "/controller/gains": 1}
    stamps = cdr.stamps_ns([m for _, m in bag.messages["/state"]])
    np.testing.assert_array_equal(stamps, np.arange(N) * 300_000)
    np.testing.assert_array_equal([t for t, _ in bag.messages["/state"]], stamps)  # log time = sim time


def test_the_bag_is_rosbag2_mcap_as_ros2_bag_writes_it(recorded):
    from mcap.reader import make_reader
    d, _, _ = recorded
    meta = yaml.safe_load((d / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == ["run.mcap"] and meta["message_count"] == 5 * N + 1
    qos = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
           for t in meta["topics_with_message_count"]}
    assert qos["/state"][0]["reliability"] == "reliable" and qos["/state"][0]["depth"] == 1
    assert qos["/controller/gains"][0]["durability"] == "transient_local"
    with open(d / "run.mcap", "rb") as f:
        reader = make_reader(f)
        header, summary = reader.get_header(), reader.get_summary()
    assert header.profile == "ros2"
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert all("offered_qos_profiles" in c.metadata for c in summary.channels.values())
    assert {ci.compression for ci in summary.chunk_indexes} == {"zstd"}


def test_score_from_the_bag_equals_the_in_process_score(recorded):
    d, cfg, run = recorded
    score, rec = score_bag(d)
    ref = simulate(cfg)
    assert score == ref.score == run.score                 # every field, bit for bit
    np.testing.assert_array_equal(rec.u, ref["u"])
    np.testing.assert_array_equal(rec.y, ref["y"])


@pytest.mark.system
def test_cli_score_and_bag_info(recorded, tmp_path):
    d, _, _ = recorded
    r = cli("score", d, "--json")
    assert r.returncode == 0, r.stderr
    s = cli("simulate", "--duration", HORIZON, "--json")
    assert json.loads(r.stdout) == json.loads(s.stdout)
    info = cli("bag-info", d)
    assert info.returncode == 0, info.stderr
    for topic in ("/state", "/command", "/clock", "/controller/reference", "/controller/gains"):
        assert f"Topic: {topic} " in info.stdout
    assert f"Count: {N}" in info.stdout and "Duration:          1.499700 s" in info.stdout


def test_the_summary_counts_are_the_messages_other_readers_count(recorded, tmp_path):
    """What the readers' length check reads up front (the summary's Statistics)
    is what the mcap package counts; an unfinished file has no summary."""
    from mcap.reader import make_reader
    from has_control.bag.read import summary_message_counts
    f = recorded[0] / "run.mcap"
    with open(f, "rb") as stream:
        summary = make_reader(stream).get_summary()
    want = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    assert summary_message_counts(f) == want and want["/state"] == N
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(f.read_bytes()[:-100])
    assert summary_message_counts(torn) == {}


def test_other_readers_decode_every_message(recorded):
    """rosbags' AnyReader and mcap_ros2's reader agree with the in-process trace."""
    from mcap_ros2.reader import read_ros2_messages
    from rosbags.highlevel import AnyReader
    d, cfg, _ = recorded
    ref = simulate(cfg)
    counts, ys, us = {}, [], []
    with AnyReader([d], default_typestore=typestore()) as reader:
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            if conn.topic == "/state":
                ys.append(msg.position[0])
            elif conn.topic == "/command":
                us.append(msg.position[0])
    assert counts["/state"] == counts["/command"] == N
    np.testing.assert_array_equal(ys, ref["y"])
    np.testing.assert_array_equal(us, ref["u"])
    e1 = []
    total = 0
    for m in read_ros2_messages(str(d / "run.mcap")):
        total += 1
        if m.channel.topic == "/controller/controller_state":
            e1.append(m.ros_msg.data[1])
    assert total == 5 * N + 1
    np.testing.assert_array_equal(e1, ref["e1"])


def test_encoded_trace_messages_equal_rosbags_serialisation():
    ts = typestore()
    js = ts.types["sensor_msgs/msg/JointState"]
    header = ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=3, nanosec=300000),
                                             frame_id="")
    m = js(header=header, name=["actuator", "chamber_1", "chamber_2"], position=np.array([1.0, 2.0, 3.0]),
           velocity=np.array([4.0, 5.0, 6.0]), effort=np.array([7.0, 8.0, 9.0]))
    mine = cdr.encode_joint_states([3_000_300_000], ["actuator", "chamber_1", "chamber_2"],
                                   [[1.0, 2, 3]], [[4.0, 5, 6]], [[7.0, 8, 9]])[0]
    assert mine == bytes(ts.serialize_cdr(m, "sensor_msgs/msg/JointState"))
    f = ts.types["std_msgs/msg/Float64MultiArray"](
        layout=ts.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0), data=np.array([0.5, 1.0]))
    assert cdr.encode_float64_arrays([[0.5, 1.0]])[0] == bytes(ts.serialize_cdr(f, "std_msgs/msg/Float64MultiArray"))


# --- bad files -----------------------------------------------------------------

def test_a_bare_mcap_file_is_accepted(recorded):
    d, _, run = recorded
    score, _ = score_bag(d / "run.mcap")
    assert score == run.score


def test_truncated_bag_yields_complete_chunks_with_a_warning(recorded, tmp_path):
    d, _, _ = recorded
    cut = tmp_path / "cut"
    cut.mkdir()
    data = (d / "run.mcap").read_bytes()
    (cut / "cut.mcap").write_bytes(data[: len(data) // 2])          # recorder killed: no metadata.yaml
    warnings = []
    bag = read_bag(cut, on_warning=warnings.append)
    assert not bag.complete and bag.lost_bytes > 0
    assert any("no metadata.yaml" in w for w in warnings)
    assert any("truncated" in w and "lost the last" in w for w in warnings)
    n = bag.count("/state")
    assert 0 < n < N
    np.testing.assert_array_equal(cdr.stamps_ns([m for _, m in bag.messages["/state"]]),
                                  np.arange(n) * 300_000)             # a prefix, in order
    r = cli("bag-info", cut)
    assert r.returncode == 0 and "truncated" in r.stderr and "Complete:          no" in r.stdout
    r = cli("score", cut)
    assert r.returncode == 2 and r.stderr.count("\n") <= 4 and "incomplete" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("case", ["not-mcap", "bad-yaml", "no-topics", "missing"])
def test_bad_files_get_one_line_naming_the_file(recorded, tmp_path, case, capsys):
    d, _, _ = recorded
    if case == "not-mcap":
        target = tmp_path / "x.mcap"
        target.write_text("this is not a bag\n")
        expect = "not an MCAP file"
    elif case == "bad-yaml":
        target = tmp_path / "bag"
        target.mkdir()
        (target / "bag.mcap").write_bytes((d / "run.mcap").read_bytes())
        (target / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
        expect = "metadata.yaml: malformed YAML"
    elif case == "no-topics":
        from has_control.bag import BagWriter
        target = tmp_path / "clock_only"
        with BagWriter(target) as w:
            w.add_topic("/clock", "rosgraph_msgs/msg/Clock")
            w.write("/clock", 0, cdr.encode_float64_arrays([[0.0]])[0])
        expect = "no '…/state'"
    else:
        target = tmp_path / "nothing"
        expect = "no such bag"
    r = run_main(capsys, "score", target)
    assert r.returncode == 2
    err = [line for line in r.stderr.splitlines() if line.startswith("has-control: error")]
    assert len(err) == 1 and str(target) in err[0] and expect in err[0], r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.ros
def test_the_recorder_never_overwrites(recorded, capsys):
    d, _, _ = recorded
    r = run_main(capsys, "stack", "--duration", HORIZON, "--record", d)
    assert r.returncode == 2 and "exists already" in r.stderr


# --- replay ----------------------------------------------------------------------

@pytest.mark.ros
def test_replay_to_this_codes_controller_matches_bit_for_bit(recorded, domain_id):
    d, _, _ = recorded
    r = cli("replay", d, "--check-code", domain=domain_id)
    assert r.returncode == 0, r.stderr
    assert (f"replayed {N} states to an in-process controller built from the bag's parameters: 0 mismatches, "
            "max |du| = 0.000e+00 m") in r.stdout


def _with_parameters(src, dst, **changes):
    """A copy of bag ``src`` whose stored parameters differ by ``changes``."""
    meta = yaml.safe_load((src / "metadata.yaml").read_text())
    custom = meta["rosbag2_bagfile_information"]["custom_data"]
    params = json.loads(custom["has_control/parameters"])
    params.update({k.replace("__", "."): v for k, v in changes.items()})
    custom["has_control/parameters"] = json.dumps(params)
    dst.mkdir()
    (dst / "run.mcap").write_bytes((src / "run.mcap").read_bytes())
    (dst / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return dst


@pytest.mark.ros
def test_replay_with_a_changed_controller_reports_mismatches(recorded, tmp_path, domain_id):
    from has_control.nodes.replay import replay_controller
    d, _, _ = recorded
    # the gains topic says 150: the controller runs with the gains in force then, so no mismatch ...
    same = _with_parameters(d, tmp_path / "same", gains__k1=151.0)
    # ... but a changed adaptation law does mismatch
    changed = _with_parameters(d, tmp_path / "changed", adaptation__gain=[96000.0, 1e-49])
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    try:
        assert replay_controller(same, context=ctx).mismatches == 0
        check = replay_controller(changed, context=ctx)
    finally:
        rclpy.try_shutdown(context=ctx)
    assert check.mismatches > 0 and check.max_abs_diff > 0


@pytest.mark.ros
def test_replay_publishes_clock_that_use_sim_time_nodes_follow(recorded, domain_id):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from has_control.nodes.replay import replay
    d, _, _ = recorded
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    try:
        listener = rclpy.create_node("listener", context=ctx,
                                     parameter_overrides=[Parameter("use_sim_time", value=True)])
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(listener)
        out = {}
        th = threading.Thread(target=lambda: out.setdefault("r", replay(d, rate=5.0, topics=["/clock"],
                                                                        context=ctx, wait_for_subscribers=1.0)))
        th.start()
        while th.is_alive():
            ex.spin_once(timeout_sec=0.01)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
        now = listener.get_clock().now().nanoseconds
        listener.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    count, seconds = out["r"]
    assert count == N and seconds == pytest.approx(HORIZON / 5.0, rel=0.5)
    assert now == (N - 1) * 300_000                          # the last recorded sample time


def test_score_bag_raises_bag_error_for_missing_path(tmp_path):
    with pytest.raises(BagError, match="no such bag"):
        score_bag(tmp_path / "none")


def test_an_edited_or_damaged_metadata_yaml_is_never_used_silently(recorded, tmp_path):
    d, _, _ = recorded
    edited = _with_parameters(d, tmp_path / "edited", gains__k1=151.0)
    said = []
    read_bag(edited, on_warning=said.append)
    assert any("differs from the copy inside the MCAP file" in m and "has_control/parameters" in m for m in said)
    said.clear()
    read_bag(d, on_warning=said.append)
    assert said == []


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
