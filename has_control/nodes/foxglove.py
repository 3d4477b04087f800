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
"""
from __future__ import annotations

import struct
import threading
from typing import Callable

from has_control.common.errors import HasControlError
from has_control.wire.topics import CLOCK, JOINT_STATE, LAYOUTS, RUN_TOPICS
from has_control.bag import msgdef

DEFAULT_PORT = 8765
PARAMETER = "foxglove_port"

#: The run topics' types by the last part of their name (``gains``, ``state``,
#: ...): a node's full topic names depend on its namespace and name.
_TYPES = {rel.rsplit("/", 1)[-1]: ty for rel, ty in RUN_TOPICS.items()}

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
    import foxglove

    return foxglove.Schema(name=msgtype, encoding="ros2msg", data=msgdef(msgtype).encode())


class LiveView:
    """A Foxglove WebSocket server on ``host:port`` for the run topics; ``port``
    0 picks a free one (:attr:`port` says which)."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1", name: str = "has_control",
                 what: str = "--foxglove"):
        try:
            import foxglove
        except ImportError:
            raise HasControlError(f"{what} {port}: needs foxglove-sdk (pip install foxglove-sdk)") from None
        if port != 0:
            check_port(port, what)
        self._foxglove = foxglove
        self._context = foxglove.Context()       # its own: two views in one process stay apart
        self._schemas: dict[str, object] = {}
        self.channels: dict[str, object] = {}
        self.subscribed = threading.Event()      # a client has subscribed to a channel
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self._context,
                                                server_listener=self)
        except RuntimeError as exc:
            reason = str(exc).removeprefix("FoxgloveError: ")
            raise HasControlError(f"{what} {port}: {reason}") from None
        self.port = self.server.port

    def on_subscribe(self, client, channel) -> None:
        """The server's listener: a client subscribed to ``channel``."""
        self.subscribed.set()

    def on_unsubscribe(self, client, channel) -> None:
        """The server's listener: nothing to do."""

    def wait_for_client(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for a client to subscribe to a channel; whether one did."""
        return self.subscribed.wait(timeout)

    def channel(self, topic: str):
        """The channel of ``topic`` (a full name), created on first use."""
        if topic not in self.channels:
            rel = topic.rsplit("/", 1)[-1]
            if rel not in _TYPES:
                raise HasControlError(f"live view: {topic}: not a run topic ({', '.join(RUN_TOPICS)})")
            msgtype = _TYPES[rel]
            if msgtype not in self._schemas:
                self._schemas[msgtype] = _schema(msgtype)
            self.channels[topic] = self._foxglove.Channel(
                topic, schema=self._schemas[msgtype], message_encoding="cdr", context=self._context)
        return self.channels[topic]

    def sink(self, topic: str) -> Callable[[bytes], None]:
        """The tap for ``topic`` (its full name): a function that logs each
        message as published, with its simulation time as log time [ns]."""
        log = self.channel(topic).base.log          # the SDK's call, past Channel.log's type checks
        if _TYPES[topic.rsplit("/", 1)[-1]] in (JOINT_STATE, CLOCK):
            def take(data: bytes) -> None:
                try:
                    sec, nsec = _STAMP(data, 4)
                except struct.error:
                    log(data)
                    return
                log(data, sec * 1_000_000_000 + nsec)
        else:
            offset = _T_OFFSETS[topic.rsplit("/", 1)[-1]]

            def take(data: bytes) -> None:
                try:
                    t = _T(data, offset)[0]
                except struct.error:
                    log(data)
                    return
                log(data, round(t * 1e9) if 0.0 <= t < 9e9 else None)
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
