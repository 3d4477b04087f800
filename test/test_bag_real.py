"""Bags as a machine records them: wall-clock stamps, jitter,
dropped states, the ros2_control layout, a bag of only state and command;
and the one-line refusals (a truncated payload, a conflicting duplicate).

Every derived bag is written from one clean recorded run (a simulated
identification experiment whose plant publishes its sensors' readings on
``/state`` and its true state on ``/true_state``), message bytes rewritten
as the machine would have written them."""
import numpy as np
import pytest

from has_control.bag import BagWriter, PARAMETERS_KEY, parameters_json, read_bag, score_bag, write_trace
from has_control.bag.recorded import TOLERANCE, read_recording
from has_control.bag.series import run_series
from has_control.cli.main import main
from has_control.config import CONFIG_DIR, build_config, load_config
from has_control.core.actuator import joint_state
from has_control.core.cost import score_arrays
from has_control.core.episode import EpisodeArrays, simulate
from has_control.identify.data import experiment_from_bag, measured
from has_control.identify.fit import identify
from has_control.wire import cdr

TRUTH = {"mass": 1720.0, "damping": 3300.0, "bulk_modulus": 5.6e8, "leakage": 4.5e-13, "valve_gain": 3.3e-4,
         "valve_time_constant": 8.0e-4}
SENSORS = {"noise.position": 1e-6, "noise.velocity": 1e-4, "noise.pressure_cap": 1e4, "noise.pressure_rod": 1e4,
           "noise.seed": 11, "noise.added_by": "plant", "plant.valve_limit": 5e-3}
MUST = ("mass", "damping", "bulk_modulus", "valve_gain")
EPOCH = 1_700_000_000 * 10**9            # [ns], a wall clock in 2023
CMD = "/forward_command_controller/commands"


def _quiet(_):
    pass


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """(directory, cfg, trace, readings, types, messages, custom data): the clean 4 s recording."""
    cfg = build_config({**{f"plant.{k}": v for k, v in TRUTH.items()}, **SENSORS, "simulation.horizon": 4.0},
                       base=load_config([CONFIG_DIR / "identify.yaml"]))
    tr = simulate(cfg)
    x = measured(np.column_stack([tr["y"], tr["ydot"], tr["P1"], tr["P2"]]), cfg.noise)
    d = tmp_path_factory.mktemp("real")
    raw = d / "raw"
    w = BagWriter(raw, {PARAMETERS_KEY: parameters_json(cfg)})
    write_trace(w, tr, cfg)
    w.close()
    bag = read_bag(raw)
    msgs = {t: list(m) for t, m in bag.messages.items()}
    types = dict(bag.types)
    msgs["/true_state"], types["/true_state"] = msgs["/state"], types["/state"]
    stamps = np.array([t for t, _ in msgs["/state"]], dtype=np.int64)
    js = joint_state(x[:, 0], x[:, 1], x[:, 2], x[:, 3], cfg.actuator.as_array())
    readings = cdr.encode_joint_states(stamps, ["actuator", "chamber_1", "chamber_2"], np.column_stack(js[0:3]),
                                       np.column_stack(js[3:6]), np.column_stack(js[6:9]))
    msgs["/state"] = list(zip(stamps.tolist(), readings))
    _write(d / "clean", types, msgs, bag.custom_data)
    return d, cfg, tr, x, types, msgs, bag.custom_data


def _write(path, types, msgs, custom):
    w = BagWriter(path, dict(custom))
    for t in msgs:
        w.add_topic(t, types[t])
    w.write_batches({t: (np.array([lt for lt, _ in m], dtype=np.int64), [b for _, b in m])
                     for t, m in msgs.items() if m})
    w.close()
    return path


