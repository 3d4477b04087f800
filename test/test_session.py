"""Tuning sessions on disk (has_control.tuning.session): a hand-edited or damaged session is refused in one
line naming the culprit, or resumed from its last good iteration; a stored result without its keys is not used;
a finished session is never replaced without --force, a session directory is locked, and --resume finishes
an interrupted final write."""
import json
import shutil
import time

import pytest
from conftest import main_result, one_error_line, one_line, stopped_session

from has_control.bag import BagWriter, read_bag
from has_control.cli import main
from has_control.common.files import DirectoryLock
from has_control.tuning.tuner import Tuning, tuning_json


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


def test_a_session_with_damaged_scenarios_is_one_line(tmp_path, monkeypatch):
    import has_control.tuning.session as session
    from has_control.bag import BagError
    from has_control.core.params import Config

    def damaged(t):
        return dict(tuning_json(t), scenarios=[{"name": "a", "overrides": [1, 2]}], aggregate="mean")
    monkeypatch.setattr(session, "tuning_json", damaged)
    session.Session(tmp_path / "s", Tuning(), Config()).close()
    with pytest.raises(BagError, match="cannot resume"):
        session.resume(tmp_path / "s")


TUNE = ["tune", "--variant", "pso-cp-tvac", "--particles", "4", "--iterations", "3", "--duration", "1.5"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished session (tune --out) and what tune --json printed."""
    d = tmp_path_factory.mktemp("results") / "s"
    assert main([*TUNE, "--out", str(d), "--json"]) == 0
    return d, json.loads((d / "tune.json").read_text())


@pytest.mark.system
def test_tune_out_never_replaces_a_session_without_force(finished, tmp_path, capsys):
    d, result = finished
    copy = tmp_path / "s"
    shutil.copytree(d, copy)
    before = (copy / "tune.json").read_bytes()
    t0 = time.perf_counter()
    rc, _, err = main_result(capsys, *TUNE, "--out", copy)
    one_error_line(rc, err, str(copy / "session"), "--force")
    assert time.perf_counter() - t0 < 2 and (copy / "tune.json").read_bytes() == before
    (copy / "session").rename(copy / "elsewhere")          # tune.json alone is protected as well
    rc, _, err = main_result(capsys, *TUNE, "--out", copy)
    one_error_line(rc, err, str(copy / "tune.json"))
    rc, out, err = main_result(capsys, *TUNE, "--out", copy, "--force", "--json")
    assert rc == 0, err
    assert json.loads((copy / "tune.json").read_text())["gains"] == result["gains"]


def test_a_second_resume_on_a_locked_session_is_refused(finished, tmp_path, capsys):
    d, _ = finished
    copy = tmp_path / "s"
    shutil.copytree(d, copy)
    lock = DirectoryLock(copy, ".lock", "the tuning session")      # as a running tune holds it
    try:
        rc, _, err = main_result(capsys, "tune", "--resume", copy)
        one_error_line(rc, err, str(copy), "in use by another process")
        rc, _, err = main_result(capsys, *TUNE, "--out", copy, "--force")
        one_error_line(rc, err, "in use by another process")
    finally:
        lock.release()
    assert (copy / "session").is_dir() and (copy / "tune.json").exists()   # nothing touched


@pytest.mark.system
@pytest.mark.parametrize("cut", ["no-tune.json", "no-figures-no-tune.json", "bag-cut-in-finish"])
def test_resume_finishes_a_session_whose_final_writes_were_interrupted(finished, tmp_path, capsys, cut):
    d, result = finished
    copy = tmp_path / "s"
    shutil.copytree(d, copy)
    (copy / "tune.json").unlink()
    if cut == "no-figures-no-tune.json":
        (copy / "gains.png").unlink()
        (copy / "convergence.png").unlink()
    if cut == "bag-cut-in-finish":                     # killed while writing the validation run
        mcap = copy / "session" / "session.mcap"
        mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size * 2 // 3])
        (copy / "session" / "metadata.yaml").unlink()
    rc, out, err = main_result(capsys, "tune", "--resume", copy, "--json")
    assert rc == 0 and "finished already" not in err, err
    got = json.loads(out)
    if cut != "bag-cut-in-finish":
        assert got == result                           # the stored result, seconds included
    assert {k: v for k, v in got.items() if k != "seconds"} == {k: v for k, v in result.items() if k != "seconds"}
    assert json.loads((copy / "tune.json").read_text()) == got
    assert (copy / "gains.png").exists() and (copy / "convergence.png").exists()
    rc, _, err = main_result(capsys, "tune", "--resume", copy)
    one_error_line(rc, err, "finished already")
