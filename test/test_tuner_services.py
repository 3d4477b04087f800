"""The tuner node driven through services: ~/start, ~/cancel, ~/status; the
batch evaluator without any plant or controller."""
import time

import pytest
from conftest import spin_until
import rclpy
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from has_control.config import config_parameters, with_horizon
from has_control.core.params import Config
from has_control.nodes.tuner_node import TunerNode
from has_control.tuning.tuner import load_tuning, tune

pytestmark = [pytest.mark.ros]


def _tuner(context, **swarm):
    cfg = with_horizon(Config(), 1.5)
    params = [Parameter(k, value=v) for k, v in config_parameters(cfg).items()]
    params += [Parameter(f"swarm.{k}", value=v) for k, v in swarm.items()]
    params += [Parameter("evaluator", value="batch"), Parameter("lane_timeout", value=0.5)]
    return cfg, TunerNode(context=context, parameter_overrides=params)


def test_the_batch_evaluator_needs_no_plant_or_controller(context):
    cfg, tuner = _tuner(context, variant="pso-cp-tvac", iterations=2, particles=3)
    ex = EventsExecutor(context=context)
    ex.add_node(tuner)
    try:
        tuner.start()
        assert spin_until(ex, tuner.done.is_set, 120)
    finally:
        ex.shutdown()
        tuner.destroy_node()
    ref = tune(cfg, load_tuning().replace(variant="pso-cp-tvac", iterations=2, particles=3))
    assert tuner.error is None and tuner.result["gains"] == list(ref.gains)
    assert tuner.result["validation"]["J"] == ref.result.fun          # validated in-process
    assert tuner.result["controller_gains"] is None and tuner.result["lanes"] == []
    assert tuner.status.startswith("finished")


def test_start_cancel_and_status_through_services(context):
    _, tuner = _tuner(context, variant="pso-cp-tvac", iterations=100000, particles=3)
    client = rclpy.create_node("operator", context=context)
    ex = EventsExecutor(context=context)
    for n in (tuner, client):
        ex.add_node(n)

    def call(name):
        cli = client.create_client(Trigger, f"/tuner/{name}")
        assert cli.wait_for_service(timeout_sec=10.0)
        fut = cli.call_async(Trigger.Request())
        assert spin_until(ex, fut.done, 10)
        return fut.result()
    try:
        assert call("status").message.startswith("idle")
        assert not call("cancel").success                                 # nothing to cancel
        assert call("start").success
        assert spin_until(ex, lambda: "iteration" in call("status").message, 60)
        assert not call("start").success                                  # one session at a time
        assert call("cancel").success
        assert spin_until(ex, tuner.done.is_set, 30)
        assert call("status").message == "cancelled" and tuner.result is None and tuner.error is None
        assert call("start").success                                      # and again
        assert spin_until(ex, lambda: "iteration" in call("status").message, 60)
        assert call("cancel").success and spin_until(ex, tuner.done.is_set, 30)
    finally:
        ex.shutdown()
        tuner.destroy_node()
        client.destroy_node()


def _service(ex, client, name):
    cli = client.create_client(Trigger, name)
    assert cli.wait_for_service(timeout_sec=10.0)
    fut = cli.call_async(Trigger.Request())
    assert spin_until(ex, fut.done, 10)
    return fut.result()


@pytest.mark.parametrize("name,value,why", [
    ("swarm.iterations", 10**12, "swarm.iterations"),
    ("swarm.variant", "garbage", "expected one of"),
    ("evaluator", "garbage", "expected one of batch, graph"),
    ("scenarios", "nope.yaml", "nope.yaml"),
    ("aggregate", "cvar:7", "cvar:7"),
    ("episode_timeout", -1.0, "must be > 0"),
    ("simulation.horizon", 1e9, "more than the limit"),
    ("swarm.lower", [2000.0, 2000.0, 2000.0], "lower 2000 must be below upper 1200"),
    ("lanes", ["/sim9"], "read-only"),
])
def test_a_bad_setting_is_refused_when_set_and_the_old_value_kept(context, name, value, why):
    """Refused at set time by the CLI's checks, with the reason; the old value stays."""
    _, tuner = _tuner(context)
    try:
        before = tuner.get_parameter(name).value
        res = tuner.set_parameters([Parameter(name, value=value)])[0]
        assert not res.successful and why in res.reason, res.reason
        after = tuner.get_parameter(name).value
        assert (list(after) if hasattr(after, "tolist") or isinstance(after, list) else after) == \
            (list(before) if hasattr(before, "tolist") or isinstance(before, list) else before)
    finally:
        tuner.destroy_node()


