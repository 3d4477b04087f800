"""Resource limits: numbers and files that are refused with one line and
exit 2 (resource limits before allocation, sizes before parsing, regular files
only), and Ctrl-C in the first second ending with one line and exit 130."""
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import argparse_error, one_line


HEAD = "/**:\n  ros__parameters:\n"


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


def _yaml(tmp_path, name, body):
    p = tmp_path / name
    p.write_text(HEAD + body) if isinstance(body, str) else p.write_bytes(body)
    return p


def _bomb():
    lines = ["    swarm:", "      a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"      a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 9)]
    return "\n".join(lines) + "\n"


CONFIGS = {
    "binary": (b"\xff\xfe\x00\x01binary\x80", ["not UTF-8"]),
    "self-alias": ("    actuator:\n      mass: &m [*m]\n", ["alias *m"]),
    "alias-bomb": (_bomb(), ["alias *a0"]),
    "deep": ("    x: " + "[" * 2000 + "]" * 2000 + "\n", ["nested deeper"]),
    "int-400-digits": ("    actuator:\n      mass: " + "9" * 400 + "\n", ["actuator.mass", "finite"]),
    "int-5000-digits": ("    actuator:\n      mass: " + "9" * 5000 + "\n", ["not valid YAML"]),
    "tiny-step": ("    simulation:\n      step: 1.0e-9\n", ["simulation.step = 1e-09", "limit"]),
    "dup-key": ("    actuator:\n      mass: 1.0\n      mass: 2.0\n", ["duplicate key 'mass'", "line 5"]),
    "dup-block": ("    actuator:\n      mass: 1500.0\n    actuator:\n      damping: 1.0\n",
                  ["duplicate key 'actuator'"]),
    "negative-bounds": ("    swarm:\n      lower: [-5.0, -5.0, -5.0]\n      upper: [-1.0, -1.0, -1.0]\n",
                        ["swarm.lower[0] = -5"]),
    "upper-beyond-gain-range": ("    swarm:\n      upper: [2.0e6, 800.0, 800.0]\n", ["swarm.upper[0]"]),
    "inertia-inf": ("    swarm:\n      inertia_max: .inf\n", ["swarm.inertia_max = inf", "finite"]),
    "particles-300-digits": ("    swarm:\n      particles: " + "9" * 300 + "\n", ["swarm.particles", "limit"]),
}


@pytest.mark.parametrize("case", sorted(CONFIGS))
def test_hostile_config_files_are_one_line_naming_the_file(capsys, tmp_path, case):
    body, culprits = CONFIGS[case]
    p = _yaml(tmp_path, f"{case}.yaml", body)
    t0 = time.perf_counter()
    one_line(capsys, ["tune", "--iterations", "1", "--particles", "2", "--config", str(p)], str(p), *culprits)
    assert time.perf_counter() - t0 < 5


def test_fifo_device_directory_and_oversize_file_are_refused_without_reading(capsys, tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    big = tmp_path / "big.yaml"
    big.write_text(HEAD + "#" * (2 << 20))
    for path, why in ((fifo, "not a regular file"), ("/dev/zero", "not a regular file"),
                      (tmp_path, "a directory"), (big, "larger than the limit")):
        one_line(capsys, ["simulate", "--config", str(path)], str(path), why)
        one_line(capsys, ["bag-info", str(path)] if path != tmp_path else ["bag-info", str(fifo)],
                 "not a regular file" if path != big else "MCAP")


@pytest.mark.ros
def test_ctrl_c_in_the_first_second_is_one_line_and_130():
    for args in (["tune", "--variant", "pso-cp-tvac", "--iterations", "1", "--particles", "2"],
                 ["stack", "--duration", "2"]):
        p = subprocess.Popen([sys.executable, "-m", "has_control.cli", *args],
                             stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
        time.sleep(0.4)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
        assert p.returncode == 130 and "Traceback" not in err, (args[0], err)
        assert err.strip().splitlines() == ["has-control: interrupted"], err
