"""The loop's guards: the fail-safe outage and the conflict checks.

:class:`FailSafe` counts the samples run with the valve centred (u = 0) and
warns once per outage; :class:`Conflicts` counts messages that only a second
participant on a loop topic could have sent (two different commands for one
sample, a state that goes back in time) and logs them as errors;
:class:`AnswerLedger` remembers what each recent sample ran with, so a late
second answer to it is caught.
"""
from __future__ import annotations

from typing import Callable

#: Recent samples whose applied answer is kept, to catch a second controller's late answers.
ANSWERS_KEPT = 4096


class FailSafe:
    """The valve centred while commands are missing: counted, warned once per outage."""

    def __init__(self, log):
        self.log = log
        self.samples = 0                 # samples run with the valve centred
        self.in_outage = False

    def centre(self, missing: int, sample: int) -> float:
        """Sample ``sample`` runs with u = 0 [m] (``missing`` commands in a row); returns 0.0."""
        self.samples += 1
        if not self.in_outage:
            self.log.warning(f"no command for {missing} samples at sample {sample}: "
                             "valve centred (u = 0) until commands return")
            self.in_outage = True
        return 0.0

    def back(self, sample: int) -> None:
        self.log.info(f"commands are back at sample {sample}")
        self.in_outage = False


class Conflicts:
    """Messages a second publisher on a loop topic sent: counted and logged as errors.

    ``where()`` names the topic and how many publish on it (the node asks the graph);
    with ``stop`` set, ``on_stop()`` is called at the first conflict (the stack ends the run)."""

    def __init__(self, log, where: Callable[[], str] = lambda: "", what: str = "conflicting messages"):
        self.log, self.where, self.what = log, where, what
        self.count = 0
        self.stop = False
        self.on_stop: Callable[[], None] = lambda: None

    def seen(self, message: str) -> None:
        self.count += 1
        if self.stop:
            self.on_stop()
        where = self.where()
        self.log.error(f"{message}: {where + '; ' if where else ''}{self.count} {self.what} so far",
                       throttle_duration_sec=5.0)


class AnswerLedger:
    """The command each of the last :data:`ANSWERS_KEPT` samples ran with (when it was an answer)."""

    def __init__(self, kept: int = ANSWERS_KEPT):
        self.kept = kept
        self.reset()

    def reset(self) -> None:
        self._at, self._u = [-1] * self.kept, [0.0] * self.kept

    def ran(self, sample: int, u: float, answered: bool) -> None:
        k = sample % self.kept
        self._at[k], self._u[k] = (sample, u) if answered else (-1, 0.0)

    def differs(self, sample: int, u: float) -> bool:
        """Sample ``sample`` already ran with an answer other than ``u``."""
        k = sample % self.kept
        return self._at[k] == sample and self._u[k] != u
