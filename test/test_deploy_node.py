"""Guarded deployment on a running machine: the watchdog and the stepping
policy watch the loop's topics and move the controller through its
parameters; the same policy as the in-process deployment, read from either
documented layout."""
from types import SimpleNamespace

import numpy as np
import pytest

from has_control.config import build_config, with_horizon
from has_control.core.cost import score_arrays
from has_control.core.episode import Col, simulate
from has_control.deploy.guarded import DeploymentPlan, deploy_in_process, gap_words
from has_control.deploy.stepping import Deployer
from has_control.deploy.watchdog import WatchdogLimits
from has_control.deploy.watched import Pairing, Watched, internals_of
from has_control.loop.controller import ControllerProcess
from has_control.loop.guards import Conflicts
from has_control.loop.log import ListLog
from has_control.loop.ports import Outputs, make_port
from has_control.wire.joint_mapping import DEFAULT_STATE_INTERFACES, parse_state_interfaces
from test_loop import _encoded_states

SAFE = (150.0, 158.0, 162.0)
LIMIT_CYCLING = (264.0, 264.0, 263.0)       # tuned on a first-order valve: limit-cycles on a 100 Hz spool
LIMIT = 5e-3


@pytest.fixture(scope="module")
def machine():
    """The project's plant with a 100 Hz second-order valve (zeta 0.7) and a 5 mm spool travel."""
    return build_config({"plant.valve_frequency": 100.0, "plant.valve_damping_ratio": 0.7,
                         "plant.valve_limit": LIMIT})


@pytest.mark.parametrize("steps_", [1, 4])
def test_the_message_driven_deployer_trips_and_falls_back_where_the_in_process_kernel_does(machine, steps_):
    """One policy: the kernel's guarded run, its (u, e1) fed sample by sample to
    the Deployer a node uses, asks for the same rows at the same samples."""
    plan = DeploymentPlan(SAFE, LIMIT_CYCLING, steps=steps_, settle=0.5, hold=0.5)
    run = deploy_in_process(machine, plan, keep_trace=True)
    assert run.tripped_at is not None
    dt = machine.episode.step
    d = Deployer(plan.schedule(), plan.switches(dt), WatchdogLimits(valve_limit=LIMIT), dt)
    k = run.trace[:, 12:15]
    for i, row in enumerate(run.trace):
        asked = d.sample(i, row[Col.u], row[Col.e1])
        if asked >= 0 and i + 1 < len(k):             # the kernel ran sample i + 1 on the row asked for
            np.testing.assert_array_equal(k[i + 1], plan.schedule()[asked])
    at, reason, step = d.tripped()
    assert at * dt == pytest.approx(run.tripped_at) and reason == run.reason and step == run.step
    assert tuple(plan.schedule()[d.final_row()]) == pytest.approx(run.final_gains)


@pytest.mark.parametrize("layout", ["has_control", "ros2_control"])
def test_each_layouts_command_and_internals_pair_into_the_samples_the_controller_ran(layout):
    """Through the controller's own ports: what the deployment reads off either
    layout's topics is each sample's u and e1, in arrival order for ros2_control
    (its command has no stamp) and by stamp for has_control, even out of order."""
    cfg = with_horizon(build_config({}), 1.5)
    ref = simulate(cfg)
    commands, internals = [], []
    out = Outputs(commands.append, commands.append, internals.append, lambda b: None, lambda b: None)
    port = make_port(layout, ControllerProcess(cfg, ListLog()), out, Conflicts(ListLog()),
                     mapping=parse_state_interfaces(DEFAULT_STATE_INTERFACES), command_topic="/valve/commands")
    watched = Watched(layout, command_topic="/valve/commands")
    assert watched.command[0] == ("/valve/commands" if layout == "ros2_control" else "/command")
    for data, x in _encoded_states(cfg, ref.data[:20]):
        port.on_state(data if layout == "has_control" else SimpleNamespace(
            name=["actuator", "chamber_1", "chamber_2"], position=[x[0], 0.0, 0.0], velocity=[x[1], 0.0, 0.0],
            effort=[0.0, x[2], x[3]]))
    pairing = Pairing(stamped=layout == "has_control")
    got = []
    first = [internals_of(bytes(b), cfg.episode.step) for b in internals]
    if layout == "has_control":                         # internals before their commands: still paired
        for s, e1 in first:
            got += pairing.internals(s, e1)
        for c in commands:
            got += pairing.command(*watched.command_of(bytes(c), cfg.episode.step_ns))
    else:
        for c, (s, e1) in zip(commands, first):
            got += pairing.command(*watched.command_of(bytes(c), cfg.episode.step_ns))
            got += pairing.internals(s, e1)
    assert [g[0] for g in got] == list(range(20))
    np.testing.assert_array_equal([g[1] for g in got], ref.data[:20, Col.u])
    np.testing.assert_array_equal([g[2] for g in got], ref.data[:20, Col.e1])


