"""Live view: the loop's topics served on a Foxglove WebSocket from the CDR bytes already in hand.

A :class:`LiveView` runs a foxglove-sdk WebSocket server (loopback by
default) with one channel per run topic (message encoding ``cdr``, schema
encoding ``ros2msg``, schema name the ROS type, the schema text as in our
MCAP bags). :meth:`LiveView.sink` is a tap like
:meth:`~has_control.nodes.recorder.Recorder.sink`: the nodes hand it the
bytes they publish and it logs them, never re-encoding, with log time the
message's simulation time (the stamp of JointState and Clock, the leading t
of our Float64MultiArray topics). With no client subscribed a message costs
a struct unpack and one call into the SDK; a slow client loses the oldest
messages (the SDK's per-client backlog), never slows the loop down.

``has-control stack --foxglove [PORT]`` serves both nodes' topics on one
server; the plant and controller nodes serve their own with the parameter
``foxglove_port`` (:func:`has_control.nodes.live_tap.node_tap`). Open it in Foxglove with
``ws://127.0.0.1:PORT``.

Besides the ROS topics as they are, the view serves what a viewer needs to
show the run by name: each Float64MultiArray topic (``controller_state``,
``reference``, ``gains``) also as ``TOPIC/named``, a JSON channel (schema
``jsonschema``) with one field per column (``e1``, ``a1_hat``, ...) and a
``header.stamp`` of the sample's simulation time; and the nodes'
``/diagnostics`` (handed to it by :func:`has_control.nodes.runtime.publish_diagnostics`),
logged at the newest simulation time the view has served, so that every
channel shares one time base. The shipped layout
``config/foxglove/has_control.json`` reads these channels only.
"""
from __future__ import annotations

import json
import math
import struct
import threading
from typing import Callable

from has_control.common.errors import HasControlError
from has_control.wire.topics import (CLOCK, CONTROLLER_STATE, CONTROLLER_STATE_COLUMNS, GAINS, GAINS_COLUMNS,
                                     JOINT_STATE, LAYOUTS, QOS, REFERENCE, REFERENCE_COLUMNS, RUN_TOPICS)
from has_control.bag import msgdef

DEFAULT_PORT = 8765
PARAMETER = "foxglove_port"
DIAGNOSTICS = "/diagnostics"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
#: The suffix of the JSON channel that serves a Float64MultiArray topic's columns by name.
NAMED = "/named"

#: The run topics' types by the last part of their name (``gains``, ``state``,
#: ...): a node's full topic names depend on its namespace and name; and the nodes' diagnostics.
_TYPES = {**{rel.rsplit("/", 1)[-1]: ty for rel, ty in RUN_TOPICS.items()}, "diagnostics": DIAGNOSTIC_ARRAY}
#: Topics offered transient local (the gains in force): the view logs their newest message again
#: for a client that subscribes later (:meth:`LiveView.relatch`), as a late ROS subscriber gets it.
_LATCHED = {rel.rsplit("/", 1)[-1] for rel, (_, transient_local) in QOS.items() if transient_local}
#: The columns of each Float64MultiArray topic (by the last part of its name), served by name on TOPIC/named.
_COLUMNS = {rel.rsplit("/", 1)[-1]: cols for rel, cols in
            ((CONTROLLER_STATE, CONTROLLER_STATE_COLUMNS), (REFERENCE, REFERENCE_COLUMNS), (GAINS, GAINS_COLUMNS))}

_STAMP = struct.Struct("<iI").unpack_from        # header.stamp / Clock.clock at byte 4
_T = struct.Struct("<d").unpack_from             # data[0] = t of our Float64MultiArray layouts
#: Where data[0] = t sits in each Float64MultiArray topic (by the last part of its name).
_T_OFFSETS = {rel.rsplit("/", 1)[-1]: int(lay.values[0]) for rel, lay in LAYOUTS.items() if not lay.stamped}


