"""A fuzz test of the config loader and the bag reader. Random and
mutated inputs (seeded, bounded in count and time): every input gives a
result or a one-line HasControlError, never another exception, never a hang."""
import dataclasses
import signal
import time

import numpy as np
import pytest
from conftest import stopped_session

from has_control.bag import STRING, BagWriter, describe, read_bag, recorded_run
from has_control.config import CONFIG_DIR, load_config
from has_control.common.errors import HasControlError
from has_control.tuning.tuner import load_tuning

CONFIG_CASES = 300          # inputs to the config loader (about 2 s)
BAG_CASES = 1400            # inputs to the bag reader (about 4 s)
SECONDS = 6.0               # per target, at most, on a loaded machine
HANG = 2.0                  # one input taking longer than this is a hang [s]

YAML_TOKENS = [b": ", b"[", b"]", b"{", b"}", b"&a ", b"*a", b"- ", b"\t", b"\n", b"!!python/object:os.system ",
               b"1e999", b"-1", b".nan", b".inf", b"~", b'"', b"'", b"#", b"? ", b"<<: ", b"9" * 400,
               b"ros__parameters:", b"/**:", b"  ", b"\xff", b"\x00", b"%YAML 1.2\n", b"---\n", b"..."]


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang()


def _mutate(rng, data: bytes, tokens=()) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 6))):
        op = int(rng.integers(0, 6 if tokens else 5))
        at = int(rng.integers(0, len(b) + 1)) if b else 0
        if op == 0 and b:                                   # flip a bit
            b[min(at, len(b) - 1)] ^= 1 << int(rng.integers(0, 8))
        elif op == 1:                                       # delete a run
            del b[at:at + int(rng.integers(1, 64))]
        elif op == 2:                                       # random bytes
            b[at:at] = rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8).tobytes()
        elif op == 3:                                       # truncate
            del b[at:]
        elif op == 4 and b:                                 # duplicate a slice elsewhere
            a = int(rng.integers(0, len(b)))
            b[at:at] = b[a:a + int(rng.integers(1, 256))]
        elif op == 5:
            b[at:at] = tokens[int(rng.integers(0, len(tokens)))]
    return bytes(b)


def _fuzz(seeds: list[bytes], check, tmp_path, name: str, seed: int, cases: int, tokens=()):
    rng = np.random.default_rng(seed)
    path = tmp_path / name
    old = signal.signal(signal.SIGALRM, _alarm)
    counts = {"accepted": 0, "refused": 0}
    t0 = time.perf_counter()
    try:
        for i in range(cases):
            if time.perf_counter() - t0 > SECONDS:
                break
            kind = i % 10
            if kind == 0:                                   # random input
                data = rng.integers(0, 256, int(rng.integers(0, 2048)), dtype=np.uint8).tobytes()
                if i % 20 == 0:
                    data = seeds[0][:8] + data               # past the magic, for the bag reader
            else:
                data = _mutate(rng, seeds[i % len(seeds)], tokens)
            path.write_bytes(data)
            signal.setitimer(signal.ITIMER_REAL, HANG)
            try:
                check(path)
                counts["accepted"] += 1
            except HasControlError as exc:
                assert "\n" not in str(exc), (i, str(exc))
                counts["refused"] += 1
            except Hang:
                pytest.fail(f"{name} case {i} hangs (seed {seed})")
            except Exception as exc:                        # noqa: BLE001 - the point of the test
                (tmp_path / f"{name}.case{i}").write_bytes(data)
                pytest.fail(f"{name} case {i} (kept as {name}.case{i}): {type(exc).__name__}: {exc}")
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
    finally:
        signal.signal(signal.SIGALRM, old)
    assert sum(counts.values()) >= 50
    print(f"{name}: {sum(counts.values())} inputs in {time.perf_counter() - t0:.1f} s: {counts}")
    return counts


@pytest.mark.system
def test_fuzz_the_config_loader(tmp_path):
    seeds = [p.read_bytes() for p in sorted(CONFIG_DIR.glob("*.yaml"))]

    def check(path):
        load_config([path])
        load_tuning([path])
    _fuzz(seeds, check, tmp_path, "config.yaml", seed=2026, cases=CONFIG_CASES, tokens=YAML_TOKENS)


