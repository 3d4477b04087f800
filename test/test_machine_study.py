"""The machine study's tool (has_control.bench.machines): its drawn machines
are the acceptance class, seeded, and its --reuse refuses what it cannot use
in one line. The study itself is measured, not tested (docs/machines.md)."""
import json

from has_control.bench.machines import MACHINES, drawn_machines, main


def test_drawn_machines_are_seeded_and_in_the_acceptance_class():
    drawn = drawn_machines(20)
    assert drawn == drawn_machines(20) and drawn[:8] == drawn_machines(8)
    assert not {m.name for m in drawn} & {m.name for m in MACHINES}
    for m in drawn:
        p = m.plant
        assert 80.0 <= p["valve_frequency"] <= 150.0 and 0.5 <= p["valve_damping_ratio"] <= 0.9
        assert p["delay"] in (0, 1) and 0.0 <= p["friction_coulomb"] <= 250.0 and 0.0 <= p["friction_stribeck"] <= 300.0
        truth = m.truth()
        assert truth["plant.valve_frequency"] == p["valve_frequency"]
    assert len({m.seed for m in drawn + MACHINES}) == len(drawn) + len(MACHINES)     # Table 1 off differently


def test_reuse_of_another_budget_or_a_foreign_file_is_one_line(tmp_path, capsys):
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"evaluations": 1000, "rows": []}))
    assert main(["--reuse", str(other), "--machines", "in-class"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "its budget is 1000 evaluations, not 2000" in err[0] and str(other) in err[0]
    foreign = tmp_path / "foreign.json"
    foreign.write_text(json.dumps({"evaluations": 2000, "rows": [{"machine": "in-class", "rows": {}}]}))
    assert main(["--reuse", str(foreign), "--machines", "in-class"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a study's JSON" in err[0] and str(foreign) in err[0]
    assert main(["--reuse", str(tmp_path / "missing.json")]) == 2
    assert "missing.json" in capsys.readouterr().err


def test_reuse_takes_the_best_and_paper_rows_of_an_earlier_study(tmp_path):
    from has_control.bench.machines import reused_rows
    row = {"machine": "in-class", "rows": {"best": {"gains": [300.0, 300.0, 300.0]},
                                           "path": {"gains": [280.0, 280.0, 280.0], "predicted": 2e-5, "vouch": []}}}
    f = tmp_path / "earlier.json"
    f.write_text(json.dumps({"evaluations": 2000, "rows": [row]}))
    assert reused_rows(str(f), 2000) == {"in-class": row}