def _stamp(data: bytes, ns: int) -> bytes:
    """A JointState with header.stamp set to ``ns``."""
    import struct
    return data[:4] + struct.pack("<iI", ns // 10**9, ns % 10**9) + data[12:]


def _stamp_of(data: bytes) -> int:
    return int(cdr.stamps_ns([data])[0])


def _derive(clean, kind):
    d, cfg, tr, x, types, msgs, custom = clean
    types, msgs = dict(types), {t: list(m) for t, m in msgs.items()}
    rng = np.random.default_rng(27)
    stamped = ("/state", "/true_state", "/command")
    if kind == "epoch":
        msgs = {t: [(lt + EPOCH, _stamp(b, _stamp_of(b) + EPOCH) if t in stamped else b) for lt, b in m]
                for t, m in msgs.items()}
    elif kind == "jitter":
        n = len(msgs["/state"])
        jit = rng.uniform(-50e3, 50e3, n).astype(np.int64)       # ±50 µs
        for t in stamped:
            msgs[t] = [(lt, _stamp(b, _stamp_of(b) + int(jit[i]))) for i, (lt, b) in enumerate(msgs[t])]
    elif kind == "dropped":
        n = len(msgs["/state"])
        gone = set(rng.choice(np.arange(1, n), size=n // 100, replace=False).tolist())
        for t in ("/state", "/true_state"):
            msgs[t] = [m for i, m in enumerate(msgs[t]) if i not in gone]
    elif kind == "ros2_control":
        u = cdr.joint_states([b for _, b in msgs["/command"]])[1][:, 0]
        cmds = cdr.encode_float64_arrays(u[:, None])                 # no layout, as forward_command_controller
        keep = {"/joint_states": msgs["/state"],
                CMD: [(lt + 100_000, c) for (lt, _), c in zip(msgs["/command"], cmds)]}   # answered 0.1 ms later
        types = {"/joint_states": types["/state"], CMD: "std_msgs/msg/Float64MultiArray"}
        msgs = keep
    elif kind == "state_command":
        msgs = {t: msgs[t] for t in ("/state", "/command")}
    types = {t: types[t] for t in msgs}
    return _write(d / kind, types, msgs, custom)


@pytest.fixture(scope="module")
def derived(clean):
    return {k: _derive(clean, k) for k in ("epoch", "jitter", "dropped", "ros2_control", "state_command")}


@pytest.fixture(scope="module")
def clean_fit(clean):
    d = clean[0]
    return identify([experiment_from_bag(d / "clean", on_warning=_quiet)])


def _measured_J(clean):
    """J of the readings against the run's reference (what a bag without true_state scores)."""
    _, cfg, tr, x, *_ = clean
    return score_arrays(tr["x1d"] - x[:, 0], tr["u"], EpisodeArrays.from_config(cfg).episode).J


def test_each_derived_bag_reads_the_clean_samples_and_says_what_it_did(clean, derived):
    d, cfg, tr, x, *_ = clean
    for kind, path in derived.items():
        notes = []
        rec = read_recording(read_bag(path, on_warning=notes.append), cfg.episode.step)
        got = rec.x[rec.state]
        ref = x[rec.state[:len(x)]]
        np.testing.assert_array_equal(got, ref, err_msg=kind)          # the same values on the same samples
        np.testing.assert_array_equal(rec.u[rec.command], tr["u"][rec.command[:len(x)]], err_msg=kind)
        text = "\n".join(notes)
        if kind == "epoch":
            assert rec.epoch and rec.samples == len(x) and "not simulation time" in text
        if kind == "jitter":
            assert "each message taken as its nearest sample" in text and rec.samples == len(x)
        if kind == "dropped":
            assert len(rec.dropped) == len(x) // 100 and f"{len(x) // 100} of {len(x)} samples have no state" in text
        if kind == "ros2_control":
            assert rec.layout == "ros2_control" and "the first command logged after state k" in text
            assert rec.command.all()


def test_identify_gives_the_clean_estimates_within_their_intervals(clean, derived, clean_fit):
    ref = clean_fit.estimates
    for kind, path in derived.items():
        warned = []
        res = identify([experiment_from_bag(path, on_warning=warned.append)])
        for k in MUST:
            e = res.estimates[k]
            assert e.lower <= ref[k].value <= e.upper, (kind, k, e, ref[k])
            if kind != "dropped":                   # the same samples: the same numbers
                assert e.value == pytest.approx(ref[k].value, rel=1e-9), (kind, k)
        if kind == "dropped":
            assert res.segments < clean_fit.segments                    # the segments spanning a drop left out
            assert any("leaves out every segment that spans one" in w for w in warned)


def test_score_gives_the_clean_J_or_states_its_policy(clean, derived, capsys):
    J_clean = score_bag(clean[0] / "clean")[0].J
    J_meas = _measured_J(clean)
    for kind, path in derived.items():
        if kind == "dropped":                       # isolated drops: interpolated, said, scored
            assert main(["score", str(path)]) == 0
            err = capsys.readouterr().err.strip()
            assert "samples without a state: each interpolated from its neighbours" in err, err
            score, _ = score_bag(path, on_warning=_quiet)
            assert score.J == pytest.approx(J_clean, rel=1e-4)
            continue
        score, _ = score_bag(path, on_warning=_quiet)
        expect = J_clean if kind in ("epoch", "jitter") else J_meas    # no true_state: the readings are scored
        assert score.J == pytest.approx(expect, rel=1e-9), kind
    assert main(["score", str(derived["state_command"])]) == 0
    err = capsys.readouterr().err
    assert "the reference and the metrics recomputed from has_control/parameters of the bag" in err


def test_plot_accepts_every_derived_bag_and_shows_the_drops_as_gaps(clean, derived, tmp_path, capsys):
    x = clean[3]
    for kind, path in derived.items():
        out = tmp_path / f"{kind}.png"
        assert main(["plot", str(path), "--out", str(out)]) == 0, capsys.readouterr().err
        assert out.read_bytes()[:4] == b"\x89PNG"
    s = run_series(derived["dropped"], on_warning=_quiet)
    assert np.isnan(s.y).sum() == len(x) // 100 and np.isfinite(s.x1d).all()
    s = run_series(derived["state_command"], on_warning=_quiet)
    np.testing.assert_allclose(s.x1d, clean[2]["x1d"], rtol=0, atol=1e-15)   # the reference recomputed


def test_bag_info_says_the_layout_and_the_drops(clean, derived, capsys):
    assert main(["bag-info", str(derived["ros2_control"])]) == 0
    out = capsys.readouterr().out
    assert "Layout:            ros2_control (states /joint_states, commands " + CMD in out
    assert main(["bag-info", str(derived["dropped"])]) == 0
    out = capsys.readouterr().out
    assert f"{len(clean[3]) // 100} dropped" in out


def test_a_ros2_control_bag_with_other_joint_names_is_read_through_state_interfaces(clean, tmp_path, capsys):
    d, cfg, tr, x, types, msgs, custom = clean
    names = ["rod", "cap_side", "rod_side"]
    renamed = [(lt, cdr.encode_joint_states([_stamp_of(b)], names, *cdr.joint_states([b])[1:])[0])
               for lt, b in msgs["/state"]]
    cmds = [(lt + 1, c) for (lt, _), c in zip(msgs["/command"], cdr.encode_float64_arrays(tr["u"][:, None]))]
    path = _write(tmp_path / "renamed", {"/joint_states": types["/state"], "/valve/commands":
                                         "std_msgs/msg/Float64MultiArray"},
                  {"/joint_states": renamed, "/valve/commands": cmds}, custom)
    assert main(["score", str(path)]) == 2                       # the default mapping names joints it lacks
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "actuator/position" in err and "--state-interfaces" in err
    assert main(["score", str(path), "--json", "--state-interfaces", "rod/position", "rod/velocity",
                 "cap_side/effort", "rod_side/effort", "--command-topic", "/valve/commands"]) == 0
    import json
    assert json.loads(capsys.readouterr().out)["J"] == pytest.approx(_measured_J(clean), rel=1e-9)


def _one_line_exit_2(args, capsys, *culprits):
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err and all(c in err for c in culprits), err


def test_a_truncated_payload_is_one_line_naming_the_message(clean, tmp_path, capsys):
    d, cfg, tr, x, types, msgs, custom = clean
    msgs = {t: list(m) for t, m in msgs.items()}
    for t in ("/state", "/true_state"):                # score reads the true state, identify the readings
        lt, b = msgs[t][1234]
        msgs[t][1234] = (lt, b[:-20])
    path = _write(tmp_path / "truncated", types, msgs, custom)
    for cmd in ("score", "plot", "identify"):
        extra = ["--out", str(tmp_path / "t.png")] if cmd == "plot" else []
        _one_line_exit_2([cmd, str(path), *extra], capsys, "state: message 1234: truncated")


def test_a_conflicting_duplicate_is_one_line_naming_the_sample_and_an_identical_one_is_collapsed(
        clean, tmp_path, capsys):
    d, cfg, tr, x, types, msgs, custom = clean
    st = list(msgs["/state"])
    other = cdr.encode_joint_states([_stamp_of(st[500][1])], ["actuator", "chamber_1", "chamber_2"],
                                    np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)))[0]
    bad = {**msgs, "/state": st[:501] + [(st[500][0], other)] + st[501:],
           "/true_state": st[:501] + [(st[500][0], other)] + st[501:]}
    path = _write(tmp_path / "conflict", types, bad, custom)
    for cmd in ("score", "identify"):
        _one_line_exit_2([cmd, str(path)], capsys, "two different states for sample 500")
    same = {**msgs, "/state": st[:501] + [st[500]] + st[501:]}
    notes = []
    rec = read_recording(read_bag(_write(tmp_path / "repeat", types, same, custom), on_warning=notes.append),
                         cfg.episode.step)
    assert rec.samples == len(x) and any("1 repeated identical message collapsed" in n for n in notes)


def test_a_stamp_beyond_the_tolerance_is_one_line_naming_bag_topic_message_and_offset(clean, tmp_path, capsys):
    d, cfg, tr, x, types, msgs, custom = clean
    st = list(msgs["/state"])
    off = int(0.45 * cfg.episode.step * 1e9)
    assert off > TOLERANCE * cfg.episode.step * 1e9
    st[77] = (st[77][0], _stamp(st[77][1], _stamp_of(st[77][1]) + off))
    path = _write(tmp_path / "late", types, {**msgs, "/state": st}, custom)
    _one_line_exit_2(["plot", str(path), "--out", str(tmp_path / "l.png")], capsys, "late: /state: message 77",
                     "+135.0 µs from sample 77", "tolerance of ±0.4 step")


def test_non_finite_states_are_counted_and_left_out_of_identification(clean, tmp_path):
    d, cfg, tr, x, types, msgs, custom = clean
    st = list(msgs["/state"])
    nan = cdr.encode_joint_states([_stamp_of(st[900][1])], ["actuator", "chamber_1", "chamber_2"],
                                  np.full((1, 3), np.nan), np.zeros((1, 3)), np.zeros((1, 3)))[0]
    st[900] = (st[900][0], nan)
    path = _write(tmp_path / "nan", types, {**msgs, "/state": st}, custom)
    notes = []
    exp = experiment_from_bag(path, on_warning=notes.append)
    assert any("1 state with non-finite values" in n for n in notes)
    assert list(exp.gaps) == [900 - exp.first] and np.isfinite(exp.x).all()


def test_ros2_control_commands_pair_by_log_time_the_first_after_each_state_wins(clean, tmp_path):
    d, cfg, tr, x, types, msgs, custom = clean
    u = tr["u"]
    first = cdr.encode_float64_arrays(u[:, None])
    later = cdr.encode_float64_arrays(u[:, None] + 1.0)                  # a second, different command per state
    states = [(lt + 1000, b) for lt, b in msgs["/state"]]
    cmds = [(0, cdr.encode_float64_arrays([[7.0]])[0])]                # before the first state
    for (lt, _), a, b in zip(states, first, later):
        cmds += [(lt + 10_000, a), (lt + 20_000, b)]
    path = _write(tmp_path / "twice", {"/joint_states": types["/state"], CMD: "std_msgs/msg/Float64MultiArray"},
                  {"/joint_states": states, CMD: cmds}, custom)
    notes = []
    rec = read_recording(read_bag(path, on_warning=notes.append), cfg.episode.step)
    np.testing.assert_array_equal(rec.u, u)
    assert any(f"{len(u)} commands not first after their state and 1 logged before the first state: ignored" in n
               for n in notes), notes


# --- every reader of recorded samples, one policy ------------------------------------------------


def _one_state(clean, tmp_path, name, row, column, value, topics=("/state", "/true_state")):
    """The clean bag with state ``row``'s value ``column`` (3 x array + joint: 0 y, 7 P1) set to ``value``."""
    d, cfg, tr, x, types, msgs, custom = clean
    msgs = {t: list(m) for t, m in msgs.items()}
    for t in topics:
        lt, b = msgs[t][row]
        _, pos, vel, eff = cdr.joint_states([b])
        arrays = [pos.copy(), vel.copy(), eff.copy()]
        arrays[column // 3][0, column % 3] = value
        msgs[t][row] = (lt, cdr.encode_joint_states([_stamp_of(b)], ["actuator", "chamber_1", "chamber_2"],
                                                    *arrays)[0])
    return _write(tmp_path / name, types, msgs, custom)


def test_an_impossible_value_is_a_sample_not_measured_for_every_reader(clean, tmp_path, capsys):
    # one P1 = 1e300 Pa or y = 1e300 m: identify fits exactly what it fits with that sample NaN (the
    # estimates cannot move through a channel weight), score interpolates it, plot draws a gap; each says so
    d, cfg, tr, x, *_ = clean
    nan = experiment_from_bag(_one_state(clean, tmp_path, "nan", 900, 0, np.nan), on_warning=_quiet)
    for name, column in (("p1", 7), ("y", 0)):
        path = _one_state(clean, tmp_path, name, 900, column, 1e300)
        notes = []
        exp = experiment_from_bag(path, on_warning=notes.append)
        assert any("1 state with non-finite values" in n and "beyond what a sensor of this actuator reads" in n
                   and "message 900" in n for n in notes), notes
        np.testing.assert_array_equal(exp.x, nan.x)
        np.testing.assert_array_equal(exp.gaps, nan.gaps)
        assert exp.samples == nan.samples == len(x) - exp.first         # nothing after the sample is lost
        assert main(["score", str(path)]) == 0
        err = capsys.readouterr().err
        assert "each interpolated from its neighbours" in err and "diverged" not in err, err
        assert score_bag(path, on_warning=_quiet)[0].J == pytest.approx(score_bag(d / "clean")[0].J, rel=1e-4)
        assert main(["plot", str(path), "--out", str(tmp_path / f"{name}.png")]) == 0, capsys.readouterr().err
        assert "Traceback" not in capsys.readouterr().err


def test_a_position_beyond_y_limit_and_back_is_one_bad_sample_and_one_to_the_end_is_said(clean, tmp_path):
    d, cfg, tr, x, types, msgs, custom = clean
    notes = []
    exp = experiment_from_bag(_one_state(clean, tmp_path, "out", 900, 0, 5.0), on_warning=notes.append)
    assert exp.samples == len(x) - exp.first and list(exp.gaps) == [900 - exp.first]
    st = list(msgs["/state"])
    for i in range(3000, len(st)):
        _, pos, vel, eff = cdr.joint_states([st[i][1]])
        pos[0, 0] = 5.0
        st[i] = (st[i][0], cdr.encode_joint_states([_stamp_of(st[i][1])], ["actuator", "chamber_1", "chamber_2"],
                                                   pos, vel, eff)[0])
    notes = []
    exp = experiment_from_bag(_write(tmp_path / "diverged", types, {**msgs, "/state": st}, custom),
                              on_warning=notes.append)
    assert exp.first + exp.samples == 3000
    assert any("exceeds simulation.y_limit 1 m from t = 0.900000 s to the end (the run diverged)" in n
               for n in notes), notes


def test_score_says_what_it_scores(clean, derived, tmp_path, capsys):
    # a non-finite true state inside the run: interpolated and said; from one on to the end: diverged, said
    d = clean[0]
    path = _one_state(clean, tmp_path, "nan_true", 900, 0, np.nan, topics=("/true_state",))
    assert score_bag(path, on_warning=_quiet)[0].J == pytest.approx(score_bag(d / "clean")[0].J, rel=1e-4)
    _, cfg, tr, x, types, msgs, custom = clean
    true = list(msgs["/true_state"])
    for i in range(3000, len(true)):
        true[i] = _one_state_bytes(true[i], np.nan)
    tail = _write(tmp_path / "nan_tail", types, {**msgs, "/true_state": true}, custom)
    assert main(["score", str(tail)]) == 0
    err = capsys.readouterr().err
    assert "the states from t = 0.900000 s to the end are not finite: the run is scored as diverged" in err, err
    # noise.added_by: plant and no true_state: the readings are scored, said
    assert main(["score", str(derived["state_command"])]) == 0
    err = capsys.readouterr().err
    assert "noise.added_by is plant and the bag has no '…/true_state': the states on /state are scored as " \
        "recorded (from the node graph: the sensors' readings" in err, err


def _one_state_bytes(message, value):
    lt, b = message
    _, pos, vel, eff = cdr.joint_states([b])
    pos[0, 0] = value
    return lt, cdr.encode_joint_states([_stamp_of(b)], ["actuator", "chamber_1", "chamber_2"], pos, vel, eff)[0]


def test_a_big_endian_message_is_one_line_naming_bag_and_byte_order(clean, tmp_path, capsys):
    d, cfg, tr, x, types, msgs, custom = clean
    st = [(lt, b"\x00\x00" + b[2:]) for lt, b in msgs["/state"]]
    path = _write(tmp_path / "big_endian", types, {**msgs, "/state": st, "/true_state": st}, custom)
    for cmd in ("score", "plot", "identify"):
        extra = ["--out", str(tmp_path / "b.png")] if cmd == "plot" else []
        _one_line_exit_2([cmd, str(path), *extra], capsys, "big_endian: /", "message 0: big-endian CDR")


def test_a_bag_without_effort_is_one_line_naming_the_missing_interfaces(clean, tmp_path, capsys):
    d, cfg, tr, x, types, msgs, custom = clean

    def strip(m):
        _, pos, vel, _ = cdr.joint_states([b for _, b in m])
        return list(zip([lt for lt, _ in m], cdr.encode_joint_states(
            cdr.stamps_ns([b for _, b in m]), ["actuator", "chamber_1", "chamber_2"], pos, vel, None)))
    path = _write(tmp_path / "no_effort", types, {**msgs, "/state": strip(msgs["/state"]),
                                                  "/true_state": strip(msgs["/true_state"])}, custom)
    for cmd in ("score", "plot", "identify"):
        extra = ["--out", str(tmp_path / "e.png")] if cmd == "plot" else []
        _one_line_exit_2([cmd, str(path), *extra], capsys, "no_effort: /", "lack chamber_1/effort, chamber_2/effort")


def test_a_library_warning_is_one_line_not_a_source_echo(clean, monkeypatch, capsys):
    # numpy's RuntimeWarnings once leaked onto stderr as two lines each (message and source line)
    import has_control.bag.score as scoring
    original = scoring.score_arrays

    def overflowing(*args, **kwargs):
        np.float64(1e300) * np.float64(1e300)
        return original(*args, **kwargs)
    monkeypatch.setattr(scoring, "score_arrays", overflowing)
    assert main(["score", str(clean[0] / "clean")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("has-control: warning: RuntimeWarning: overflow"), err


def test_a_recording_longer_than_the_readers_limit_is_refused_up_front(clean, tmp_path, monkeypatch, capsys):
    # a 10-minute recording once took 3.9 GB in identify and 3 GB in plot; the readers hold every
    # message, so a run beyond MAX_SAMPLES is refused from metadata.yaml's counts before a message is read
    import shutil

    import has_control.bag.read as reader
    import has_control.bag.recorded as recorded
    from has_control.bag.recorded import MAX_SAMPLES
    d = clean[0]
    long = tmp_path / "long"
    shutil.copytree(d / "clean", long)
    meta = (long / "metadata.yaml").read_text()
    count = len(clean[3])
    (long / "metadata.yaml").write_text(meta.replace(f"message_count: {count}", f"message_count: {MAX_SAMPLES + 1}"))
    monkeypatch.setattr(reader, "_McapScan", None)               # a message read would raise TypeError
    for cmd in ("score", "plot", "identify"):
        extra = ["--out", str(tmp_path / "l.png")] if cmd == "plot" else []
        _one_line_exit_2([cmd, str(long), *extra], capsys, f"has {MAX_SAMPLES + 1} messages (metadata.yaml)",
                         f"more than the {MAX_SAMPLES} samples")
    monkeypatch.setattr(recorded, "MAX_SAMPLES", count - 1)         # a bare .mcap: from its summary, up front
    _one_line_exit_2(["score", str(d / "clean" / "clean.mcap")], capsys,
                     f"has {count} messages (the MCAP summary)", f"more than the {count - 1} samples")
    monkeypatch.undo()
    monkeypatch.setattr(recorded, "MAX_SAMPLES", count - 1)         # a bare .mcap without a summary: once read
    monkeypatch.setattr(recorded, "summary_message_counts", lambda f, limit: {})
    _one_line_exit_2(["score", str(d / "clean" / "clean.mcap")], capsys, f"{count} messages: more than the")


def test_validation_compares_the_whole_held_out_run_around_a_bad_sample(clean, tmp_path):
    # with a NaN in the held-out run, --validate once compared only the part before it
    from has_control.identify.validate import validate
    d, cfg = clean[0], clean[1]
    full = validate(experiment_from_bag(d / "clean", on_warning=_quiet), cfg)
    held = experiment_from_bag(_one_state(clean, tmp_path, "nan_held", 900, 0, np.nan), on_warning=_quiet)
    v = validate(held, cfg)
    assert len(v.t) == len(full.t) == len(clean[3]) - held.first
    for c, f in full.fit.items():
        assert np.isfinite(v.fit[c]) and v.fit[c] == pytest.approx(f, abs=0.05), c


def test_a_joint_named_twice_in_one_state_is_one_line(clean, tmp_path, capsys):
    # a duplicated joint was once answered with the second copy's values, uncounted
    d, cfg, tr, x, types, msgs, custom = clean
    st = list(msgs["/state"])
    _, pos, vel, eff = cdr.joint_states([b for _, b in st])
    names = ["actuator", "chamber_1", "chamber_2", "actuator"]
    arrays = [np.column_stack([a, a[:, :1] + 1.0]) for a in (pos, vel, eff)]
    twice = cdr.encode_joint_states(cdr.stamps_ns([b for _, b in st]), names, *arrays)
    path = _write(tmp_path / "twice_joint", {"/joint_states": types["/state"], CMD: "std_msgs/msg/Float64MultiArray"},
                  {"/joint_states": list(zip([lt for lt, _ in st], twice)),
                   CMD: [(lt + 1, c) for (lt, _), c in zip(st, cdr.encode_float64_arrays(tr["u"][:, None]))]},
                  custom)
    _one_line_exit_2(["score", str(path)], capsys, "/joint_states: message 0: joint actuator named twice")
