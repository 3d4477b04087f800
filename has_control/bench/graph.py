"""Speed of the node graph against bare rclpy loops measured in the same run.

Part of ``scripts/bench`` (``scripts/bench --graph`` runs it alone). Prints
figures, never a pass/fail. The baselines are the floor rclpy sets here: a
round trip of one ``sensor_msgs/JointState`` each way as serialized bytes
(``publish(bytes)``, ``raw=True``), reliable, keep-last 1, between two nodes
on one EventsExecutor, and between two processes. The graph is measured
lock-step (as fast as it goes) and paced to real time, composed in one
process and as ``ros2 run``-style processes. Each figure is the best of
``repeats`` runs, the layouts alternated within one session.

Real time across processes is measured against its limit on this machine:
a bare paced cross-process loop (:func:`bare_paced`: the plant's own pacing,
:func:`~has_control.loop.schedule.run_loop` (paced), with the same period, deadline
rule and priority, driving raw state bytes to a second process that answers
each with a command stamped like it, no plant or controller arithmetic).
The live-view row runs ``stack --realtime`` in one process with a Foxglove
client subscribed to every channel, beside the same run without one.
"""
from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from has_control.config import with_horizon
from has_control.core.params import Config
from has_control.loop.schedule import Paced, run_loop
from has_control.nodes.runtime import CONTROL_QOS, spin
from has_control.nodes.stack import run_stack
from has_control.wire.topics import COMMAND, COMMAND_LAYOUT, COMMAND_NAMES, RUN_TOPICS, STATE, STATE_LAYOUT, STATE_NAMES

STEP = Config().episode.step           # [s], the reference configuration's


def _env(domain: int) -> dict:
    return dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain))


def _domain() -> int:
    return 200 + os.getpid() % 30


def _bare_nodes(context, echo_in_process: bool):
    import rclpy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    a = rclpy.create_node("bare_plant", context=context)
    state = serialize_message(JointState(name=STATE_NAMES, position=[0.0] * 3, velocity=[0.0] * 3,
                                         effort=[0.0] * 3))
    pub = a.create_publisher(JointState, STATE, CONTROL_QOS)
    got = [0]
    a.create_subscription(JointState, COMMAND, lambda d: got.__setitem__(0, got[0] + 1), CONTROL_QOS, raw=True)
    nodes = [a]
    if echo_in_process:
        nodes.append(_echo_node(context))
    return nodes, pub, state, got


def _echo_node(context):
    """Answers every state with a one-joint command, as bytes."""
    import rclpy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    b = rclpy.create_node("bare_controller", context=context)
    command = serialize_message(JointState(name=COMMAND_NAMES, position=[0.0]))
    out = b.create_publisher(JointState, COMMAND, CONTROL_QOS)
    b.create_subscription(JointState, STATE, lambda d: out.publish(command), CONTROL_QOS, raw=True)
    return b