@pytest.fixture(scope="module")
def small_bags(tmp_path_factory):
    from has_control.bag import PARAMETERS_KEY, parameters_json, write_trace
    from has_control.core.episode import simulate
    from has_control.config import with_horizon
    from has_control.core.params import Config
    out = []
    for compression in ("zstd", "none"):
        cfg = with_horizon(Config(), 1.5)
        d = tmp_path_factory.mktemp("fuzz") / f"run-{compression}"
        w = BagWriter(d, {PARAMETERS_KEY: parameters_json(cfg)}, compression=compression)
        w._mcap.chunk_bytes = 16 << 10
        tr = simulate(cfg)
        tr = dataclasses.replace(tr, data=tr.data[:200])    # a short run: small bag, many chunks
        write_trace(w, tr, cfg)
        w.add_topic("/note", STRING)
        w.write("/note", 1, b"\x00\x01\x00\x00\x05\x00\x00\x00hello\x00")
        w.close()
        out.append((d / f"{d.name}.mcap").read_bytes())
    return out


@pytest.mark.system
def test_fuzz_the_bag_reader(small_bags, tmp_path, capsys):
    def check(path):
        bag = read_bag(path, on_warning=lambda m: None)
        describe(bag)
        if bag.complete:
            try:
                recorded_run(bag)
            except HasControlError:
                pass
    _fuzz(small_bags, check, tmp_path, "bag.mcap", seed=2027, cases=BAG_CASES)


# --- metadata.yaml's custom_data and session records --------------------------------------------

METADATA_CASES = 400        # edits of metadata.yaml custom_data (each a bag read: SECONDS ends it near 100)
SESSION_CASES = 400         # edits of a session's records, each checked as a resume checks it (about 3 s)
JSON_TOKENS = [b"[", b"]", b"{", b"}", b",", b":", b'"', b"null", b"true", b"1e999", b"-1", b"NaN", b"[" * 5000,
               b'{"a": {"b": [1, {"c": 2}]}}', b'"simulation.step": 0.0007', b'"swarm"', b"\\u0000", b"9" * 5000]


@pytest.fixture(scope="module")
def metadata_bag(tmp_path_factory):
    from has_control.bag import PARAMETERS_KEY, parameters_json, write_trace
    from has_control.core.episode import simulate
    from has_control.config import with_horizon
    from has_control.core.params import Config
    cfg = with_horizon(Config(), 1.2)
    d = tmp_path_factory.mktemp("fuzzmeta") / "run"
    w = BagWriter(d, {PARAMETERS_KEY: parameters_json(cfg)})
    tr = simulate(cfg)
    write_trace(w, dataclasses.replace(tr, data=tr.data[:200]), cfg)
    w.close()
    return d


@pytest.mark.system
def test_fuzz_metadata_custom_data(metadata_bag, tmp_path):
    """The fuzzed bytes are the parameters' JSON (most cases) or the whole
    custom_data mapping's YAML, in an otherwise intact metadata.yaml."""
    import shutil

    import yaml

    from has_control.bag import PARAMETERS_KEY
    bag = tmp_path / "bag"
    shutil.copytree(metadata_bag, bag)
    doc = yaml.safe_load((metadata_bag / "metadata.yaml").read_text())
    info = doc["rosbag2_bagfile_information"]
    stored = info["custom_data"][PARAMETERS_KEY]
    head, _, tail = (metadata_bag / "metadata.yaml").read_text().partition("  custom_data:")
    seeds = [stored.encode(), b'{"simulation.horizon": 1.2}', b"{}", yaml.safe_dump(info["custom_data"]).encode()]

    def check(path):
        data = path.read_bytes()
        if data.startswith(b"{") or data.startswith(b"[") or path.stat().st_size % 4:
            info["custom_data"] = {PARAMETERS_KEY: data.decode("utf-8", "replace")}
            (bag / "metadata.yaml").write_text(yaml.safe_dump(doc, width=10**9))
        else:                                           # the mapping itself, as YAML text
            custom = "\n".join("    " + x for x in data.decode("utf-8", "replace").splitlines())
            rest = tail.split("\n", 1)[1] if "\n" in tail else ""
            rest = "\n".join(x for x in rest.splitlines() if not x.startswith("    "))
            (bag / "metadata.yaml").write_text(f"{head}  custom_data:\n{custom}\n{rest}\n")
        b = read_bag(bag, on_warning=lambda m: None)
        describe(b)
        b.config()
    _fuzz(seeds, check, tmp_path, "custom_data", seed=2028, cases=METADATA_CASES, tokens=JSON_TOKENS + YAML_TOKENS)


@pytest.fixture(scope="module")
def session_records(tmp_path_factory):
    """The messages of a session of 2 iterations of 3 particles (stopped after them)."""
    d = stopped_session(tmp_path_factory.mktemp("fuzzsession") / "s", particles=3, iterations=4)
    return read_bag(d / "session").messages


