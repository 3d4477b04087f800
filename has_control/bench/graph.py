"""Speed of the node graph against bare rclpy loops measured in the same run.

Part of ``scripts/bench`` (``scripts/bench --graph`` runs it alone). Prints
figures, never a pass/fail. The baselines are the floor rclpy sets here: a
round trip of one ``sensor_msgs/JointState`` each way as serialized bytes
(``publish(bytes)``, ``raw=True``), reliable, keep-last 1, between two nodes
on one EventsExecutor, and between two processes. The graph is measured
lock-step (as fast as it goes) and paced to real time, composed in one
process and as ``ros2 run``-style processes. Each figure is the best of
``repeats`` runs, the layouts alternated within one session.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

STEP = 0.0003


def _env(domain: int) -> dict:
    return dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain))


def _domain() -> int:
    return 200 + os.getpid() % 30


def _bare_nodes(context, echo_in_process: bool):
    import rclpy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from has_control.wire.topics import COMMAND, STATE, STATE_NAMES
    from has_control.nodes.runtime import CONTROL_QOS
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

    from has_control.wire.topics import COMMAND, COMMAND_NAMES, STATE
    from has_control.nodes.runtime import CONTROL_QOS
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


def _processes(duration: float, domain: int, realtime: bool) -> dict:
    """Plant and controller as two processes (``has-control plant`` / ``controller``)."""
    n = int(round(duration / STEP))
    cli = [sys.executable, "-m", "has_control.cli.main"]
    env = _env(domain)
    controller = subprocess.Popen(cli + ["controller"], env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
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
    from has_control.config import with_horizon
    from has_control.core.params import Config
    from has_control.nodes.stack import run_stack
    run = run_stack(with_horizon(Config(), duration), domain_id=domain, publish_internals=True, **kw)
    n = len(run.trace)
    return {**run.loop, "seconds": run.seconds, "bag": run.bag,
            "with_close": n / (n / run.loop["samples_per_second"] + run.close_seconds)}


def bench_graph(duration: float = 3.0, repeats: int = 3) -> dict:
    """Every figure of the table in the README, best of ``repeats``."""
    domain = _domain()
    n = int(round(duration / STEP))
    best: dict[str, dict] = {}

    def keep(key: str, r: dict, by: str = "samples_per_second") -> None:
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
            keep("realtime_one", _stack(duration, domain, realtime=True), by="realtime_factor")
            keep("realtime_two", _processes(duration, domain, realtime=True), by="realtime_factor")
        best["recorded_one"]["bag_mib"] = sum(
            f.stat().st_size for f in best["recorded_one"].pop("bag").iterdir()) / 2**20
    best["graph_one"].pop("bag")
    best["realtime_one"].pop("bag")
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
    for key, what in (("realtime_one", "one process"), ("realtime_two", "two processes")):
        r = g[key]
        if "error" in r:
            print(f"  realtime, {what}: no result: {r['error']}")
            continue
        total = g["samples"]
        late = f"{r['late_p99_us']:.0f} us" if r.get("late_p99_us") is not None else "n/a"
        print(f"  realtime, {what:<13}: real-time factor {r['realtime_factor']:.4f}, missed "
              f"{r['missed_samples']} ({100 * r['missed_samples'] / total:.2f} %), fail-safe "
              f"{r['failsafe_samples']}, lateness p99 {late}")


def _echo_main() -> None:
    import rclpy
    from rclpy.experimental import EventsExecutor

    from has_control.nodes.runtime import spin
    with rclpy.init():
        ex = EventsExecutor()
        ex.add_node(_echo_node(None))
        spin(ex)


if __name__ == "__main__":
    if sys.argv[1:] == ["--echo"]:
        try:
            _echo_main()
        except KeyboardInterrupt:
            pass
    else:
        print_graph(bench_graph(repeats=int(sys.argv[1]) if len(sys.argv) > 1 else 3))