def bare_round_trips(samples: int, two_processes: bool, domain: int) -> float:
    """Round trips per second of the bare raw loop."""
    import gc

    import rclpy
    from rclpy.experimental import EventsExecutor
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    echo = None
    try:
        if two_processes:
            echo = subprocess.Popen([sys.executable, "-m", "has_control.bench.graph", "--echo"],
                                    env=_env(domain), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        nodes, pub, state, got = _bare_nodes(ctx, not two_processes)
        ex = EventsExecutor(context=ctx)
        for n in nodes:
            ex.add_node(n)
        end = time.monotonic() + 60
        while got[0] == 0 and time.monotonic() < end:      # matched both ways, echo warm
            pub.publish(state)
            ex.spin_once(timeout_sec=0.05)
        gc.disable()
        t0 = time.perf_counter()
        for _ in range(samples):
            want = got[0] + 1
            pub.publish(state)
            while got[0] < want:
                ex.spin_once(timeout_sec=1.0)
        rate = samples / (time.perf_counter() - t0)
        gc.enable()
        ex.shutdown()
        for n in nodes:
            n.destroy_node()
        return rate
    finally:
        if echo is not None:
            echo.terminate()
            echo.wait(timeout=30)
        rclpy.try_shutdown(context=ctx)


class _BarePlant:
    """The plant's side of the bare paced loop, for :func:`~has_control.loop.schedule.run_loop` (paced):
    state bytes stamped with the sample out, the stamp of each answer in; nothing computed."""

    failsafe_samples = 10

    def __init__(self, node, samples: int, step_ns: int):
        from sensor_msgs.msg import JointState

        self.node, self.samples, self.step_ns = node, samples, step_ns
        self.sample, self.finished = 0, False
        self.command_sample, self.command_u = -1, 0.0
        self._state = bytearray(STATE_LAYOUT.encode([0.0] * 9))
        self.pub = node.create_publisher(JointState, STATE, CONTROL_QOS)
        self.sub = node.create_subscription(JointState, COMMAND, self._on_command, CONTROL_QOS, raw=True)

    def _on_command(self, data: bytes) -> None:
        sec, nsec = struct.unpack_from("<iI", data, 4)
        self.command_sample = (sec * 1_000_000_000 + nsec) // self.step_ns

    def publish_state(self) -> None:
        struct.pack_into("<iI", self._state, 4, *divmod(self.sample * self.step_ns, 1_000_000_000))
        self.pub.publish(bytes(self._state))

    def first_answer_timeout(self) -> float:
        return 5.0

    def step(self, u: float, answered: bool = True) -> bool:
        self.sample += 1
        self.finished = self.sample >= self.samples
        return not self.finished

    def failsafe(self, missing: int) -> None:
        pass

    def commands_back(self) -> None:
        pass

    @property
    def logger(self):
        return self.node.get_logger()


def bare_paced(samples: int, domain: int) -> dict:
    """The bare paced cross-process loop, both sides fresh processes as the stack's
    plant and controller are: missed samples, fail-safe samples, lateness."""
    import json
    r = subprocess.run([sys.executable, "-m", "has_control.bench.graph", "--bare-paced", str(samples)],
                       env=_env(domain), capture_output=True, text=True, timeout=600)
    try:
        return json.loads(r.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"error": (r.stdout + r.stderr)[-400:]}


def _bare_paced_here(samples: int, domain: int | None, priority: int = 50, warm_up: int = 200) -> dict:
    """The plant's side of :func:`bare_paced`, in this process (its echo in another)."""
    import gc

    import rclpy
    from rclpy.experimental import EventsExecutor

    step_ns = Config().episode.step_ns
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    echo = subprocess.Popen([sys.executable, "-m", "has_control.bench.graph", "--stamp-echo"],
                            env=os.environ if domain is None else _env(domain),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        node = rclpy.create_node("bare_paced_plant", context=ctx)
        plant = _BarePlant(node, samples, step_ns)
        ex = EventsExecutor(context=ctx)
        ex.add_node(node)
        end = time.monotonic() + 60
        answered = 0
        while answered < warm_up and time.monotonic() < end:       # matched both ways, echo warm
            plant.command_sample = -1
            plant.publish_state()
            stop = time.monotonic() + 0.05
            while plant.command_sample != 0 and time.monotonic() < stop:
                ex.spin_once(timeout_sec=0.01)
            answered += plant.command_sample == 0
        if answered < warm_up:
            return {"error": "the echo process did not answer"}
        plant.command_sample = -1
        gc.collect()
        paced = Paced(failsafe_samples=plant.failsafe_samples)
        st = run_loop(plant, ex.spin_once, paced, priority=priority).as_dict()
        ex.shutdown()
        node.destroy_node()
        return {"samples_per_second": st["rate_hz"], "realtime_factor": st["realtime_factor"],
                "missed_samples": int(st["missed_samples"]), "failsafe_samples": int(st["failsafe_samples"]),
                "late_p99_us": st["late_p99_us"]}
    finally:
        echo.terminate()
        echo.wait(timeout=30)
        rclpy.try_shutdown(context=ctx)


def _stamp_echo_main() -> None:
    """The bare loop's other process: answer each state with a command stamped like it, as bytes."""
    import gc

    import rclpy
    from rclpy.experimental import EventsExecutor
    from sensor_msgs.msg import JointState

    with rclpy.init():
        node = rclpy.create_node("bare_paced_echo")
        command = bytearray(COMMAND_LAYOUT.encode([0.0]))
        out = node.create_publisher(JointState, COMMAND, CONTROL_QOS)

        def answer(data: bytes) -> None:
            command[4:12] = data[4:12]
            out.publish(bytes(command))
        node.create_subscription(JointState, STATE, answer, CONTROL_QOS, raw=True)
        ex = EventsExecutor()
        ex.add_node(node)
        gc.freeze()                           # as a controller process: no collector pause in the loop
        gc.disable()
        spin(ex)


LIVE_CLIENT = r"""
import asyncio, json, sys, time
import websockets
async def main(port, seconds):
    end = time.monotonic() + 60
    while True:
        try:
            ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], max_size=None)
            break
        except OSError:
            if time.monotonic() > end:
                return
            await asyncio.sleep(0.05)
    async with ws:
        channels, until = {}, time.monotonic() + 60
        while len(channels) < int(sys.argv[3]) and time.monotonic() < until:     # every run topic
            try:
                m = await asyncio.wait_for(ws.recv(), 0.1)
            except asyncio.TimeoutError:
                continue
            if isinstance(m, str) and json.loads(m)["op"] == "advertise":
                channels.update({c["id"]: c["topic"] for c in json.loads(m)["channels"]})
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": c} for k, c in enumerate(channels)]}))
        n, end = 0, time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                n += isinstance(await asyncio.wait_for(ws.recv(), 0.5), bytes)
            except asyncio.TimeoutError:
                continue
            except websockets.ConnectionClosed:
                break
        print(len(channels), n, flush=True)
asyncio.run(main(int(sys.argv[1]), float(sys.argv[2])))
"""


def _live_view_run(duration: float, domain: int) -> dict:
    """``stack --realtime`` in one process, a Foxglove client subscribed to every channel."""
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    client = subprocess.Popen([sys.executable, "-c", LIVE_CLIENT, str(port), str(duration + 30), str(len(RUN_TOPICS))],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        r = _stack(duration, domain, realtime=True, foxglove=port, foxglove_wait=60.0)
    finally:
        client.terminate()
        out = client.communicate(timeout=30)[0]
    r["client"] = out.strip()
    return r


def _processes(duration: float, domain: int, realtime: bool, internals: bool = True) -> dict:
    """Plant and controller as two processes (``has-control plant`` / ``controller``;
    ``internals``: the controller publishes ~/controller_state and ~/reference too)."""
    n = int(round(duration / STEP))
    cli = [sys.executable, "-m", "has_control.cli.main"]
    env = _env(domain)
    controller = subprocess.Popen(cli + ["controller", "--ros-args", "-p", f"publish_internals:={internals}"],
                                  env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        plant = subprocess.run(cli + ["plant", "--ros-args", "-p", f"samples:={n}", "-p", "command_timeout:=5.0",
                                      "-p", f"mode:={'realtime' if realtime else 'lockstep'}"],
                               env=env, capture_output=True, text=True, timeout=600)
    finally:
        controller.terminate()
        controller.wait(timeout=30)
    log = plant.stdout + plant.stderr
    if realtime:
        m = re.search(r"realtime: (\d+) samples/s, real-time factor ([\d.]+), (\d+) missed, (\d+) fail-safe, "
                      r"lateness p50 (\d+) us, p99 (\d+) us", log)
        if not m:
            return {"error": log[-400:]}
        return {"samples_per_second": float(m.group(1)), "realtime_factor": float(m.group(2)),
                "missed_samples": int(m.group(3)), "failsafe_samples": int(m.group(4)),
                "late_p99_us": float(m.group(6))}
    m = re.search(r"fail-safe events = (\d+), (\d+) samples/s", log)
    if not m:
        return {"error": log[-400:]}
    return {"samples_per_second": float(m.group(2)), "failsafe_samples": int(m.group(1))}


def _stack(duration: float, domain: int, **kw) -> dict:
    run = run_stack(with_horizon(Config(), duration), domain_id=domain, publish_internals=True, **kw)
    n = len(run.run)
    return {**run.loop, "seconds": run.seconds, "bag": run.bag,
            "with_close": n / (n / run.loop["samples_per_second"] + run.close_seconds)}


def bench_graph(duration: float = 3.0, repeats: int = 3) -> dict:
    """Every figure of the table in the README, best of ``repeats``."""
    domain = _domain()
    n = int(round(duration / STEP))
    best: dict[str, dict] = {}

    def keep(key: str, r: dict, by: str = "samples_per_second") -> None:
        if by == "fewest_missed" and "error" not in r:
            r["fewest_missed"] = -(r["missed_samples"] + r["failsafe_samples"])
        if "error" in r:
            best.setdefault(key, r)
        elif "error" in best.get(key, {"error": 1}) or r[by] > best[key][by]:
            best[key] = r
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            keep("bare_one", {"samples_per_second": bare_round_trips(n, False, domain)})
            keep("graph_one", _stack(duration, domain))
            keep("bare_two", {"samples_per_second": bare_round_trips(n, True, domain)})
            keep("graph_two", _processes(duration, domain, realtime=False))
            keep("recorded_one", _stack(duration, domain, record=Path(tmp) / f"run{k}"), by="with_close")
            keep("realtime_one", _stack(duration, domain, realtime=True), by="fewest_missed")
            keep("realtime_two", _processes(duration, domain, realtime=True), by="fewest_missed")
            keep("bare_paced_two", bare_paced(n, domain), by="fewest_missed")
            keep("live_view_one", _live_view_run(duration, domain), by="fewest_missed")
        best["recorded_one"]["bag_mib"] = sum(
            f.stat().st_size for f in best["recorded_one"].pop("bag").iterdir()) / 2**20
    for key in ("graph_one", "realtime_one", "live_view_one"):
        best[key].pop("bag", None)
    best["samples"] = n
    return best


def print_graph(g: dict) -> None:
    def rate(key):
        r = g[key]
        return "no result: " + r["error"] if "error" in r else f"{r['samples_per_second']:>9,.0f}"
    one, two = g["bare_one"]["samples_per_second"], g["bare_two"]["samples_per_second"]
    print(f"node graph, {g['samples']:,} samples of 0.3 ms (real time is 3,333 samples/s), best of each:")
    print("  layout                                   samples/s   vs bare loop")
    print(f"  bare raw round trip, one process         {rate('bare_one')}")
    print(f"  lock-step graph, one process             {rate('graph_one')}   "
          f"{g['graph_one']['samples_per_second'] / one:.2f}x (controller internals published)")
    rec = g["recorded_one"]
    print(f"  lock-step graph, recorded to MCAP        {rec['with_close']:>9,.0f}   "
          f"recording overhead {100 * (g['graph_one']['samples_per_second'] / rec['with_close'] - 1):.0f} % "
          f"(closing the bag included; {rec['bag_mib']:.1f} MiB bag)")
    print(f"  bare raw round trip, two processes       {rate('bare_two')}")
    if "error" not in g["graph_two"]:
        print(f"  lock-step graph, two processes           {rate('graph_two')}   "
              f"{g['graph_two']['samples_per_second'] / two:.2f}x")
    else:
        print(f"  lock-step graph, two processes           {rate('graph_two')}")
    total = g["samples"]
    rows = (("realtime_one", "realtime, one process"),
            ("live_view_one", "realtime, one process, Foxglove client on every channel"),
            ("bare_paced_two", "bare paced loop, two processes (the limit)"),
            ("realtime_two", "realtime, two processes (the stack)"))
    print("  real time (paced at 0.3 ms, fewest missed of each):")
    for key, what in rows:
        r = g[key]
        if "error" in r:
            print(f"    {what}: no result: {r['error']}")
            continue
        late = f"{r['late_p99_us']:.0f} us" if r.get("late_p99_us") is not None else "n/a"
        print(f"    {what}: real-time factor {r['realtime_factor']:.4f}, missed "
              f"{r['missed_samples']} ({100 * r['missed_samples'] / total:.2f} %), fail-safe "
              f"{r['failsafe_samples']}, lateness p99 {late}")
    bare, stack = g["bare_paced_two"], g["realtime_two"]
    if "error" not in bare and "error" not in stack:
        ratio = stack["missed_samples"] / bare["missed_samples"] if bare["missed_samples"] else float("inf")
        print(f"    across processes the stack misses {ratio:.2f}x the bare loop's samples "
              f"({stack['missed_samples']} vs {bare['missed_samples']}; target <= 1.5x)")
    live, alone = g["live_view_one"], g["realtime_one"]
    if "error" not in live and "error" not in alone:
        print(f"    the live view adds {live['missed_samples'] - alone['missed_samples']} missed "
              f"({100 * (live['missed_samples'] - alone['missed_samples']) / total:+.3f} % of samples) and "
              f"{live['failsafe_samples'] - alone['failsafe_samples']} fail-safe samples "
              f"(client: {' channels, '.join(live.get('client', '? ?').split()[:2])} messages received; "
              "target <= 0.1 %, 0 fail-safe)")


def _echo_main() -> None:
    import rclpy
    from rclpy.experimental import EventsExecutor

    with rclpy.init():
        ex = EventsExecutor()
        ex.add_node(_echo_node(None))
        spin(ex)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--bare-paced"]:
        import json
        print(json.dumps(_bare_paced_here(int(sys.argv[2]), None)))
    elif sys.argv[1:] in (["--echo"], ["--stamp-echo"]):
        try:
            _echo_main() if sys.argv[1] == "--echo" else _stamp_echo_main()
        except KeyboardInterrupt:
            pass
    else:
        print_graph(bench_graph(repeats=int(sys.argv[1]) if len(sys.argv) > 1 else 3))
