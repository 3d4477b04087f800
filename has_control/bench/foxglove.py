"""Microseconds per message logged through the live view's tap (has_control.nodes.foxglove).

Not a test: prints figures only. Logs N state messages (the loop's bytes)
through ``LiveView.sink`` with no client, then with one client (a separate
process) subscribed to the topic, and a list append (the recorder's tap)
for scale. Run: ``scripts/bench --foxglove``.
"""
from __future__ import annotations

import subprocess
import sys
import time

from has_control.nodes.foxglove import LiveView
from has_control.wire.topics import STATE_LAYOUT

CLIENT = r"""
import asyncio, json, sys, time
import websockets
async def main(port):
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        while (m := json.loads(await ws.recv()))["op"] != "advertise":
            pass
        await ws.send(json.dumps({"op": "subscribe",
                                  "subscriptions": [{"id": 1, "channelId": m["channels"][0]["id"]}]}))
        print("subscribed", flush=True)
        n, end = 0, time.monotonic() + float(sys.argv[2])
        while time.monotonic() < end:
            try:
                f = await asyncio.wait_for(ws.recv(), 0.5)
            except asyncio.TimeoutError:
                continue
            except websockets.ConnectionClosed:
                break
            n += isinstance(f, bytes)
        print(n, flush=True)
asyncio.run(main(int(sys.argv[1])))
"""


def per_message(take, msgs, n: int) -> float:
    t0 = time.perf_counter()
    for i in range(n):
        take(msgs[i % len(msgs)])
    return (time.perf_counter() - t0) / n * 1e6


def bench_foxglove(n: int = 300_000) -> None:
    """Print the microseconds per message of each tap (``n`` messages each)."""
    msgs = [STATE_LAYOUT.encode([0.01 * i] * 9, i * 300_000) for i in range(1000)]
    sink: list[bytes] = []
    print(f"list append (the recorder's tap): {per_message(sink.append, msgs, n):.3f} us per message")
    with LiveView(port=0) as view:
        take = view.sink("/state")
        print(f"live view, no client:             {per_message(take, msgs, n):.3f} us per message")
        client = subprocess.Popen([sys.executable, "-c", CLIENT, str(view.port), "30"],
                                  stdout=subprocess.PIPE, text=True)
        assert client.stdout.readline().strip() == "subscribed"
        time.sleep(0.3)
        us = per_message(take, msgs, n)
        print(f"live view, one client:            {us:.3f} us per message")
        time.sleep(0.5)
    received = int(client.communicate(timeout=10)[0])         # the server has stopped: the client ends
    print(f"({n:,} messages of {len(msgs[0])} bytes each; the client received {received:,}: "
          "a slow client loses the oldest)")
