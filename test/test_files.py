"""Outputs as has_control.common.files writes them: check_output refuses what is not a regular file (a FIFO,
a device, a directory) before the work starts; write_atomic writes through a symlink and names the user's
path, never its temporary file, when it fails, and keeps the old file; a command's outputs are checked
before its work starts."""
import errno
import os
import stat
import time

import pytest
from conftest import main_result, NOM, one_error_line, one_line

from has_control.cli import main
from has_control.common.errors import HasControlError
from has_control.common.files import check_output, write_atomic


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


def test_reproduce_out_is_checked_before_the_work_starts(tmp_path, capsys):
    f = tmp_path / "report.md"
    f.write_text("someone's report\n")
    full = tmp_path / "full"
    full.mkdir()
    (full / "report.md").write_text("someone's report\n")
    for out, why in ((f, "not a directory"), (full, "--force")):
        t0 = time.perf_counter()
        rc, _, err = main_result(capsys, "reproduce", "--seeds", "1", "--particles", "2", "--iterations", "1",
                                 "--out", out)
        one_error_line(rc, err, str(out), why)
        assert time.perf_counter() - t0 < 2
    assert f.read_text() == (full / "report.md").read_text() == "someone's report\n"


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
