"""The tuner node's session service (ROS-free): one tuning session at a time, its status and result.

:class:`TunerService` keeps what ``~/start``, ``~/cancel`` and ``~/status``
answer (the status line, the result, the error, whether a session runs) and
runs the session (:class:`~has_control.tuning.lane_session.LaneSession`: the
same runner as ``has-control tune``, over the lanes) in a thread of its own.
The log is any object with ``info``, ``warning`` and ``error`` (an rclpy logger);
the node wires it, the lanes and the ``~/progress`` publisher.
"""
from __future__ import annotations

import json
import threading
from typing import Callable

from has_control.common.errors import HasControlError
from has_control.tuning.lane_session import Cancelled, LaneSession
from has_control.tuning.service_settings import Settings
from has_control.tuning.session import conflict
from has_control.tuning.validation import disagreement_status

__all__ = ["Cancelled", "TunerService"]


class TunerService:
    """One session at a time over ``lanes`` (see the module): ``start``, ``cancel``,
    ``status_message``; ``publish_progress(row)`` takes each iteration's progress row."""

    def __init__(self, settings: Settings, lanes: list, log, publish_progress: Callable[[list], None]):
        self.settings, self.lanes, self.log, self.publish_progress = settings, lanes, log, publish_progress
        self.result: dict | None = None
        self.error: str | None = None
        self.status = "idle: call ~/start"
        self.done = threading.Event()
        self.done.set()                               # no session running
        self._thread: threading.Thread | None = None
        self._cancel = threading.Event()

    # --- what the services answer ----------------------------------------------
    def start(self, read: Callable[[], Settings]) -> str | None:
        """Read and check the settings (``read()``), refuse a known conflict (a session
        running, a session already in ``record`` without ``force``, nothing to ``resume``),
        then run the session in a thread of its own. The reason it refused, or None
        (also kept as ``error``)."""
        if not self.done.is_set():
            return f"busy: {self.status}"
        try:
            settings = read()
            why = conflict(settings.record, settings.resume, settings.force)
            if why:
                raise HasControlError(f"parameter record/resume: {why}")
        except HasControlError as exc:
            self.error = str(exc)
            self.status = f"refused: {self.error}"
            self.log.error(f"~/start refused: {self.error}")
            return self.error
        self.settings = settings
        self.done.clear()
        self._cancel.clear()
        self.result = self.error = None
        self.status = "running: starting"
        self._thread = threading.Thread(target=self._guarded, name="tuner-session", daemon=True)
        self._thread.start()
        return None

    def cancel(self) -> tuple[bool, str]:
        """(whether a session will stop, the answer's message)."""
        if self.done.is_set():
            return False, f"nothing to cancel: {self.status}"
        self._cancel.set()
        return True, "cancelling at the next episode"

    def status_message(self) -> str:
        """The status line; after a validated session, a second line ``validation: {JSON}``."""
        validation = (self.result or {}).get("validation")
        if validation is not None and self.done.is_set():
            return self.status + "\nvalidation: " + json.dumps(validation)
        return self.status

    def check_cancel(self) -> None:
        if self._cancel.is_set():
            raise Cancelled()

    def _guarded(self) -> None:
        try:
            self.result = self.run_session()
            gains = tuple(round(k, 2) for k in self.result["gains"])
            validation = self.result.get("validation") or {}
            if validation.get("agrees", True):
                self.status = f"finished: best k = {gains}, J = {self.result['J']}"
            else:
                self.status = disagreement_status(self.result["gains"], self.result["J"], validation)
        except Cancelled:
            self.status = "cancelled"
            self.log.warning("session cancelled (~/cancel); a recorded one resumes with resume:=DIR")
        except HasControlError as exc:
            self.error = str(exc)
            self.status = f"failed: {self.error}"
            self.log.error(self.error)
        except Exception as exc:                 # a bug, not bad input: keep its type in the report
            self.error = f"{type(exc).__name__}: {exc}"
            self.status = f"failed: {self.error}"
            self.log.error(f"tuning session failed: {self.error}")
        finally:
            self.done.set()

    def run_session(self) -> dict:
        """One session in this thread (:class:`~has_control.tuning.lane_session.LaneSession`); its result."""
        return LaneSession(self.settings, self.lanes, self.log, self.publish_progress, self.check_cancel,
                           self._set_status).run()

    def _set_status(self, line: str) -> None:
        self.status = line
