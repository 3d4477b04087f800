"""What a deployment through the topics did (has_control.deploy.report): the changes asked,
when each took effect, and the report taken from the stepping policy; no ROS."""
import math

import pytest

from has_control.core.params import Config
from has_control.deploy.guarded import DeploymentPlan
from has_control.deploy.report import Changes, NodeDeployment
from has_control.deploy.stepping import Deployer
from has_control.deploy.watchdog import WatchdogLimits

DT = 1e-3
PLAN = DeploymentPlan((300.0, 300.0, 30.0), (600.0, 600.0, 60.0), steps=2, settle=0.01, hold=0.01)
EP = Config().episode.as_array()


def _run(e1_of, announce_after=None, first=100):
    """The plan on samples first, first + 1, ... with u = 0 and e1 = e1_of(i) [m]; each change
    asked is announced by the controller ``announce_after`` samples later (None: never)."""
    schedule = PLAN.schedule()
    d = Deployer(schedule, PLAN.switches(DT), WatchdogLimits(), DT, end=int(round(PLAN.duration() / DT)))
    changes, pending = Changes(schedule), []
    i = first
    while not d.done():
        for at, k in [p for p in pending if p[0] == i]:
            changes.announced(at, k)
        row = d.sample(i, 0.0, e1_of(i))
        if row >= 0:
            changes.ask(i, row, d.rows[-1][2])
            if announce_after is not None:
                pending.append((i + announce_after, tuple(schedule[row])))
        i += 1
    res = NodeDeployment(PLAN, DT, predicted_J=1.0, predicted_horizon=1.0)
    res.take(d, schedule, EP, changes)
    res.changes = changes.rows()
    return res


def test_each_change_took_effect_when_its_gains_were_first_announced():
    res = _run(lambda i: 1e-4, announce_after=3)
    assert [(a, row, took) for a, row, _, took in res.changes] == [(100, 0, 103), (110, 1, 113), (120, 2, 123)]
    assert res.tripped is None and res.final_gains == pytest.approx(PLAN.tuned)
    assert (res.first, res.last) == (100, 130)


def test_an_announcement_of_other_gains_or_before_the_ask_takes_no_effect():
    schedule = PLAN.schedule()
    changes = Changes(schedule)
    changes.ask(10, 1, "step")
    changes.announced(9, tuple(schedule[1]))             # before it was asked: an old announcement
    changes.announced(11, tuple(schedule[2]))            # other gains
    assert changes.rows() == [(10, 1, "step", None)]
    changes.announced(12, tuple(schedule[1] * (1 + 1e-12)))
    assert changes.rows() == [(10, 1, "step", 12)]


def test_the_tuned_gains_cost_rate_counts_from_when_they_took_effect():
    """e1 doubles from sample 125 on: the tuned gains (asked at 120, in effect at 125) cost what a run
    at the doubled e1 costs per second; counted from the ask, the rate would mix in the smaller e1."""
    steady = _run(lambda i: 2e-4)
    per_second = steady.J / ((steady.last - steady.first + 1) * DT)
    late = _run(lambda i: 2e-4 if i >= 125 else 1e-4, announce_after=5)
    assert late.tuned_rate == pytest.approx(per_second, rel=1e-12)
    unseen = _run(lambda i: 2e-4 if i >= 125 else 1e-4)          # never announced: counted from the ask
    assert unseen.tuned_rate < per_second and unseen.changes[-1][3] is None
    assert late.gap == pytest.approx(per_second)                 # against a prediction of 1 per second
    assert math.isfinite(late.J) and late.as_json()["samples"] == 31 and late.as_json()["tripped"] is False
