"""The control loop's QoS and the small message helpers the nodes share.

Names, types, joints and wire layouts of the topics are in
:mod:`has_control.wire.topics`.
"""
from __future__ import annotations

import faulthandler
import gc
import os
import signal
import sys
import tempfile
import threading
import weakref
from contextlib import contextmanager

import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy._rclpy_pybind11 import RCLError
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import LoggingSeverity
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from has_control.common.interrupts import exit_quietly_on_interrupt
from has_control.common.errors import HasControlError, shown
from has_control.config.params_file import read_parameter_file
from has_control.core.actuator import joint_state
from has_control.core.params import Actuator
from has_control.wire.topics import QOS, RECORDING_QOS as TOPICS_RECORDING_QOS, STATE, STATE_NAMES, offered


def _profile(depth: int, transient_local: bool) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE)


def qos(relative: str) -> QoSProfile:
    """The QoS a run topic's writers offer (:func:`has_control.wire.topics.offered`)."""
    return _profile(*offered(relative))


#: What the control loop's readers take on state and command (see :data:`has_control.wire.topics.QOS`).
CONTROL_QOS = _profile(*QOS[STATE])
#: What the loop's writers offer on state and command (and the ros2_control layout's topics).
CONTROL_OFFERED_QOS = qos(STATE)
#: The recording QoS (:data:`has_control.wire.topics.RECORDING_QOS`): a reader outside the loop gets every sample.
RECORDING_QOS = _profile(*TOPICS_RECORDING_QOS)


def stamp(sample: int, step_ns: int) -> Time:
    """Simulation time of sample i: i·Δt, exact in integer nanoseconds."""
    ns = sample * step_ns
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def sample_of(t: Time, step_ns: int) -> int:
    """Sample index of a stamp (inverse of :func:`stamp`)."""
    return round((t.sec * 1_000_000_000 + t.nanosec) / step_ns)


def state_message(sample: int, step_ns: int, x, a: Actuator) -> JointState:
    """The state message of sample ``sample`` as a message object (the nodes
    publish the same bytes from :mod:`has_control.wire.steps`)."""
    values = [float(v) for v in joint_state(*(float(s) for s in x), a.as_array())]
    msg = JointState()
    msg.header.stamp = stamp(sample, step_ns)
    msg.name = STATE_NAMES
    msg.position, msg.velocity, msg.effort = values[0:3], values[3:6], values[6:9]
    return msg


def normalise_namespace(namespace: str | None) -> str:
    """A namespace as ROS resolves it: ``sim0`` → ``/sim0``; '' or '/' → '' (the root)."""
    namespace = (namespace or "").strip("/")
    return f"/{namespace}" if namespace else ""


def publish_diagnostics(node, publisher, what: str, hardware_id: str, values: dict, ok: bool, message: str) -> None:
    """One ``diagnostic_msgs/DiagnosticArray`` on ``publisher``: status "<node>: ``what``",
    OK or WARN, ``values`` as key/value strings (floats to 6 significant digits)."""
    status = DiagnosticStatus(
        level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
        name=f"{node.get_fully_qualified_name()}: {what}", message=message, hardware_id=hardware_id,
        values=[KeyValue(key=k, value=f"{v:.6g}" if isinstance(v, float) else str(v)) for k, v in values.items()])
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = node.get_clock().now().to_msg()
    publisher.publish(msg)
    taps = _diagnostics_taps.get(node)
    if taps:
        data = serialize_message(msg)
        for take in taps:
            take(data)


#: The taps a node's diagnostics go to besides its publisher (a live view): node -> [take(bytes)].
_diagnostics_taps: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def tap_diagnostics(node, tap, topic: str = "/diagnostics") -> None:
    """Hand every diagnostics message ``node`` publishes (:func:`publish_diagnostics`)
    to ``tap(topic)`` as well, e.g. :meth:`~has_control.nodes.foxglove.LiveView.sink`,
    so that a live view serves ``/diagnostics`` too. ``tap`` None: nothing."""
    if tap is not None:
        _diagnostics_taps.setdefault(node, []).append(tap(topic))


