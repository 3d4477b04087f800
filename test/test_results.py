"""Results that a kill or a race could strand or overwrite.
Result files are written then renamed, a session directory is locked,
outputs are checked before the work starts and never replaced without
--force, an interrupted final write is finished by --resume, and every I/O
error names its path."""
import errno
import json
import shutil
import time

import pytest
from conftest import one_error_line

from has_control.cli import main
from has_control.common.errors import HasControlError
from has_control.common.files import DirectoryLock, write_atomic

TUNE = ["tune", "--variant", "pso-cp-tvac", "--particles", "4", "--iterations", "3", "--duration", "1.5"]


def run(capsys, *argv):
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


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
    rc, _, err = run(capsys, *TUNE, "--out", copy)
    one_error_line(rc, err, str(copy / "session"), "--force")
    assert time.perf_counter() - t0 < 2 and (copy / "tune.json").read_bytes() == before
    (copy / "session").rename(copy / "elsewhere")          # tune.json alone is protected as well
    rc, _, err = run(capsys, *TUNE, "--out", copy)
    one_error_line(rc, err, str(copy / "tune.json"))
    rc, out, err = run(capsys, *TUNE, "--out", copy, "--force", "--json")
    assert rc == 0, err
    assert json.loads((copy / "tune.json").read_text())["gains"] == result["gains"]


def test_reproduce_out_is_checked_before_the_work_starts(tmp_path, capsys):
    f = tmp_path / "report.md"
    f.write_text("someone's report\n")
    full = tmp_path / "full"
    full.mkdir()
    (full / "report.md").write_text("someone's report\n")
    for out, why in ((f, "not a directory"), (full, "--force")):
        t0 = time.perf_counter()
        rc, _, err = run(capsys, "reproduce", "--seeds", "1", "--particles", "2", "--iterations", "1", "--out", out)
        one_error_line(rc, err, str(out), why)
        assert time.perf_counter() - t0 < 2
    assert f.read_text() == (full / "report.md").read_text() == "someone's report\n"


def test_a_second_resume_on_a_locked_session_is_refused(finished, tmp_path, capsys):
    d, _ = finished
    copy = tmp_path / "s"
    shutil.copytree(d, copy)
    lock = DirectoryLock(copy, ".lock", "the tuning session")      # as a running tune holds it
    try:
        rc, _, err = run(capsys, "tune", "--resume", copy)
        one_error_line(rc, err, str(copy), "in use by another process")
        rc, _, err = run(capsys, *TUNE, "--out", copy, "--force")
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
    rc, out, err = run(capsys, "tune", "--resume", copy, "--json")
    assert rc == 0 and "finished already" not in err, err
    got = json.loads(out)
    if cut != "bag-cut-in-finish":
        assert got == result                           # the stored result, seconds included
    assert {k: v for k, v in got.items() if k != "seconds"} == {k: v for k, v in result.items() if k != "seconds"}
    assert json.loads((copy / "tune.json").read_text()) == got
    assert (copy / "gains.png").exists() and (copy / "convergence.png").exists()
    rc, _, err = run(capsys, "tune", "--resume", copy)
    one_error_line(rc, err, "finished already")


def test_write_atomic_keeps_the_old_file_and_names_the_path(tmp_path):
    p = tmp_path / "tune.json"
    p.write_text("old\n")

    def full_disk(tmp):
        tmp.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    with pytest.raises(HasControlError) as info:
        write_atomic(p, full_disk)
    assert str(info.value) == f"{p}: cannot write: No space left on device"
    assert p.read_text() == "old\n" and [x.name for x in tmp_path.iterdir()] == ["tune.json"]


def test_a_full_disk_under_the_bag_writer_names_the_bag(tmp_path, capsys, monkeypatch):
    import has_control.cli.bag_info as bag_info
    from has_control.bag import BagWriter, STRING

    def record_to_a_full_disk(args):
        w = BagWriter(tmp_path / "bag")
        w._mcap._file.close()
        w._mcap._file = open("/dev/full", "wb", buffering=0)
        w.add_topic("/x", STRING)
        w.write("/x", 1, b"\0" * 64)
        w.sync()
    monkeypatch.setattr(bag_info, "run", record_to_a_full_disk)
    rc, _, err = run(capsys, "bag-info", "x")
    one_error_line(rc, err, str(tmp_path / "bag" / "bag.mcap"), "No space left on device")