def check_port(port, what: str) -> int:
    """``port`` if it is a TCP port 1..65535, else an error naming ``what``."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise HasControlError(f"{what} {port!r}: expected a port 1..65535")
    return port


def _schema(msgtype: str):
    import foxglove                              # lazy: foxglove-sdk is the optional "live" extra

    return foxglove.Schema(name=msgtype, encoding="ros2msg", data=msgdef(msgtype).encode())


def named_schema(rel: str) -> dict:
    """The JSON schema of ``TOPIC/named`` for the Float64MultiArray topic ``rel``:
    ``header.stamp`` {sec, nsec} (the sample's simulation time) and one number per column
    (null where the value is not finite: JSON has no NaN)."""
    stamp = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
    header = {"type": "object", "properties": {"stamp": stamp, "frame_id": {"type": "string"}}}
    return {"type": "object", "title": f"has_control/{rel}",
            "properties": {"header": header, **{c: {"type": ["number", "null"]} for c in _COLUMNS[rel]}}}


def named_message(columns: tuple[str, ...], values, log_ns: int | None) -> bytes:
    """A ``TOPIC/named`` message: the columns' ``values`` by name, stamped ``log_ns``."""
    ns = log_ns or 0
    msg = {"header": {"stamp": {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}, "frame_id": ""}}
    msg.update({c: (v if math.isfinite(v) else None) for c, v in zip(columns, values)})
    return json.dumps(msg).encode()


class LiveView:
    """A Foxglove WebSocket server on ``host:port`` for the run topics; ``port``
    0 picks a free one (:attr:`port` says which)."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1", name: str = "has_control",
                 what: str = "--foxglove"):
        try:
            import foxglove                          # lazy: foxglove-sdk is the optional "live" extra
        except ImportError:
            raise HasControlError(f"{what} {port}: needs foxglove-sdk (pip install foxglove-sdk)") from None
        if port != 0:
            check_port(port, what)
        self._foxglove = foxglove
        self._context = foxglove.Context()       # its own: two views in one process stay apart
        self._schemas: dict[str, object] = {}
        self.channels: dict[str, object] = {}
        self.subscribed = threading.Event()      # a client has subscribed to a channel
        self._now = [0]                          # the newest simulation time served [ns]: /diagnostics' log time
        self._latest: dict[str, tuple] = {}      # transient-local topics: their newest message (take, data)
        self._subscriptions = [0, 0]             # subscriptions seen, and relatched for
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self._context,
                                                server_listener=self)
        except RuntimeError as exc:
            reason = str(exc).removeprefix("FoxgloveError: ")
            raise HasControlError(f"{what} {port}: {reason}") from None
        self.port = self.server.port

    def on_subscribe(self, client, channel) -> None:
        """The server's listener: a client subscribed to ``channel``."""
        self._subscriptions[0] += 1
        self.subscribed.set()

    def relatch(self) -> None:
        """After a new subscription: the newest message of each transient-local
        topic logged again (called by the viewer's loop, off the server's thread)."""
        seen = self._subscriptions[0]
        if seen != self._subscriptions[1]:
            self._subscriptions[1] = seen
            for take, data in list(self._latest.values()):
                take(data)

    def on_unsubscribe(self, client, channel) -> None:
        """The server's listener: nothing to do."""

    def wait_for_client(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for a client to subscribe to a channel; whether one did."""
        return self.subscribed.wait(timeout)

    def channel(self, topic: str):
        """The channel of ``topic`` (a full name), created on first use; a
        Float64MultiArray topic's ``TOPIC/named`` JSON channel with it."""
        if topic not in self.channels:
            rel = topic.rsplit("/", 1)[-1]
            if rel not in _TYPES:
                raise HasControlError(f"live view: {topic}: not a run topic ({', '.join(RUN_TOPICS)})")
            msgtype = _TYPES[rel]
            if msgtype not in self._schemas:
                self._schemas[msgtype] = _schema(msgtype)
            self.channels[topic] = self._foxglove.Channel(
                topic, schema=self._schemas[msgtype], message_encoding="cdr", context=self._context)
            if rel in _COLUMNS:
                schema = self._foxglove.Schema(name=f"has_control/{rel}", encoding="jsonschema",
                                               data=json.dumps(named_schema(rel)).encode())
                self.channels[topic + NAMED] = self._foxglove.Channel(
                    topic + NAMED, schema=schema, message_encoding="json", context=self._context)
        return self.channels[topic]

    def sink(self, topic: str) -> Callable[[bytes], None]:
        """The tap for ``topic`` (its full name): a function that logs each
        message as published, with its simulation time as log time [ns]."""
        log = self.channel(topic).base.log          # the SDK's call, past Channel.log's type checks
        rel = topic.rsplit("/", 1)[-1]
        take = self._take(topic, rel, log)
        if rel not in _LATCHED:
            return take
        latest = self._latest

        def take_and_keep(data: bytes) -> None:
            latest[topic] = (take, data)
            take(data)
        return take_and_keep

    def _take(self, topic: str, rel: str, log) -> Callable[[bytes], None]:
        now = self._now
        if _TYPES[rel] == DIAGNOSTIC_ARRAY:
            def take(data: bytes) -> None:
                log(data, now[0])                    # the run's time base, not the wall clock of its header
        elif _TYPES[rel] in (JOINT_STATE, CLOCK):
            def take(data: bytes) -> None:
                try:
                    sec, nsec = _STAMP(data, 4)
                except struct.error:
                    log(data)
                    return
                now[0] = max(now[0], sec * 1_000_000_000 + nsec)
                log(data, sec * 1_000_000_000 + nsec)
        else:
            offset, columns = _T_OFFSETS[rel], _COLUMNS.get(rel)
            values = struct.Struct(f"<{len(columns)}d").unpack_from if columns else None
            named = self.channels[topic + NAMED].base.log if columns else None
            wanted = self.channels[topic + NAMED].has_sinks if columns else None   # a client subscribed to it

            def take(data: bytes) -> None:
                try:
                    t = _T(data, offset)[0]
                except struct.error:
                    log(data)
                    return
                log_ns = round(t * 1e9) if 0.0 <= t < 9e9 else None
                log(data, log_ns)
                if log_ns is not None:
                    now[0] = max(now[0], log_ns)
                if named is not None and wanted():           # JSON only for a client that reads it
                    try:
                        row = values(data, offset)
                    except struct.error:
                        return
                    named(named_message(columns, row, log_ns), log_ns)
        return take

    def close(self) -> None:
        """Stop the server (clients are disconnected) and close the channels; again: no-op."""
        if self.server is None:
            return
        self.server.stop()
        self.server = None
        for ch in self.channels.values():
            ch.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
