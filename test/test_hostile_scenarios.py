"""Hostile input on issue #14's surfaces: scenario files, road parameters, robustness labels,
aggregates stored in a session, and the plant options reaching every node."""
from __future__ import annotations

import pytest

from has_control.errors import ConfigError
from has_control.scenarios import load_scenarios


@pytest.mark.parametrize("body,culprit", [
    ("1: x\nfoo: y\n", "not 1, foo"),
    ("random: {count: 2, 1: 2, foo: 3}\n", "random.1: unknown key"),
    ("random: {count: 2, ranges: {plant.mass: [1, " + "9" * 400 + "]}}\n", "random.ranges.plant.mass"),
])
def test_scenario_files_with_odd_keys_or_huge_numbers_are_one_line(tmp_path, body, culprit):
    p = tmp_path / "s.yaml"
    p.write_text(body)
    with pytest.raises(ConfigError) as err:
        load_scenarios(p)
    assert "\n" not in str(err.value) and str(p) in str(err.value) and culprit in str(err.value), str(err.value)