@pytest.mark.ros
def test_on_the_plant_node_a_limit_cycling_deployment_falls_back_within_100_ms_of_the_onset(
        machine, context, tmp_path):
    """The deploy node on the graph: the project's plant node with a 100 Hz second-order valve, the
    controller node moved through its gains.* parameters by the deploy node
    watching the topics: the fallback gains take effect before the limit cycle's
    onset (+100 ms at most), and the run's J stays within 2x the safe gains'."""
    from has_control.nodes.deploy_node import WATCHDOG_TOPIC, deploy_on_plant_node
    plan = DeploymentPlan(SAFE, LIMIT_CYCLING, steps=1, settle=1.0, hold=1.0)
    res, trace = deploy_on_plant_node(machine, plan, context=context, record=tmp_path / "run", predicted_J=2.9e-5)
    dt = machine.episode.step
    assert res.tripped is not None
    (_, _, _, switched), (_, _, _, fell_back) = res.changes[1], res.changes[2]
    assert res.changes[1][2] == "step" and res.changes[2][2].startswith("fallback")
    assert switched is not None and fell_back is not None
    # the limit cycle's onset unguarded, the tuned gains taking effect where they did through the graph
    blind = deploy_in_process(machine, DeploymentPlan(SAFE, LIMIT_CYCLING, steps=1, settle=switched * dt, hold=1.0),
                              WatchdogLimits(hf_rms=1e9, stop_share=1.0, e1_max=1e9, valve_limit=LIMIT),
                              keep_trace=True)
    u, t = blind.trace[:, Col.u], blind.trace[:, Col.t]
    onset = t[np.flatnonzero((np.abs(u) >= 0.98 * LIMIT) & (t > switched * dt))[0]]
    assert blind.tuned_J > 10 * blind.safe_J                   # unguarded, it does limit-cycle
    assert fell_back * dt <= onset + 0.1 and res.fallback_latency() <= 0.1
    assert res.final_gains == pytest.approx(SAFE)
    cfg = with_horizon(machine, max(plan.duration() + 0.05, 1.5))
    answered = ~np.isnan(trace[:, Col.t])
    assert answered.all()
    run_J = score_arrays(trace[:, Col.e1], trace[:, Col.u], cfg.episode.as_array()).J
    assert run_J == res.J and res.safe_J == simulate(cfg, SAFE).score.J
    assert run_J <= 2.0 * res.safe_J
    assert (tmp_path / "run" / "metadata.yaml").exists()
    assert WATCHDOG_TOPIC in (tmp_path / "run" / "metadata.yaml").read_text()


@pytest.mark.ros
def test_on_the_plant_node_a_deployment_that_behaves_ends_on_the_tuned_gains_and_is_measured(machine, context):
    from has_control.nodes.deploy_node import deploy_on_plant_node
    tuned = (170.0, 170.0, 175.0)
    plan = DeploymentPlan(SAFE, tuned, steps=2, settle=0.5, hold=0.5)
    predicted = simulate(machine, tuned).score.J                 # the tuner's prediction, over its 10 s
    res, _ = deploy_on_plant_node(machine, plan, context=context, predicted_J=predicted)
    assert res.tripped is None and res.final_gains == pytest.approx(tuned)
    assert [c[1] for c in res.changes] == [0, 1, 2] and all(c[3] is not None for c in res.changes)
    assert res.J < res.safe_J
    # the tuned gains' cost rate over their step (after the start-up transient) is below the whole run's
    assert res.gap is not None and 0.0 < res.gap < 1.0
    assert gap_words(res.gap) in res.lines()[-1] and "GAP" not in res.lines()[-1]


def test_the_deployer_is_done_when_the_plans_last_step_has_been_held():
    plan = DeploymentPlan(SAFE, (170.0, 170.0, 175.0), steps=2, settle=1.0, hold=0.25)
    dt = 3e-4
    d = Deployer(plan.schedule(), plan.switches(dt), WatchdogLimits(), dt, end=int(round(plan.duration() / dt)))
    asked = {i: d.sample(100 + i, 0.0, 0.0) for i in range(6000) if not d.done()}    # joins at sample 100
    assert [i for i, row in asked.items() if row >= 0] == list(plan.switches(dt)) == [0, 3333, 4166]
    assert max(asked) == 5000


@pytest.mark.ros
def test_deploying_to_a_controller_that_is_not_there_is_one_line_exit_2(capfd, domain_id, monkeypatch):
    from has_control.cli.main import main
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain_id))
    code = main(["deploy", "--gains", "264", "264", "263", "--controller", "/nobody", "--timeout", "1"])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "/nobody" in err[0]