def test_a_valid_change_between_sessions_takes_effect_at_the_next_start(context):
    """The settings are read at ~/start, not frozen at construction."""
    cfg, tuner = _tuner(context, variant="pso-cp-tvac", iterations=2, particles=3)
    ex = EventsExecutor(context=context)
    ex.add_node(tuner)
    try:
        assert tuner.start() is None and spin_until(ex, tuner.done.is_set, 120)
        assert tuner.result["iterations"] == 2
        assert tuner.set_parameters([Parameter("swarm.iterations", value=3),
                                     Parameter("swarm.upper", value=[900, 700, 700])])[0].successful  # whole numbers
        assert tuner.start() is None and spin_until(ex, tuner.done.is_set, 120)
    finally:
        ex.shutdown()
        tuner.destroy_node()
    ref = tune(cfg, load_tuning().replace(variant="pso-cp-tvac", iterations=3, particles=3,
                                          upper=(900.0, 700.0, 700.0)))
    assert tuner.result["iterations"] == 3 and tuner.result["gains"] == list(ref.gains)


def test_record_without_lanes_writes_the_result_and_a_second_start_needs_force(context, tmp_path):
    """No 10 s wait for optional lanes; a known conflict refused at once."""
    _, tuner = _tuner(context, variant="pso-cp-tvac", iterations=2, particles=3)
    client = rclpy.create_node("operator", context=context)
    ex = EventsExecutor(context=context)
    for n in (tuner, client):
        ex.add_node(n)
    rec = tmp_path / "rec"
    try:
        assert tuner.set_parameters([Parameter("record", value=str(rec)),
                                     Parameter("lane_timeout", value=30.0)])[0].successful
        t0 = time.monotonic()
        assert _service(ex, client, "/tuner/start").success
        assert spin_until(ex, tuner.done.is_set, 120)
        assert time.monotonic() - t0 < 9.5 and tuner.error is None         # optional lanes: 2 s, not 10
        assert (rec / "tune.json").is_file() and (rec / "gains.yaml").is_file()
        again = _service(ex, client, "/tuner/start")                     # the session is there: refused now
        assert not again.success and "exists already" in again.message and "force" in again.message
        assert tuner.done.is_set()
        assert tuner.set_parameters([Parameter("resume", value=str(tmp_path / "none"))])[0].successful
        nothing = _service(ex, client, "/tuner/start")
        assert not nothing.success and "no session bag to resume" in nothing.message
        assert tuner.set_parameters([Parameter("resume", value=""), Parameter("force", value=True)])[0].successful
        assert _service(ex, client, "/tuner/start").success
        assert spin_until(ex, tuner.done.is_set, 120) and tuner.error is None
    finally:
        ex.shutdown()
        tuner.destroy_node()
        client.destroy_node()


