"""Scenario files that draw relative to the plant they are loaded over (scale:),
for robust tuning around an identified machine."""
import pytest

from has_control.common.errors import ConfigError
from has_control.config import CONFIG_DIR, build_config
from has_control.config.scenario_files import load_scenarios


def test_the_machine_file_draws_around_the_identified_plant():
    ident = build_config({"plant.mass": 1700.0, "plant.valve_frequency": 100.0, "plant.valve_damping_ratio": 0.7,
                          "plant.valve_limit": 5e-3})
    drawn = load_scenarios(CONFIG_DIR / "scenarios_machine.yaml", ident)
    assert len(drawn) == 20 and drawn[0].name == "identified"
    cfgs = [s.config(ident) for s in drawn[1:]]
    assert all(0.97 * 1700.0 <= c.plant.mass <= 1.03 * 1700.0 for c in cfgs)
    assert all(85.0 <= c.plant.valve_frequency <= 115.0 for c in cfgs)
    assert all(c.plant.valve_time_constant == 0.0 for c in cfgs)          # 0 stays 0: the spool stays second order
    assert {c.plant.delay for c in cfgs} == {0, 1}
    assert all(c.plant.valve_limit == 5e-3 for c in cfgs)                 # what is not drawn stays the base's
    other = load_scenarios(CONFIG_DIR / "scenarios_machine.yaml", build_config({"plant.mass": 1200.0}))
    assert all(0.97 * 1200.0 <= s.config(build_config({})).plant.mass <= 1.03 * 1200.0 for s in other[1:])


def test_a_bad_scale_is_one_line_naming_the_key(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text("random: {count: 2, seed: 1, scale: {plant.mass: [1.1, 0.9]}}\n")
    with pytest.raises(ConfigError, match="scale.plant.mass"):
        load_scenarios(f)
    f.write_text("random: {count: 2, seed: 1, scale: {noise.seed: [0.5, 2]}}\n")
    with pytest.raises(ConfigError, match="scale.noise.seed"):
        load_scenarios(f)


def test_scaled_friction_keeps_its_shape_and_a_lag_stays_at_least_a_step():
    ident = build_config({"plant.valve_time_constant": 3e-4, "plant.friction_coulomb": 200.0,
                          "plant.friction_stribeck": 200.0})
    cfgs = [s.config(ident) for s in load_scenarios(CONFIG_DIR / "scenarios_machine.yaml", ident)[1:]]
    assert all(c.plant.friction_stribeck == c.plant.friction_coulomb for c in cfgs)
    assert all(c.plant.valve_time_constant >= ident.episode.step for c in cfgs)