def raw_publish(publisher, tap=None):
    """A function that publishes serialized bytes (``publish(bytes)``) on
    ``publisher``, and hands them to ``tap(topic)``, an in-process observer
    such as the recorder's :meth:`~has_control.nodes.recorder.Recorder.sink`,
    if one is given and takes the topic (``tap(topic)`` not None)."""
    publish = publisher.publish
    take = tap(publisher.topic_name) if tap is not None else None
    if take is None:                             # no observer takes this topic
        return publish

    def publish_and_tap(data: bytes) -> None:
        publish(data)
        take(data)
    return publish_and_tap


@contextmanager
def borrowed_context(context=None, args=None, domain_id: int | None = None):
    """``context`` itself, or (None) a new initialised rclpy context that is
    shut down on the way out."""
    if context is not None:
        yield context
        return
    context = rclpy.Context()
    rclpy.init(args=args, context=context, domain_id=domain_id)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


def tee(*taps):
    """One tap that hands each message to every one of ``taps`` (None: left
    out), e.g. a bag and a live view at once; a single tap is returned as is."""
    taps = [t for t in taps if t is not None]
    if len(taps) <= 1:
        return taps[0] if taps else None

    def tap(topic: str):
        takes = tuple(f for f in (t(topic) for t in taps) if f is not None)
        if len(takes) <= 1:
            return takes[0] if takes else None

        def take(data: bytes) -> None:
            for f in takes:
                f(data)
        return take
    return tap


def spin(executor, done=lambda: False, period: float = 0.1) -> None:
    """Serve ``executor`` until ``done()`` or shutdown (Ctrl-C, SIGTERM).

    rclpy 9.1's ``EventsExecutor.spin()`` busy-loops at full CPU and does not
    return on a signal here; ``spin_once`` with a timeout does neither."""
    while rclpy.ok(context=executor.context) and not done():
        executor.spin_once(timeout_sec=period)


class NodeSignals:
    """Ctrl-C and SIGTERM for a node process, handled in one place.

    rclpy's own handlers are off (``rclpy.init(signal_handler_options=NO)``):
    they shut the context down under a running callback (a publish then fails:
    "publisher's context is invalid") and chain to Python's handler, whose
    KeyboardInterrupt raised inside a subscription or service callback ends in
    rclpy's FATAL stack or, from a service handler, in C++'s ``terminate`` (exit
    134). Here, until the node serves, a signal ends the process at once (one
    line, 130: loading code, nothing to close); once it serves, the signal only
    marks the stop (a plant's episode ends at the next sample) and the
    executor's ``spin_once`` (:meth:`executor`) raises KeyboardInterrupt on its
    return, where no callback runs. :func:`node_main` then closes the node and the context and
    the command ends with one line, "interrupted", and status 130."""

    SIGNALS = ("SIGINT", "SIGTERM")

    def __init__(self):
        self.received: list[int] = []
        self.node = None
        self._previous: dict = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for name in self.SIGNALS:
            sig = getattr(signal, name)
            if signal.getsignal(sig) is signal.SIG_IGN:
                continue                           # ignored by whoever started us (a background job): stays so
            self._previous[sig] = signal.signal(sig, self._loading)

    def _loading(self, signum, frame) -> None:
        exit_quietly_on_interrupt(signum, frame)

    def _serving(self, signum, frame) -> None:
        self.received.append(signum)
        if hasattr(self.node, "finished"):
            self.node.finished = True              # a plant's episode ends at the next sample

    def executor(self, context=None):
        """rclpy's EventsExecutor whose ``spin_once`` raises KeyboardInterrupt on its
        return once a signal came while serving; later signals are deferred to it."""

        received = self.received

        class GuardedEventsExecutor(_rclpy.EventsExecutor):
            def spin_once(self, timeout_sec=None):
                super().spin_once(timeout_sec=timeout_sec)
                if received:
                    raise KeyboardInterrupt            # here no callback is running
        context = context or rclpy.get_default_context()
        faulthandler.enable()                          # as rclpy.experimental.EventsExecutor does
        ex = GuardedEventsExecutor(context)
        context.on_shutdown(ex.wake)
        for sig in self._previous:
            signal.signal(sig, self._serving)
        return ex

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()


