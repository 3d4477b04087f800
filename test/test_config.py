"""Parameter files: the shipped ones are the reference configuration; bad ones fail in one line (YAML
aliases, deep nesting, duplicate keys, values beyond the limits, a FIFO, a device or an oversize file)."""
import os
import time

import pytest
from conftest import one_line

from has_control.config import CONFIG_DIR, config_parameters, load_config
from has_control.common.errors import ConfigError
from has_control.core.params import Config


def test_shipped_files_are_the_reference_configuration():
    assert load_config() == Config()
    assert (CONFIG_DIR / "actuator.yaml").read_text().count("/**:") == 1


def test_parameters_round_trip():
    from has_control.config import build_config
    assert build_config(config_parameters(Config())) == Config()


def _write(tmp_path, body: str, name="bad.yaml"):
    p = tmp_path / name
    p.write_text("/**:\n  ros__parameters:\n" + body)
    return p


@pytest.mark.parametrize("body, key, value", [
    ("    actuator:\n      mass: -1500.0\n", "actuator.mass", "-1500.0"),
    ("    actuator:\n      area_cap: 0.0\n", "actuator.area_cap", "0.0"),
    ("    actuator:\n      volume_rod0: -1.0e-3\n", "actuator.volume_rod0", "-0.001"),
    ("    simulation:\n      step: 0.0\n", "simulation.step", "0.0"),
    ("    actuator:\n      supply_pressure: 1.0e+5\n      return_pressure: 2.0e+5\n",
     "actuator.supply_pressure", "100000.0"),
    ("    adaptation:\n      lower: [3500.0, 4.0e-12]\n", "adaptation.lower", "3500.0"),
    ("    metrics:\n      skip_end: 12.0\n", "metrics.skip_end", "12.0"),
    ("    actuator:\n      mas: 1500.0\n", "actuator.mas", "unknown parameter"),
    ("    actuator:\n      mass: '1500'\n", "actuator.mass", "'1500'"),
    ("    gains:\n      k1: .nan\n", "gains.k1", "nan"),
    ("    reference:\n      kind: square\n", "reference.kind", "square"),
])
def test_bad_values_name_file_key_and_value(tmp_path, body, key, value):
    path = _write(tmp_path, body)
    with pytest.raises(ConfigError) as info:
        load_config([path])
    msg = str(info.value)
    assert "\n" not in msg
    assert str(path) in msg and key in msg and value in msg


def test_malformed_files(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("/**:\n  ros__parameters: [\n")
    with pytest.raises(ConfigError, match="broken.yaml: not valid YAML"):
        load_config([p])
    p.write_text("actuator:\n  mass: 3\n")
    with pytest.raises(ConfigError, match="has no ros__parameters"):
        load_config([p])
    with pytest.raises(ConfigError, match="missing.yaml: cannot read"):
        load_config([tmp_path / "missing.yaml"])


def test_later_files_override_earlier_ones_and_yaml_floats_read_like_ros(tmp_path):
    p = _write(tmp_path, "    actuator:\n      mass: 1.2e3\n    gains:\n      k1: 2e2\n")
    cfg = load_config([p])
    assert cfg.actuator.mass == 1200.0 and cfg.gains.k1 == 200.0


@pytest.mark.ros
def test_sections_apply_to_the_nodes_they_name_as_rcl_decides(tmp_path):
    from has_control.config import load_config, node_matches, read_parameter_file
    assert node_matches("/**", "/sim0/plant") and node_matches("controller", "/controller")
    assert node_matches("/**/controller", "/sim0/controller") and not node_matches("/plant", "/controller")
    assert not node_matches("/controller", "/sim0/controller") and node_matches("/sim0/*", "/sim0/plant")
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    gains: {k1: 150.0}\n    actuator: {mass: 1400.0}\n"
                 "/controller:\n  ros__parameters:\n    gains: {k1: 400.0}\n"
                 "/plant:\n  ros__parameters:\n    simulation: {y_limit: 0.5}\n"
                 "/recorder:\n  ros__parameters:\n    gains: {k2: 1.0}\n")
    assert read_parameter_file(p, "/plant") == {"gains.k1": 150.0, "actuator.mass": 1400.0,
                                                "simulation.y_limit": 0.5}
    assert read_parameter_file(p, "/controller") == {"gains.k1": 400.0, "actuator.mass": 1400.0}
    cfg = load_config([p])                                  # the library: the controller's gains, one model
    assert cfg.gains.k1 == 400.0 and cfg.gains.k2 == 158.0 and cfg.actuator.mass == 1400.0
    assert cfg.episode.y_limit == 0.5
    q = tmp_path / "q.yaml"
    q.write_text("/plant:\n  ros__parameters:\n    actuator: {mass: 1000.0}\n"
                 "/controller:\n  ros__parameters:\n    actuator: {mass: 1500.0}\n")
    with pytest.raises(ConfigError, match=r"actuator.mass = 1000.0 for /plant .* 1500.0 for /controller"):
        load_config([q])


def test_the_shipped_files_comments_derive_from_the_parameter_tables():
    """One table per component: each value line's comment in config/*.yaml is its Param's
    meaning and unit (regenerate with has_control.config.yaml_with_comments after editing a table)."""
    from has_control.config import CONFIG_DIR, CONFIG_TABLE, yaml_with_comments
    from has_control.tuning.parameters import TUNING_TABLE
    tables = {**CONFIG_TABLE, **TUNING_TABLE}
    for name in ("actuator.yaml", "controller.yaml", "simulation.yaml", "plant.yaml", "tuner.yaml"):
        text = (CONFIG_DIR / name).read_text()
        assert yaml_with_comments(text, tables) == text, name
    assert "# m, moving mass [kg]" in (CONFIG_DIR / "actuator.yaml").read_text()


def test_a_parameter_table_checks_type_range_and_choices_in_one_line():
    from has_control.config import CONFIG_TABLE, refusal
    assert refusal(CONFIG_TABLE, "gains.k1", 300) is None                      # a whole number for a double
    assert refusal(CONFIG_TABLE, "gains.k1", -1.0) == "gains.k1 = -1.0: must be > 0 and <= 1e+06"
    assert refusal(CONFIG_TABLE, "plant.delay", 17) == "plant.delay = 17: must be a whole number in [0, 16]"
    assert "expected one of" in refusal(CONFIG_TABLE, "reference.kind", "square")
    assert refusal(CONFIG_TABLE, "noise.seed", -1) == "noise.seed = -1: expected a whole number in [0, 2^63)"
    assert refusal(CONFIG_TABLE, "adaptation.gain", [1.0]) == \
        "adaptation.gain = [1.0]: expected a list of two numbers"


HEAD = "/**:\n  ros__parameters:\n"


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
