"""Recorded data with integrity (the bag and session readers' checks). Bits flipped over every
region of a small recorded bag and of a small session bag give one line and
exit 2, or a warning and the identical result; never a different result."""
import contextlib
import io
import json
import shutil
import struct

import numpy as np
import pytest

from has_control.bag import PARAMETERS_KEY, BagError, BagWriter, describe, parameters_json, read_bag, \
    score_bag, write_trace
from has_control.cli import main
from has_control.core.episode import simulate
from has_control.config import with_horizon
from has_control.common.errors import HasControlError
from has_control.core.params import Config

RUN_FLIPS = 120               # bit flips over the recorded run's .mcap
SESSION_FLIPS = 24            # bit flips over the session's .mcap (each one a resume through the CLI)


def _flip_positions(n: int, count: int, seed: int) -> list[int]:
    """Evenly spread over the file (every region), plus as many at random."""
    rng = np.random.default_rng(seed)
    even = np.linspace(0, n - 1, count // 2).astype(int)
    return sorted(set(even.tolist()) | set(rng.integers(0, n, count - len(even)).tolist()))


def _chunks(raw: bytes) -> list[int]:
    """Offsets of the Chunk records of an MCAP file's data section."""
    pos, out = 8, []
    while raw[pos] != 0x0F:                          # DataEnd
        if raw[pos] == 0x06:
            out.append(pos)
        pos += 9 + struct.unpack_from("<Q", raw, pos + 1)[0]
    return out


def _flip(path, pos: int, bit: int) -> None:
    data = bytearray(path.read_bytes())
    data[pos] ^= 1 << bit
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def run_bag(tmp_path_factory):
    """A 1.5 s run written as the graph records it, in chunks of 64 KiB (several chunks)."""
    cfg = with_horizon(Config(), 1.5)
    trace = simulate(cfg)
    d = tmp_path_factory.mktemp("integrity") / "run"
    w = BagWriter(d, {PARAMETERS_KEY: parameters_json(cfg)})
    w._mcap.chunk_bytes = 64 << 10
    write_trace(w, trace, cfg)
    w.close()
    return d, score_bag(d)[0]


def test_chunks_and_data_section_carry_crcs_that_the_reader_checks(run_bag, tmp_path):
    d, score = run_bag
    bag = read_bag(d)
    assert bag.complete and not bag.damage
    raw = (d / "run.mcap").read_bytes()
    chunks = _chunks(raw)
    assert len(chunks) >= 3
    copy = tmp_path / "run"
    shutil.copytree(d, copy)
    data = bytearray(raw)
    data[chunks[1] + 100] ^= 0x10                    # inside the second chunk's compressed records
    (copy / "run.mcap").write_bytes(bytes(data))
    warnings = []
    bag = read_bag(copy, on_warning=warnings.append)
    assert not bag.complete
    assert any(f"chunk at offset {chunks[1]} is corrupted" in w and str(copy / "run.mcap") in w for w in warnings)
    assert not any("truncated" in w for w in warnings)            # the footer is there: damage, not truncation
    assert "corrupted chunk" in describe(bag)
    with pytest.raises(BagError, match="incomplete"):
        score_bag(copy)


@pytest.mark.system
def test_bit_flips_over_a_recorded_run_never_change_j(run_bag, tmp_path, capsys):
    d, score = run_bag
    src = (d / "run.mcap").read_bytes()
    positions = _flip_positions(len(src), RUN_FLIPS, seed=11)
    outcome = {"refused": 0, "identical": 0, "identical_with_warning": 0}
    copy = tmp_path / "run"
    shutil.copytree(d, copy)
    for i, pos in enumerate(positions):
        (copy / "run.mcap").write_bytes(src)
        _flip(copy / "run.mcap", pos, i % 8)
        capsys.readouterr()
        try:
            got = score_bag(copy)[0]
        except HasControlError as exc:
            assert "\n" not in str(exc)
            outcome["refused"] += 1
            continue
        assert got == score, f"flip at byte {pos}: J {got.J} instead of {score.J}"
        outcome["identical_with_warning" if "warning" in capsys.readouterr().err else "identical"] += 1
    assert sum(outcome.values()) == len(positions) and outcome["refused"] > len(positions) // 2
    print(f"run bag: {len(positions)} flips over {len(src)} bytes: {outcome}")


def test_reversed_bag_reads_in_log_time_order_and_bag_info_is_right(run_bag, tmp_path, capsys):
    d, score = run_bag
    bag = read_bag(d)
    dst = tmp_path / "reversed"
    w = BagWriter(dst, dict(bag.custom_data))
    for topic in bag.types:
        w.add_topic(topic, bag.types[topic])
    n = max(len(m) for m in bag.messages.values())
    for start in range(n - n % 500, -1, -500):              # blocks of 500 samples, newest block first
        w.write_batches({topic: (np.array([t for t, _ in msgs[start:start + 500]], np.int64),
                                 [x for _, x in msgs[start:start + 500]])
                         for topic, msgs in bag.messages.items() if msgs[start:start + 500]})
        w.sync()
    w.close()
    warnings = []
    back = read_bag(dst, on_warning=warnings.append)
    assert any("out of log-time order" in w for w in warnings)
    assert back.start_ns == bag.start_ns and back.end_ns == bag.end_ns > 0
    assert f"Duration:          {(bag.end_ns - bag.start_ns) / 1e9:.6f} s" in describe(back)
    assert score_bag(dst)[0] == score


def test_bag_info_labels_a_channel_by_its_message_encoding(tmp_path, capsys):
    from has_control.bag.mcap_writer import McapWriter
    f = tmp_path / "json.mcap"
    w = McapWriter(f, "", "test")
    ch = w.add_channel("/events", w.add_schema("event", "jsonschema", b"{}"), "json", {})
    w.write(ch, 5, b'{"a": 1}')
    w.close()
    assert main(["bag-info", str(f)]) == 0
    out = capsys.readouterr().out
    assert "Serialization Format: json" in out and "cdr" not in out


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory):
    """A tuning session stopped after 3 of 6 iterations (its bag closed), and
    the result of the uninterrupted run."""
    from has_control.tuning.session import Session
    from has_control.tuning.tuner import load_tuning, tune
    base = tmp_path_factory.mktemp("sessions")
    args = ["tune", "--variant", "pso-cp-tvac", "--particles", "4", "--iterations", "6", "--duration", "1.5", "--json"]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(args) == 0
    full = json.loads(buf.getvalue())
    cfg = with_horizon(Config(), 1.5)
    tuning = load_tuning().replace(variant="pso-cp-tvac", particles=4, iterations=6)
    session = Session(base / "s", tuning, cfg)

    class Stop(Exception):
        pass

    def each(sw):
        session.record(sw)
        if sw.iteration == 3:
            raise Stop
    with pytest.raises(Stop):
        tune(cfg, tuning, callback=each)
    session.close()
    session.release()
    return base / "s", full


