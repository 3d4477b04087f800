"""The tuner node driven through services: ~/start, ~/cancel, ~/status; the
batch evaluator without any plant or controller."""
import time

import pytest
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


def _spin_until(ex, cond, seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end and not cond():
        ex.spin_once(timeout_sec=0.01)
    return cond()


def test_the_batch_evaluator_needs_no_plant_or_controller(context):
    cfg, tuner = _tuner(context, variant="pso-cp-tvac", iterations=2, particles=3)
    ex = EventsExecutor(context=context)
    ex.add_node(tuner)
    try:
        tuner.start()
        assert _spin_until(ex, tuner.done.is_set, 120)
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
        assert _spin_until(ex, fut.done, 10)
        return fut.result()
    try:
        assert call("status").message.startswith("idle")
        assert not call("cancel").success                                 # nothing to cancel
        assert call("start").success
        assert _spin_until(ex, lambda: "iteration" in call("status").message, 60)
        assert not call("start").success                                  # one session at a time
        assert call("cancel").success
        assert _spin_until(ex, tuner.done.is_set, 30)
        assert call("status").message == "cancelled" and tuner.result is None and tuner.error is None
        assert call("start").success                                      # and again
        assert _spin_until(ex, lambda: "iteration" in call("status").message, 60)
        assert call("cancel").success and _spin_until(ex, tuner.done.is_set, 30)
    finally:
        ex.shutdown()
        tuner.destroy_node()
        client.destroy_node()
