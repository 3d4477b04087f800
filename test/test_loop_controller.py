"""The controller process's report (has_control.loop.controller.ControllerProcess.diagnosis): no ROS."""
from types import SimpleNamespace

from has_control.core.params import Config
from has_control.loop.controller import ControllerProcess
from has_control.loop.log import ListLog
from has_control.wire import steps


def test_the_report_counts_and_warns_on_conflicts_or_estimates_out_of_bounds():
    process = ControllerProcess(Config(), ListLog())
    process.states_answered, process.late, process.malformed_states = 12, 1, 2
    port = SimpleNamespace(missing=3, stale=4, repeated=5, restarts=6)
    values, ok, message = process.diagnosis("active", 0, port)
    assert ok and message == "active, 12 answered, 1 late, 2 malformed"
    assert values["estimates_in_bounds"] is True and (values["states_missing"], values["states_stale"],
                                                      values["states_repeated"], values["restarts"]) == (3, 4, 5, 6)
    assert float(values["a1_hat"]) == Config().adaptation.initial[0]
    assert not process.diagnosis("active", 1, port)[1]                    # a second plant on the topic
    process.mem[steps.A1_HAT] = Config().adaptation.upper[0] * 2           # an estimate out of its bounds
    values, ok, message = process.diagnosis("inactive", 0, object())       # a port that counts nothing: 0s
    assert not ok and message.endswith(", estimates out of bounds") and values["estimates_in_bounds"] is False
    assert values["states_missing"] == values["restarts"] == 0 and values["lifecycle"] == "inactive"
