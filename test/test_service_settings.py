"""The tuner node's settings checks (has_control.tuning.service_settings), from a dict: no ROS."""
import pytest

from has_control.common.errors import ConfigError
from has_control.config import config_parameters
from has_control.core.params import Config
from has_control.tuning.parameters import TUNING_TABLE
from has_control.tuning.service_settings import OWN_PARAMETERS, TUNER_TABLE, settings_from
from has_control.tuning.tuner import load_tuning, tuning_parameters
from has_control.tuning.validation import VALIDATION_TOLERANCE

WHERE = "parameter of /tuner"


def _read(**changes):
    values = {**tuning_parameters(load_tuning()), **{k: p.default for k, p in OWN_PARAMETERS.items()}, **changes}
    asked = []

    def cfg():
        asked.append(True)
        return Config()
    return (lambda: settings_from(values.__getitem__, cfg, WHERE)), asked


def test_the_defaults_give_the_batch_evaluator_on_the_model_validated():
    read, asked = _read()
    s = read()
    assert asked == [True] and s.cfg == Config() and s.tuning == load_tuning()
    assert (s.evaluator, s.record, s.resume, s.force, s.validate) == ("batch", None, None, False, True)
    assert (s.episode_timeout, s.tolerance, s.log_every, s.lane_timeout) == (120.0, VALIDATION_TOLERANCE, 1, 30.0)
    assert set(TUNER_TABLE) >= set(TUNING_TABLE) | set(OWN_PARAMETERS) | set(config_parameters(Config()))


def test_a_record_directory_and_the_tunings_own_keys_are_read():
    read, _ = _read(record="/tmp/x", resume="", log_every=5, **{"swarm.particles": 4})
    s = read()
    assert s.record == "/tmp/x" and s.resume is None and s.log_every == 5 and s.tuning.swarm.particles == 4


@pytest.mark.parametrize("changes, culprit", [
    ({"evaluator": "fast"}, "evaluator = 'fast'"),
    ({"log_every": 0}, "log_every"),
    ({"episode_timeout": 0.0}, "episode_timeout"),
    ({"validation_tolerance": -1.0}, "validation_tolerance"),
])
def test_a_bad_own_parameter_is_one_line_before_the_model_is_read(changes, culprit):
    read, asked = _read(**changes)
    with pytest.raises(ConfigError) as err:
        read()
    assert str(err.value).startswith(WHERE) and culprit in str(err.value) and "\n" not in str(err.value)
    assert asked == []


@pytest.mark.parametrize("changes, why", [
    ({"scenarios": "config/scenarios.yaml", "evaluator": "graph"}, "needs evaluator batch"),
    ({"aggregate": "max"}, "needs parameter scenarios"),
    ({"scenarios": "config/scenarios.yaml", "aggregate": ""}, "parameter aggregate"),
    ({"swarm.particles": 0}, "swarm.particles"),
])
def test_the_checks_tune_makes_name_the_parameter(changes, why):
    read, _ = _read(**changes)
    with pytest.raises(ConfigError, match=why):
        read()


def test_scenarios_with_the_batch_evaluator_make_a_robust_tuning():
    read, _ = _read(scenarios="config/scenarios.yaml", aggregate="max")
    s = read()
    assert s.tuning.scenarios and s.tuning.aggregate.kind == "max"