def _resume(d, capsys):
    rc = main(["tune", "--resume", str(d), "--json"])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.mark.system
def test_bit_flips_over_a_session_bag_resume_to_the_same_gains_or_stop_in_one_line(session_dir, tmp_path, capsys):
    d, full = session_dir
    src = (d / "session" / "session.mcap").read_bytes()
    positions = _flip_positions(len(src), SESSION_FLIPS, seed=12)
    outcome = {"refused": 0, "identical": 0, "identical_with_warning": 0}
    for i, pos in enumerate(positions):
        copy = tmp_path / f"s{i}"
        shutil.copytree(d, copy)
        _flip(copy / "session" / "session.mcap", pos, i % 8)
        rc, out, err = _resume(copy, capsys)
        assert "Traceback" not in err
        if rc == 2:
            assert len([x for x in err.splitlines() if "error" in x]) == 1, err
            outcome["refused"] += 1
            continue
        assert rc == 0, err
        got = json.loads(out)
        assert {k: v for k, v in got.items() if k != "seconds"} == \
            {k: v for k, v in full.items() if k != "seconds"}, f"flip at byte {pos}"
        outcome["identical_with_warning" if "warning" in err else "identical"] += 1
    assert sum(outcome.values()) == len(positions)
    print(f"session bag: {len(positions)} flips over {len(src)} bytes: {outcome}")


@pytest.mark.system
def test_a_damaged_iteration_falls_back_to_the_previous_good_one(session_dir, tmp_path, capsys):
    from has_control.tuning.session import ITERATION
    d, full = session_dir
    copy = tmp_path / "s"
    shutil.copytree(d, copy)
    bag = read_bag(copy / "session")
    assert bag.count(ITERATION) == 3
    raw = bytearray((copy / "session" / "session.mcap").read_bytes())
    last = _chunks(bytes(raw))[-1]                              # iteration 3's record and swarm state
    raw[last + 9 + 60] ^= 0x01                                  # inside its compressed records
    (copy / "session" / "session.mcap").write_bytes(bytes(raw))
    rc, out, err = _resume(copy, capsys)
    assert rc == 0, err
    assert "corrupted" in err and "resuming from iteration 2" in err
    got = json.loads(out)
    got.pop("seconds")
    assert got == {k: v for k, v in full.items() if k != "seconds"}
