"""A machine's requirements as the tuning cost (has_control.tuning.requirements):
the paper's J where there are none, a penalty that only a broken requirement
pays, the active ones named, bad files refused in one line."""
import json

import numpy as np
import pytest

from has_control.cli.main import main
from has_control.common.errors import ConfigError
from has_control.config import CONFIG_DIR, build_config
from has_control.core.episode import evaluate_measured
from has_control.core.measures import MEASURES
from has_control.tuning.requirements import Requirements, load_requirements
from has_control.tuning.tuner import load_tuning, tune, tuning_from_json, tuning_json

COLS = ("J", "e_max", "e_mu", "e_sigma") + MEASURES
SPOOL = build_config({"plant.valve_frequency": 100.0, "plant.valve_limit": 5e-3, "simulation.horizon": 3.0},
                     source="test")


def _run(**values):
    row = np.zeros(len(COLS))
    for k, v in values.items():
        row[COLS.index(k)] = v
    return row


def test_met_requirements_cost_the_windowed_j_and_a_broken_one_pays_its_relative_excess():
    req = Requirements(at_stop=0.01, e_max=1e-3, pressure_min=1e6, penalty=10.0)
    ok = _run(J=2.0, J_window=1.0, at_stop=0.005, e_max=5e-4, p_min=2e6)
    assert req.cost(ok[None])[0] == 1.0
    assert Requirements(window=False).cost(ok[None])[0] == 2.0
    broken = _run(J=2.0, J_window=1.0, at_stop=0.02, e_max=5e-4, p_min=0.5e6)     # +100 % and 50 % below
    assert req.cost(broken[None])[0] == pytest.approx(1.0 * (1 + 10.0 * (1.0 + 0.5)))
    assert req.cost(_run(J=np.inf, J_window=np.inf)[None])[0] == np.inf


def test_the_report_names_the_active_requirements():
    req = Requirements(at_stop=0.01, e_max=1e-3)
    rows = {r["requirement"]: r for r in req.report(_run(J_window=1.0, at_stop=0.0099, e_max=1e-4))}
    assert rows["at_stop"]["active"] and rows["at_stop"]["met"]
    assert not rows["e_max"]["active"] and rows["e_max"]["met"]
    rows = {r["requirement"]: r for r in req.report(_run(J_window=1.0, at_stop=0.5, e_max=1e-4))}
    assert not rows["at_stop"]["met"] and rows["at_stop"]["active"]


def test_tuning_to_the_requirements_keeps_the_spool_off_its_stop_and_says_which_are_active():
    req = load_requirements(CONFIG_DIR / "requirements_machine.yaml")
    tuning = load_tuning().replace(evaluations=300, requirements=req)
    res = tune(SPOOL, tuning, diagnostics=False)
    answer = res.as_json()["answer"]
    assert {r["requirement"] for r in answer["requirements"]} == set(req.limits())
    run = evaluate_measured(np.array([res.gains]), [SPOOL])[0, 0]
    assert run[COLS.index("at_stop")] <= req.at_stop and run[COLS.index("hf_rms")] <= req.hf_rms
    assert res.result.fun == pytest.approx(answer["J_requirements"], rel=1e-12)
    assert any(line.startswith("requirement at_stop") for line in res.lines())
    back = tuning_from_json(json.loads(json.dumps(tuning_json(tuning))))      # a session's settings resume
    assert back.requirements == req


def test_the_reference_tuning_has_no_answer_block():
    res = tune(None, load_tuning().replace(evaluations=40), diagnostics=False)
    assert "answer" not in res.as_json() and res.lines() == []


@pytest.mark.parametrize("text, culprit", [
    ("requirements:\n  at_stop: -1.0\n", "requirements.at_stop"),
    ("requirements:\n  hf_frequency: 0.0\n", "requirements.hf_frequency"),
    ("requirements:\n  window: 1\n", "requirements.window"),
    ("requirements:\n  nonsense: 1.0\n", "requirements.nonsense"),
    ("requirements:\n  pressure_min: 2.0e7\n  pressure_max: 1.0e7\n", "pressure_min"),
    ("gains:\n  k1: 200.0\n", "requirements"),
])
def test_a_bad_requirements_file_is_one_line_naming_file_and_key(tmp_path, capsys, text, culprit):
    f = tmp_path / "req.yaml"
    f.write_text("/**:\n  ros__parameters:\n" + "".join("    " + line + "\n" for line in text.splitlines()))
    with pytest.raises(ConfigError):
        load_requirements(f)
    rc = main(["tune", "--evaluations", "20", "--requirements", str(f)])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and culprit in err and str(f) in err, err


def test_requirements_with_dask_or_a_resume_are_refused_in_one_line(tmp_path, capsys):
    req = str(CONFIG_DIR / "requirements_machine.yaml")
    for argv in (["tune", "--requirements", req, "--dask", "local:1"],
                 ["tune", "--requirements", req, "--resume", str(tmp_path)]):
        rc = main(argv)
        err = capsys.readouterr().err
        assert rc == 2 and len(err.strip().splitlines()) == 1 and "--requirements" in err, err
