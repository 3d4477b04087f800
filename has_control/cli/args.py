"""What several subcommands take: argument types checked by argparse, the
shared options, and loading the configuration they name."""
from __future__ import annotations

import argparse
import math
from pathlib import Path
import re
from contextlib import nullcontext

from has_control.common.errors import HasControlError
from has_control.common.files import check_output
from has_control.config import check_gain, finite_number, load_config, with_horizon
from has_control.core.params import Config
from has_control.wire.joint_mapping import DEFAULT_COMMAND_TOPIC, DEFAULT_STATE_INTERFACES

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block) and exit status 2."""

    def error(self, message):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def gains_arg(values, option: str = "--gains") -> tuple[float, float, float]:
    """``option`` K1 K2 K3 [1/s], checked as the config checks gains.k1..k3."""
    out = []
    for name, v in zip(("K1", "K2", "K3"), values):
        try:
            x = finite_number(float(v))
        except ValueError:
            x = "expected a number"
        why = x if isinstance(x, str) else check_gain(x)
        if why:
            raise HasControlError(f"{option}: {name} = {v!r}: {why}")
        out.append(x)
    return tuple(out)


def load(args) -> Config:
    """The configuration of ``--config FILE ...`` with ``--duration`` applied."""
    return with_horizon(load_config(args.config or []), args.duration)


def number(low: float = -math.inf, high: float = math.inf, kind: type = float):
    """An argparse type: a finite number (``kind`` int: a whole number) in [``low``, ``high``]."""
    expected = "a whole number" if kind is int else "a number"
    where = (f">= {low:g}" if high == math.inf else f"<= {high:g}" if low == -math.inf
             else f"in {low:g} .. {high:g}")

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}") from None
        if not ((kind is int or math.isfinite(v)) and low <= v <= high):
            raise argparse.ArgumentTypeError(f"{text!r}: must be {expected}"
                                             + ("" if (low, high) == (-math.inf, math.inf) else f" {where}"))
        return v
    return parse


def at_least(low: float, kind: type = float):
    """An argparse type: a finite number (``kind`` int: a whole number) >= ``low``."""
    return number(low, kind=kind)


positive_int = at_least(1, int)

_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
_NAMESPACE = re.compile(rf"/?(?:{_NAME}(?:/{_NAME})*)?")


def namespace(text: str) -> str:
    """An argparse type: a ROS namespace (``/sim0``, ``sim0/a``; tokens of
    letters, digits and underscores, not starting with a digit)."""
    if not _NAMESPACE.fullmatch(text):
        raise argparse.ArgumentTypeError(f"{text!r}: not a ROS namespace (tokens of letters, digits and _, "
                                         "not starting with a digit, separated by /)")
    return text


def port(text: str) -> int:
    """An argparse type: a TCP port."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a port 1..65535") from None
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a port 1..65535")
    return v


def check_outputs(args, files=(), directories=()) -> None:
    """Before the work: every output the command line names (options
    ``files`` and ``directories``, those given) can be written there
    (:func:`has_control.common.files.check_output`: a new path, or a regular
    file or a link to one, in a writable directory); one line naming it if not."""
    for names, what in ((files, "file"), (directories, "directory")):
        for name in names:
            path = getattr(args, name, None)
            if path is not None:
                try:
                    check_output(path, what)
                except HasControlError as exc:
                    raise HasControlError(f"--{name}: {exc}") from None


def check_apart(args, outputs=(), inputs=()) -> None:
    """Before the work: no output (options ``outputs``) is an input (options
    ``inputs``, each a path or a list of paths), lies inside an input (a bag
    directory), or is another output; no input is given twice. One line naming
    the option and the path if so."""
    def paths(name):
        v = getattr(args, name, None)
        return [] if v is None else [v] if isinstance(v, (str, Path)) else list(v)
    seen_in: dict = {}
    for name in inputs:
        for p in paths(name):
            real = Path(p).resolve()
            if real in seen_in:
                raise HasControlError(f"{_flag(name)} {p}: given twice (also as {seen_in[real]}): one recording "
                                      "counted twice would narrow every interval")
            seen_in[real] = f"{_flag(name)} {p}"
    seen_out: dict = {}
    for name in outputs:
        for p in paths(name):
            real = Path(p).resolve()
            for src, where in seen_in.items():
                if real == src or src in real.parents:
                    raise HasControlError(f"--{name} {p}: would write into the input {where}")
            if real in seen_out:
                raise HasControlError(f"--{name} {p}: is also {seen_out[real]}: two outputs, one file")
            seen_out[real] = f"--{name}"


def _flag(name: str) -> str:
    return "BAG" if name == "bags" else f"--{name}"


def add_reading(p) -> None:
    """``--state-interfaces`` and ``--command-topic``: how a ros2_control layout bag is read."""
    p.add_argument("--state-interfaces", nargs=4, metavar=("Y", "YDOT", "P1", "P2"),
                   help="joint/interface of y, y_dot, P1, P2 in /joint_states (ros2_control layout; default: "
                        + " ".join(DEFAULT_STATE_INTERFACES) + ")")
    p.add_argument("--command-topic", metavar="TOPIC",
                   help="the valve command topic (default: .../command, else " + DEFAULT_COMMAND_TOPIC + ")")


def reading_of(args):
    """The :class:`~has_control.bag.recorded.Reading` that ``--state-interfaces`` and ``--command-topic`` ask for."""
    # lazy: the bag reader; only the commands that read a recording need it
    from has_control.bag.recorded import Reading
    si = getattr(args, "state_interfaces", None)
    return Reading(tuple(si) if si else None, getattr(args, "command_topic", None))


def figure_path(text: str) -> str:
    """An argparse type: a figure file whose format matplotlib writes (its
    place: :func:`check_outputs`; both before the run)."""
    # lazy: matplotlib takes about 1 s to load; only commands given a figure need it
    from has_control.plots.figures import figure_format
    try:
        figure_format(text)
    except HasControlError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def dask_spec(text: str) -> str:
    """An argparse type: ``local:N`` or ``tcp://HOST:PORT`` (checked by :mod:`has_control.tuning.dask_evaluator`)."""
    # lazy: distributed takes about 1 s to load; only --dask needs it
    from has_control.tuning.dask_evaluator import parse_spec
    return parse_spec(text)


def batch(args):
    """The batch evaluator of ``--dask SPEC`` (a context manager), else the local one (None)."""
    if not getattr(args, "dask", None):
        return nullcontext(None)
    # lazy: distributed takes about 1 s to load; only --dask needs it
    from has_control.tuning.dask_evaluator import dask_batch
    return dask_batch(args.dask)


def add_config(p, what: str = "ros__parameters YAML overriding the shipped config (repeatable)") -> None:
    p.add_argument("--config", action="append", metavar="FILE", help=what)


def add_duration(p) -> None:
    p.add_argument("--duration", type=float, metavar="S", help="episode horizon [s] (default: config, 10 s)")


def add_json(p, what: str = "print one JSON object") -> None:
    p.add_argument("--json", action="store_true", help=what)
