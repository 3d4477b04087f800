"""The tuning progress bar: no rate before it can be measured, an honest rate and time left after."""
import io

from has_control.cli.status import Progress


class _Tty(io.StringIO):
    def isatty(self):
        return True


class _Method:
    name, seed, gbest_f = "cma-restarts", 1, 1e-5

    def __init__(self):
        self.evaluations, self.share = 14, 0.0

    def progress(self):
        return self.share


def test_the_first_update_shows_no_rate_and_later_ones_a_rate_and_an_eta(monkeypatch):
    clock = iter([100.0, 102.0])
    monkeypatch.setattr("has_control.cli.status.time.perf_counter", lambda: next(clock))
    out, m = _Tty(), _Method()
    bar = Progress(out)
    m.share = 0.1
    bar(m)
    assert "- eval/s" in out.getvalue() and "ETA -" in out.getvalue()
    m.evaluations, m.share = 214, 0.3
    bar(m)
    last = out.getvalue().split("\r")[-1]
    assert "100 eval/s" in last and "ETA 7 s" in last          # 200 in 2 s; 0.7 left at 0.2 per 2 s
