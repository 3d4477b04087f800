"""The command line's entry point: has-control simulate's JSON keys, errors as one line and exit status 2
(in-process, and once on a real interpreter: the entry point prints the one line, no traceback), out of
memory and a closed standard output; the live view's --foxglove-wait checked before any run; numbers out of
range and bad arguments refused in one line before any work."""
import json
import subprocess
import sys
import time

import pytest
from conftest import CLI, argparse_error, one_line, run_main

from test_episode import PINNED

from has_control.cli import main


def run(*args):
    return subprocess.run([sys.executable, "-m", "has_control.cli", *args],
                          capture_output=True, text=True, timeout=300)


def test_simulate_json_gives_the_reference_numbers():
    r = run("simulate", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert set(out) == {"J", "e_max", "e_mu", "e_sigma", "samples", "diverged"}
    assert out["samples"] == 33333 and out["diverged"] is False
    assert [out[k] for k in ("J", "e_max", "e_mu", "e_sigma")] == pytest.approx(
        PINNED[(150.0, 158.0, 162.0)], rel=1e-12)


def test_diverged_run_prints_inf_as_string():
    r = run("simulate", "--gains", "1e4", "1e4", "1e4", "--json", "--duration", "2")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["J"] == "inf" and out["diverged"] is True


@pytest.mark.system
def test_trace_and_plot_files(tmp_path):
    csv, png = tmp_path / "t.csv", tmp_path / "p.png"
    r = run("simulate", "--duration", "1.5", "--trace", str(csv), "--plot", str(png))
    assert r.returncode == 0, r.stderr
    lines = csv.read_text().splitlines()
    assert lines[0] == ("t [s],x1d [m],y [m],ydot [m/s],P1 [Pa],P2 [Pa],u [m],e1 [m],e2 [m/s],e3 [N],"
                        "a1_hat [N*s/m],a2_hat [m^3/(s*Pa)]") and len(lines) == 1 + 5000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, culprit", [
    (["--gains", "150", "-1", "162"], "--gains: K2 = '-1'"),
    (["--gains", "150", "abc", "162"], "--gains: K2 = 'abc'"),
    (["--duration", "0.9"], "metrics.skip"),
])
def test_bad_arguments_fail_in_one_line(args, culprit, capsys):
    r = run_main(capsys, "simulate", *args)
    assert r.returncode == 2
    assert culprit in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_bad_config_file_fails_in_one_line(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("/**:\n  ros__parameters:\n    actuator:\n      mass: 0\n")
    r = run("simulate", "--config", str(p))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == f"has-control: error: {p}: actuator.mass = 0: must be > 0"


def test_out_of_memory_is_one_line_and_exit_2_even_with_a_thread_left():
    """The shutdown after a MemoryError could wait for anything (here a thread that
    sleeps a minute); the program leaves at once."""
    code = ("import sys, threading, time\n"
            "import has_control.cli.simulate as s\n"
            "def run(args):\n"
            "    threading.Thread(target=time.sleep, args=(60,)).start()\n"
            "    raise MemoryError\n"
            "s.run = run\n"
            "sys.argv = ['has-control', 'simulate']\n"
            "from has_control.cli.main import main\n"
            "sys.exit(main())\n")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50)
    assert r.returncode == 2 and r.stderr.strip() == "has-control: error: out of memory", r.stderr
    assert time.monotonic() - t0 < 30


def test_a_closed_standard_output_ends_quietly_with_141():
    """As ``yes | head`` does: no "(path unknown): Broken pipe", no traceback; status 128 + SIGPIPE."""
    p = subprocess.Popen(CLI + ["simulate", "--duration", "2", "--json"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.close()                                         # the reader is gone before the answer
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141 and err == "", err


@pytest.mark.parametrize("value", ["nan", "inf", "1e308", "-1", "3601"])
def test_foxglove_wait_is_a_bounded_number(capsys, value):
    with pytest.raises(SystemExit) as e:
        main(["stack", "--foxglove", "--foxglove-wait", value])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1
    assert "--foxglove-wait" in err and repr(value) in err and "0 .. 3600" in err


def test_foxglove_wait_without_foxglove_is_refused(capsys):
    one_line(capsys, ["stack", "--foxglove-wait", "3"], "--foxglove-wait 3", "only with --foxglove")


@pytest.mark.parametrize("argv, culprits", [
    (["simulate", "--duration", "1e9"], ["--duration", "simulation.horizon", "limit"]),
    (["tune", "--duration", "1e308"], ["--duration", "simulation.horizon", "limit"]),
    (["tune", "--particles", "99999999999"], ["swarm.particles", "limit"]),
    (["tune", "--particles", "9" * 400], ["swarm.particles", "limit"]),
    (["tune", "--particles", "100000", "--iterations", "1000"], ["swarm.iterations", "evaluations"]),
    (["tune", "--seed", "-1"], ["swarm.seed = -1"]),
    (["simulate", "--gains", "2e6", "150", "150"], ["--gains: K1 = '2e6'", "1e+06"]),
    (["stack", "--gains", "2e6", "150", "150"], ["--gains: K1 = '2e6'", "1e+06"]),
    (["simulate", "--gains", "inf", "150", "150"], ["--gains: K1 = 'inf'"]),
])
def test_numbers_out_of_range_are_one_line(capsys, argv, culprits):
    one_line(capsys, argv, *culprits)


@pytest.mark.parametrize("argv, culprits", [
    (["replay", "--rate", "1e-300", "x"], ["--rate", "1e-300"]),
    (["replay", "--rate", "nan", "x"], ["--rate"]),
    (["replay", "--controller", "--tolerance", "-1", "x"], ["--tolerance"]),
    (["stack", "--namespace", "a b"], ["--namespace", "'a b'"]),
    (["stack", "--namespace", "/1x"], ["--namespace"]),
    (["stack", "--tune", "--lanes", "/ok", "bad//ns"], ["--lanes"]),
])
def test_bad_arguments_are_one_argparse_line(capsys, argv, culprits):
    argparse_error(capsys, argv, *culprits)


def test_good_namespaces_pass():
    from has_control.cli.args import namespace as _namespace
    for ns in ("", "/", "/sim0", "sim0", "/a/b_2", "_x"):
        assert _namespace(ns) == ns
