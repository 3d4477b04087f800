"""``has-control``: the command-line front end.

Each subcommand is a module of this folder with ``HELP``, ``add_arguments(parser)``
and ``run(args) -> int``, listed in :data:`COMMANDS`; every one calls the
library. Bad input ends with one line on stderr naming the culprit and exit
status 2.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
from importlib import import_module

from has_control.common.interrupts import raise_interrupt
from has_control.cli.args import EXIT_INTERRUPTED, EXIT_USAGE, Parser
from has_control.cli.node_help import NODES, print_help, wants_help
from has_control.common.errors import HasControlError
from has_control.common.version import package_version

#: The subcommands, in the order ``--help`` lists them, and their one-line help; each is the module
#: ``has_control.cli.<name>`` (``-`` as ``_``), imported only when it runs.
COMMANDS = {
    "simulate": "run one episode with one gain set and print its score",
    "tune": "tune k1, k2, k3 (cma-restarts, or the paper's particle swarms)",
    "robustness": "J and e_max of gain sets on every scenario of a set, and their aggregates",
    "reproduce": "the paper's experiment over seeds, as a report",
    "stack": "run plant and controller nodes in one process, lock-step or real time",
    "score": "score a recorded run (J, e_max, e_mu, e_sigma) from its bag",
    "bag-info": "topics, types, counts and duration of a bag",
    "plot": "recorded runs (bags) as one figure: position, error, valve, pressures, estimates, gains",
    "replay": "publish a bag with its timing, or replay it to a controller",
    "identify": "estimate plant parameters from recorded runs",
    "landscape": "J over 2-D slices of the gain space: heatmaps, bound and minima marked",
    "deploy": "deploy tuned gains in steps under a watchdog that falls back to the safe gains",
}


def run_node(name: str, ros_args: list[str]) -> int:
    """Run one node as this process (for machines without the ros2 command);
    everything after the node's name goes to ROS (``--ros-args -p k:=v ...``)."""
    if wants_help(ros_args):
        return print_help(name)
    import_module(f"has_control.nodes.{NODES[name][0]}").main(args=[f"has-control {name}", *ros_args])
    return 0


def build_parser(command: str | None = None) -> Parser:
    """The parser; with ``command`` (a subcommand's name) only that
    subcommand's module is imported and its arguments declared (the others
    are listed by their help), so a run loads what it runs and no more."""
    p = Parser(prog="has-control", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"has-control {package_version()}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)
    for name, text in COMMANDS.items():
        sp = sub.add_parser(name, help=text)
        if command is None or name == command:
            module = import_module(f"has_control.cli.{name.replace('-', '_')}")
            module.add_arguments(sp)
            sp.set_defaults(func=module.run)
    for name in NODES:
        sub.add_parser(name, help=f"run the {name} node; what follows goes to ROS (--ros-args -p k:=v ...)")
    return p


def main(argv=None) -> int:
    """The program (``argv`` None: the command line); the exit status."""
    if argv is None:
        return _program(sys.argv[1:])
    argv = list(argv)
    try:
        if argv and argv[0] in NODES:
            return run_node(argv[0], argv[1:])
        args = build_parser(argv[0] if argv and argv[0] in COMMANDS else None).parse_args(argv)
        return args.func(args)
    except HasControlError as exc:
        print(f"has-control: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError as exc:
        if not _stdout_closed():
            print(f"has-control: error: {_os_error_line(exc)}", file=sys.stderr)
            return EXIT_USAGE
        _quiet_stdout()
        return EXIT_STDOUT_CLOSED
    except OSError as exc:
        print(f"has-control: error: {_os_error_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] not in ROS_MODULES:
            raise
        print(f"has-control: error: {exc.name} not found: this command needs ROS 2's Python packages "
              "(source /opt/ros/<distro>/setup.bash, or pip install the ros-* pins of requirements.txt)",
              file=sys.stderr)
        return EXIT_USAGE
    except MemoryError:
        _out_of_memory.append(True)           # leave at once: the shutdown could hang on memory it cannot get
        print("has-control: error: out of memory", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("has-control: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


#: The status of a command whose standard output was closed by its reader (``has-control ... | head``):
#: no message, as Unix tools killed by SIGPIPE end (128 + 13).
EXIT_STDOUT_CLOSED = 141

#: Set when a command ran out of memory: the program then ends without the interpreter's shutdown.
_out_of_memory: list = []


def _stdout_closed() -> bool:
    """Whether file descriptor 1 is a pipe (or socket) whose reader has gone."""
    import select
    try:
        poll = select.poll()
        poll.register(1, select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poll.poll(0))
    except (OSError, ValueError):
        return False


def _quiet_stdout() -> None:
    """Standard output to /dev/null: what is left in its buffer (flushed at exit) goes nowhere."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.close(devnull)
    except OSError:
        pass


#: Top-level modules that come with ROS 2 (rclpy and the message packages), not with pip install.
ROS_MODULES = {"rclpy", "rcl_interfaces", "builtin_interfaces", "sensor_msgs", "std_msgs", "std_srvs",
               "rosgraph_msgs", "diagnostic_msgs", "lifecycle_msgs", "rpyutils", "rosidl_runtime_py"}


def plant() -> int:
    """The ``has-control-plant`` console script."""
    return main_of("plant")


def controller() -> int:
    """The ``has-control-controller`` console script."""
    return main_of("controller")


def tuner() -> int:
    """The ``has-control-tuner`` console script."""
    return main_of("tuner")


def main_of(node: str) -> int:
    return _program([node, *sys.argv[1:]])


def _program(argv: list[str]) -> int:
    """The program run from a console script: its status, the process left at once
    (os._exit) when interrupted or out of memory."""
    if not argv[:1] or argv[0] not in NODES:      # a node's signals are its own (nodes.runtime.NodeSignals)
        _terminate_as_interrupt()
    try:
        status = main(argv)
    finally:
        _ignore_interrupts()
    try:
        sys.stdout.flush()                # what is still buffered; its reader may have gone meanwhile
    except BrokenPipeError:
        _quiet_stdout()
        status = EXIT_STDOUT_CLOSED if status == 0 else status
    if status == EXIT_INTERRUPTED or _out_of_memory:
        # what is left to run is the shutdown, which may wait on threads or need memory: end with the status
        for f in (sys.stdout, sys.stderr):
            try:
                f.flush()
            except OSError:
                pass
        os._exit(status)
    return status


def _terminate_as_interrupt() -> None:
    """SIGTERM (a supervisor, ``kill``, a CI timeout) ends a command as Ctrl-C
    does: KeyboardInterrupt, so what a command leaves (a session bag, a
    recording) is closed whole, then one line "interrupted" and status 130."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, raise_interrupt)


def _ignore_interrupts() -> None:
    """Once the program's status is decided, a Ctrl-C during the interpreter's
    shutdown (numba, rclpy and matplotlib take a while) changes nothing: the
    shutdown restores the default SIGINT action, which would end the process
    silently by the signal instead of with that status. An interrupted
    program leaves without the shutdown (os._exit), which after a
    KeyboardInterrupt in rclpy's care would otherwise re-raise SIGINT."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _os_error_line(exc: OSError) -> str:
    """``PATH: reason`` (both paths of a rename); the path is never left blank."""
    paths = [str(p) for p in (exc.filename, exc.filename2) if p is not None]
    return f"{' -> '.join(paths) or '(path unknown)'}: {exc.strerror or exc}"


if __name__ == "__main__":
    sys.exit(main())
