"""The tuner node's session service (has_control.tuning.service): start, cancel, status,
one session at a time in its own thread; no ROS."""
import json

from has_control.common.errors import HasControlError
from has_control.tuning import service as service_module
from has_control.tuning.service import TunerService
from test_lane_session import TUNING, Lane, Log, settings


def _service(lanes=(), log=None):
    return TunerService(settings(), list(lanes) or [Lane("/", ready=False)], log or Log(), lambda row: None)


def test_a_session_runs_in_its_thread_and_says_how_it_finished():
    svc = _service()
    assert svc.status_message() == "idle: call ~/start"
    assert svc.cancel() == (False, "nothing to cancel: idle: call ~/start")
    assert svc.start(settings) is None
    assert svc.done.wait(120)
    assert svc.error is None and svc.status.startswith("finished: best k = (")
    status, validation = svc.status_message().split("\nvalidation: ")
    assert status == svc.status and json.loads(validation)["J"] == svc.result["J"]


def test_a_refused_start_keeps_the_reason_and_runs_nothing():
    log = Log()
    svc = _service(log=log)

    def bad():
        raise HasControlError("parameter of /tuner: evaluator = 'fast'")
    assert svc.start(bad) == "parameter of /tuner: evaluator = 'fast'"
    assert svc.status == "refused: parameter of /tuner: evaluator = 'fast'" and svc.done.is_set()
    assert log.lines == [("error", "~/start refused: parameter of /tuner: evaluator = 'fast'")]


def test_a_recorded_session_there_already_is_refused_without_force(tmp_path):
    (tmp_path / "tune.json").write_text("{}")
    svc = _service()
    s = settings()
    reason = svc.start(lambda: type(s)(**{**s.__dict__, "record": str(tmp_path)}))
    assert reason.startswith("parameter record/resume: ") and "exists already" in reason


def test_one_session_at_a_time_and_a_cancel_stops_it():
    svc = _service()
    long = settings()
    long = type(long)(**{**long.__dict__, "tuning": TUNING.replace(iterations=100000)})
    assert svc.start(lambda: long) is None
    assert svc.start(lambda: long).startswith("busy: ")
    assert svc.cancel() == (True, "cancelling at the next episode")
    assert svc.done.wait(60)
    assert svc.status == "cancelled" and svc.result is None and svc.error is None
    assert svc.log.lines[-1][0] == "warning" and "resume:=DIR" in svc.log.lines[-1][1]


def test_a_bug_keeps_its_type_and_a_disagreement_is_no_finish(monkeypatch):
    svc = _service()

    def broken(self):
        raise ValueError("a bug")
    monkeypatch.setattr(service_module.LaneSession, "run", broken)
    svc.start(settings)
    assert svc.done.wait(10) and svc.status == "failed: ValueError: a bug" and svc.error == "ValueError: a bug"
    block = {"J": 2.0, "library_J": 1.0, "relative_difference": 1.0, "tolerance": 1e-6, "agrees": False}
    monkeypatch.setattr(service_module.LaneSession, "run",
                        lambda self: {"gains": [1.0, 2.0, 3.0], "J": 1.0, "validation": block})
    svc.start(settings)
    assert svc.done.wait(10) and svc.status.startswith("disagrees: best k = (1.0, 2.0, 3.0)")