def test_graph_validation_against_the_library_flags_a_lane_that_differs(context, tmp_path):
    """The lane's controller models mass 1700 kg, the tuner 1500 kg: a 'validating'
    status, the lanes' parameters read back into the session bag, a validation block in tune.json
    and ~/status that disagrees, and a status that is not 'finished'."""
    import json
    from has_control.bag import read_bag
    from has_control.nodes.controller_node import ControllerNode
    from has_control.nodes.plant_node import PlantNode
    from has_control.tuning.session import LANES, SESSION, _json
    cfg = with_horizon(Config(), 1.5)
    model = [Parameter(k, value=v) for k, v in config_parameters(cfg).items()]
    plant = PlantNode(context=context, parameter_overrides=model)
    controller = ControllerNode(context=context, parameter_overrides=[
        p for p in model if p.name != "actuator.mass"] + [Parameter("actuator.mass", value=1700.0)])
    _, tuner = _tuner(context, variant="pso-cp-tvac", iterations=1, particles=2)
    client = rclpy.create_node("operator", context=context)
    ex = EventsExecutor(context=context)
    for n in (plant, controller, tuner, client):
        ex.add_node(n)
    rec = tmp_path / "rec"
    seen = set()
    try:
        assert tuner.set_parameters([Parameter("record", value=str(rec))])[0].successful
        assert tuner.start() is None
        end = time.monotonic() + 120
        while not tuner.done.is_set() and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.005)
            seen.add(tuner.status.split(":")[0])
        status = _service(ex, client, "/tuner/status").message
        first = tuner.result
        # the same controller back on the tuner's model: graph = library, within the tolerance
        assert controller.set_parameters([Parameter("actuator.mass", value=1500.0)])[0].successful
        assert tuner.set_parameters([Parameter("record", value="")])[0].successful
        assert tuner.start() is None and spin_until(ex, tuner.done.is_set, 120)
        again = tuner.result
    finally:
        ex.shutdown()
        for n in (plant, controller, tuner, client):
            n.destroy_node()
    assert tuner.error is None and "validating" in seen
    v = first["validation"]
    assert not v["agrees"] and v["relative_difference"] > v["tolerance"] == 1e-6
    assert any("actuator.mass = 1700.0" in d for d in v["lane_differences"]), v["lane_differences"]
    assert status.startswith("disagrees") and "\nvalidation: " in status
    assert again["validation"]["agrees"] and again["validation"]["J"] == again["validation"]["library_J"]
    assert again["validation"]["lane_differences"] == [] and tuner.status.startswith("finished")
    assert json.loads(status.split("\nvalidation: ", 1)[1])["agrees"] is False
    assert json.loads((rec / "tune.json").read_text())["validation"]["agrees"] is False
    lanes = [_json(d)["lanes"] for _, d in read_bag(rec / SESSION).messages[LANES]]
    assert lanes[0][0]["controller"]["actuator.mass"] == 1700.0 and lanes[0][0]["plant"]["actuator.mass"] == 1500.0


def test_plant_start_on_an_inactive_plant_answers_failure(context):
    """The service says what happened."""
    from has_control.nodes.plant_node import PlantNode
    plant = PlantNode(context=context, parameter_overrides=[Parameter("autostart", value=False)])
    client = rclpy.create_node("operator", context=context)
    ex = EventsExecutor(context=context)
    for n in (plant, client):
        ex.add_node(n)
    try:
        res = _service(ex, client, "/plant/start")
        assert not res.success and "unconfigured" in res.message and not plant.run_requested
    finally:
        ex.shutdown()
        plant.destroy_node()
        client.destroy_node()


HOSTILE = [float("nan"), float("inf"), -1.0, 0.0, 1e300, -1, 0, 10**12, True, "garbage", "", "cvar:7",
           "nope.yaml", [], [1.0, 2.0], [1e9, 1e9, 1e9], [0.0, 0.0, 0.0], ["a"]]


def test_the_tuner_table_never_refuses_what_tune_takes():
    """One table per component: every swarm.*/restarts.* key is in it, and a value the
    table refuses is one the command line's check (tuning_from_parameters) refuses too."""
    from has_control.common.errors import ConfigError
    from has_control.config import refusal
    from has_control.tuning.parameters import TUNING_TABLE
    from has_control.tuning.tuner import tuning_from_parameters, tuning_parameters
    assert set(TUNING_TABLE) == set(tuning_parameters(load_tuning()))
    for key in TUNING_TABLE:
        for value in HOSTILE:
            if refusal(TUNING_TABLE, key, value) is None:
                continue
            with pytest.raises(ConfigError):
                tuning_from_parameters({key: value}, base=load_tuning())


def test_hostile_runtime_parameters_leave_a_tuner_that_starts(context):
    """A fuzz of the tuner node's runtime parameters: any value of any parameter is either
    refused with a reason or accepted, and the accepted state always passes the ~/start checks."""
    import random
    from has_control.nodes.tuner_node import OWN_PARAMETERS
    _, tuner = _tuner(context)
    rng = random.Random(5)
    fuzzed = ("swarm.", "restarts.", "simulation.", "gains.")
    names = [n for n in tuner._parameters if n in OWN_PARAMETERS or n.startswith(fuzzed)]
    outcomes = []
    try:
        for name in names:
            for value in rng.sample(HOSTILE, 8):
                try:
                    res = tuner.set_parameters([Parameter(name, value=value)])[0]
                except (TypeError, ValueError):            # rclpy: not a parameter type (e.g. a mixed list)
                    continue
                assert res.successful or res.reason, (name, value)
                outcomes.append(res.successful)
                tuner.read_settings()                      # raises if an accepted value broke the settings
    finally:
        tuner.destroy_node()
    assert len(names) > 40 and 10 < sum(outcomes) < len(outcomes) - 100