def node_main(args, make_node, serve) -> None:
    """A node's ``main``: ``with rclpy.init(args=args):``, the node from
    ``make_node()`` on an EventsExecutor, then ``serve(executor, node)``.

    A bad parameter at start-up ends in one line naming it and exit status 2;
    Ctrl-C and SIGTERM (:class:`NodeSignals`) close the node and the context,
    then raise KeyboardInterrupt for the command line to end with one line and 130."""
    prog = (args or sys.argv)[0].split("/")[-1] if (args or sys.argv) else "node"
    try:
        check_params_files(args if args is not None else sys.argv)
    except HasControlError as exc:
        print(f"{prog}: error: {exc}".splitlines()[0], file=sys.stderr)
        raise SystemExit(2) from None
    signals = NodeSignals()
    signals.install()
    interrupted = False
    try:
        with _init(args, prog):
            try:
                node = make_node()
            except (HasControlError, ValueError, ParameterException, NameValidationException) as exc:
                print(f"{prog}: error: {exc}".splitlines()[0], file=sys.stderr)
                raise SystemExit(2) from None
            signals.node = node
            executor = signals.executor()
            executor.add_node(node)
            gc.freeze()                    # start-up's objects out of the collector's way of the loop
            try:
                serve(executor, node)
            except KeyboardInterrupt:
                interrupted = True
            finally:
                if interrupted or signals.received:
                    # the stop's one line is the command's: what a worker thread of the node (the tuner's
                    # session) says while the node and the context close under it is not news
                    node.get_logger().set_level(LoggingSeverity.FATAL)
                executor.shutdown()
                try:
                    node.destroy_node()
                except Exception:          # noqa: BLE001  already destroyed by serve; the stop goes on
                    pass
    except ExternalShutdownException:
        pass
    finally:
        signals.restore()
    if interrupted or signals.received:
        raise KeyboardInterrupt


def params_files(argv) -> list[str]:
    """The files of ``--params-file FILE`` in a command line's ROS arguments."""
    argv = list(argv or [])
    out = []
    for i, a in enumerate(argv):
        if a == "--params-file":
            if i + 1 >= len(argv) or argv[i + 1].startswith("--"):
                raise HasControlError("--params-file: expects a file")
            out.append(argv[i + 1])
    return out


def check_params_files(argv) -> None:
    """Before ``rclpy.init``: each ``--params-file`` read by the project's own
    reader (:func:`has_control.config.params_file.read_parameter_file`: a
    regular UTF-8 file of bounded size, safe YAML, a ``ros__parameters``
    section under every top-level key, no key given twice), so a bad file is
    one line naming it instead of rcl's "Couldn't parse params file". The
    values are checked when the node declares them."""
    for f in params_files(argv):
        for key, value in read_parameter_file(f, node="/start_up_check").items():
            if isinstance(value, list) and len({type(v) for v in value}) > 1:
                raise HasControlError(f"{f}: {key} = {shown(value)}: a ROS parameter's list holds one type")


@contextmanager
def _stderr_held():
    """File descriptor 2 (what C code such as rcl's logger writes to) goes to
    a temporary file while the block runs; yields a list that then holds
    the bytes written."""
    sys.stderr.flush()
    saved = os.dup(2)
    written: list[bytes] = []
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield written
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            written.append(held.read())


@contextmanager
def _init(args, prog: str):
    """``rclpy.init(args=args)``; what rcl refuses after our own check (a
    value rcl's parser does not take) is one line and exit 2: rcl's own
    ``[ERROR]`` log line is held back (its text is in the exception), what
    rcl writes during a start-up that succeeds is passed on."""
    refused = None
    with _stderr_held() as held:
        try:
            init = rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)   # NodeSignals's
        except RCLError as exc:
            refused = exc
    if refused is not None:
        why = " ".join(str(refused).split())
        files = params_files(args if args is not None else sys.argv)
        print(f"{prog}: error: {', '.join(files) + ': ' if files else ''}ROS refused the arguments: {why[:200]}",
              file=sys.stderr)
        raise SystemExit(2) from None
    if held[0]:
        sys.stderr.write(held[0].decode(errors="replace"))
        sys.stderr.flush()
    with init:
        yield


def trigger_service(node, name: str, action, message: str):
    """A std_srvs/Trigger service ``name`` that calls ``action()`` and answers ``message``,
    or, when ``action()`` returns a reason (a string: it refused), success false with that reason."""
    def on_call(request, response):
        refused = action()
        response.success = not isinstance(refused, str)
        response.message = refused if isinstance(refused, str) else message
        return response
    return node.create_service(Trigger, name, on_call)
