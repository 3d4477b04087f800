"""identify refuses, before any work, outputs that would clobber an input or
each other, a recording given twice and a bound given twice; its JSON never
carries a non-finite float."""
import json
import math

import pytest

from has_control.bag import BagWriter, PARAMETERS_KEY, parameters_json, write_trace
from has_control.cli.identify import finite_json
from has_control.cli.main import main
from has_control.config import build_config
from has_control.core.episode import simulate


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    cfg = build_config({"simulation.horizon": 1.5})
    path = tmp_path_factory.mktemp("identify_input") / "run"
    w = BagWriter(path, {PARAMETERS_KEY: parameters_json(cfg)})
    write_trace(w, simulate(cfg), cfg)
    w.close()
    return path


def _one_line(capsys, argv) -> str:
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    return err[0]


def test_an_output_inside_an_input_bag_is_refused_and_the_bag_kept(capsys, bag):
    before = (bag / "metadata.yaml").read_bytes()
    line = _one_line(capsys, ["identify", str(bag), "--out", str(bag / "metadata.yaml")])
    assert "--out" in line and "input" in line
    assert (bag / "metadata.yaml").read_bytes() == before


def test_two_outputs_on_one_file_are_refused(capsys, bag, tmp_path):
    held = tmp_path / "held"
    cfg = build_config({"simulation.horizon": 1.5, "reference.omega": 9.0})
    w = BagWriter(held, {PARAMETERS_KEY: parameters_json(cfg)})
    write_trace(w, simulate(cfg), cfg)
    w.close()
    same = tmp_path / "same.png"
    line = _one_line(capsys, ["identify", str(bag), "--validate", str(held), "--out", str(same), "--plot", str(same)])
    assert "two outputs" in line and "--plot" in line
    assert not same.exists()


def test_the_same_recording_twice_is_refused(capsys, bag):
    assert "given twice" in _one_line(capsys, ["identify", str(bag), str(bag)])


def test_a_bound_given_twice_is_refused(capsys, bag):
    line = _one_line(capsys, ["identify", str(bag), "--bound", "mass", "1000", "2000", "--bound", "mass", "1", "2"])
    assert "--bound mass" in line and "twice" in line


def test_json_carries_no_non_finite_float():
    doc = finite_json({"a": math.inf, "b": [1.0, math.nan], "c": {"d": -math.inf, "e": 2}})
    assert json.loads(json.dumps(doc, allow_nan=False)) == {"a": None, "b": [1.0, None], "c": {"d": None, "e": 2}}