def test_fuzz_session_records(session_records, tmp_path):
    """Each case replaces one record (settings, an iteration, a swarm state)
    by fuzzed JSON; what resume reads of it (:func:`restore`) gives a
    session to continue, whose swarm takes its next step, or one line."""
    from has_control.tuning.session import ITERATION, SETTINGS, SWARM, _string, _unstring, restore
    slots = [(SETTINGS, 0), (ITERATION, 0), (ITERATION, 1), (SWARM, 0), (SWARM, 1)]
    seeds = [_unstring(session_records[t][i][1]).encode() for t, i in slots]
    case = [0]

    def check(path):
        topic, index = slots[case[0] % len(slots)]
        case[0] += 1
        messages = {t: list(m) for t, m in session_records.items()}
        t_ns, _ = messages[topic][index]
        messages[topic][index] = (t_ns, _string(path.read_bytes().decode("utf-8", "replace")))
        tuning, cfg, evaluator, k, swarm = restore(messages, tmp_path / "s")
        if swarm is not None and not swarm.done:
            x = swarm.ask()
            assert x.shape == (tuning.swarm.particles, 3)
            swarm.tell(np.ones(len(x)))
    _fuzz(seeds, check, tmp_path, "record.json", seed=2029, cases=SESSION_CASES, tokens=JSON_TOKENS)


# --- the reader of recorded samples, message by message -------------------------------------------

MESSAGE_CASES = 600         # edits of one run's state and command messages (in memory; SECONDS ends it)


@pytest.mark.system
def test_fuzz_recorded_samples(small_bags, tmp_path):
    """Each case edits the messages of a recorded run: a state or command
    payload truncated or mutated, a message repeated, a conflicting second
    state for a sample, a stamp moved. Every reader (read_recording, score's
    recorded_run, plot's series_of) gives a result or one line, and a second,
    different state for one sample is never taken silently."""
    import copy

    from has_control.bag.recorded import read_recording
    from has_control.bag.series import series_of
    from has_control.wire import cdr
    (tmp_path / "run.mcap").write_bytes(small_bags[1])
    base = read_bag(tmp_path / "run.mcap", on_warning=lambda m: None)
    state = next(t for t in base.messages if t.endswith("/state"))
    command = next(t for t in base.messages if t.endswith("/command"))
    rng = np.random.default_rng(2031)
    t0, counts = time.perf_counter(), {"accepted": 0, "refused": 0, "conflicts refused": 0}
    for i in range(MESSAGE_CASES):
        if time.perf_counter() - t0 > SECONDS:
            break
        bag = copy.copy(base)
        bag.messages = {t: list(m) for t, m in base.messages.items()}
        topic = state if i % 3 else command
        m = bag.messages[topic]
        k = int(rng.integers(0, len(m)))
        lt, data = m[k]
        kind = i % 5
        conflict = False
        if kind == 0:                                   # truncated payload
            m[k] = (lt, data[:int(rng.integers(0, len(data)))])
        elif kind == 1:                                 # mutated payload
            m[k] = (lt, _mutate(rng, data))
        elif kind == 2:                                 # the same message twice
            m.insert(k + 1, (lt, data))
        elif kind == 3:                                 # a second, different state for the sample
            _, pos, vel, eff = cdr.joint_states([data])
            pos = pos + 1e-3
            other = cdr.encode_joint_states(cdr.stamps_ns([data]), ["actuator", "chamber_1", "chamber_2"]
                                            if topic == state else ["valve"], pos, vel, eff)[0]
            m.insert(k + 1, (lt + 1, other))
            conflict = True
        else:                                           # a stamp moved by up to 2 steps
            ns = max(0, int(cdr.stamps_ns([data])[0]) + int(rng.integers(-600_000, 600_000)))
            m[k] = (lt, data[:4] + np.array([ns // 10**9, ns % 10**9], "<u4").tobytes() + data[12:])
        signal.setitimer(signal.ITIMER_REAL, HANG)
        old = signal.signal(signal.SIGALRM, _alarm)
        try:
            for reader in (lambda: read_recording(bag, 3e-4, emit=False), lambda: recorded_run(bag),
                           lambda: series_of(bag)):
                try:
                    reader()
                    assert not conflict, f"case {i}: two different messages for one sample accepted"
                    counts["accepted"] += 1
                except HasControlError as exc:
                    assert "\n" not in str(exc), (i, str(exc))
                    if conflict:
                        assert "two different" in str(exc), (i, str(exc))
                    counts["conflicts refused" if conflict else "refused"] += 1
        except Hang:
            pytest.fail(f"recorded samples case {i} hangs")
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
    assert sum(counts.values()) >= 150 and counts["conflicts refused"] >= 15 and counts["accepted"] >= 50, counts
    print(f"recorded samples: {counts}")
