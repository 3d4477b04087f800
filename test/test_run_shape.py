"""One run shape and one compiled reference series (#28 item 5)."""
from __future__ import annotations

import numpy as np
import pytest

from has_control.config import build_config
from has_control.core.episode import EpisodeArrays
from has_control.core.reference import reference, reference_series
from has_control.wire.topics import COMMAND_LAYOUT, MISSED_LAYOUT
from test_loop import Link


@pytest.mark.parametrize("kind", ["sine", "step", "chirp", "road", "zero"])
def test_reference_series_is_the_per_sample_reference_bit_for_bit(kind):
    """The compiled series gives every sample's (x1d, ẋ1d, ẍ1d, x1d⁽³⁾) with the
    bits of a Python call of :func:`reference` per sample (what the bag writer,
    the bag readers and the stack did before)."""
    cfg = build_config({"reference.kind": kind, "simulation.horizon": 2.0})
    rp = EpisodeArrays.from_config(cfg).reference
    t = np.arange(cfg.episode.samples) * cfg.episode.step
    one_by_one = np.array([reference(rp, ti) for ti in t])
    series = reference_series(rp, t)
    assert series.shape == (len(t), 4)
    assert np.array_equal(series.view(np.int64), one_by_one.view(np.int64))
    if kind != "zero":
        assert np.ptp(series[:, 0]) > 0                  # a reference that moves: the test can fail
    strided = reference_series(rp, np.repeat(t, 2)[::2])   # any layout of t
    assert np.array_equal(strided, series)


def _written(tmp_path, trace, cfg):
    """``trace`` written as the graph's messages into a bag with the run's parameters."""
    from has_control.bag import PARAMETERS_KEY, BagWriter, parameters_json, write_trace
    w = BagWriter(tmp_path / "run", {PARAMETERS_KEY: parameters_json(cfg)})
    write_trace(w, trace, cfg)
    return w.close()


def test_simulate_and_the_bag_readers_give_one_run_shape(tmp_path):
    """A simulated run, its bag read for a score and read for a figure: three
    producers, one :class:`Run` (same columns, same bits where each has them)."""
    from has_control.bag import score_bag
    from has_control.bag.series import run_series
    from has_control.core.episode import simulate
    from has_control.core.params import Config
    from has_control.core.run import Col, Run
    cfg = build_config({"simulation.horizon": 2.0}, base=Config())
    trace = simulate(cfg)
    bag = _written(tmp_path, trace, cfg)
    _, scored = score_bag(bag, on_warning=lambda line: None)
    series = run_series(bag, on_warning=lambda line: None)
    shared = [Col.t, Col.x1d, Col.y, Col.ydot, Col.P1, Col.P2, Col.u, Col.e1]
    for run in (trace, scored, series):
        assert isinstance(run, Run) and run.data.shape == (cfg.episode.samples, len(Col))
        assert np.array_equal(run.data[:, shared], trace.data[:, shared])
        assert np.array_equal(run.e1, run.x1d - run.y) and np.array_equal(run["P1"], run.p1)
    assert np.array_equal(series.data[:, [Col.a1_hat, Col.a2_hat]], trace.data[:, [Col.a1_hat, Col.a2_hat]])
    assert np.isnan(scored.a1_hat).all()          # a score reads no controller internals: said as NaN, not zero


def test_the_run_figure_draws_the_run_it_is_given(tmp_path):
    """The figure's view holds the producer's Run itself; a crop is a Run of the kept rows."""
    from has_control.core.episode import simulate
    from has_control.core.params import Config
    from has_control.plots.run_figure import crop, view_of_trace
    cfg = build_config({"simulation.horizon": 2.0}, base=Config())
    trace = simulate(cfg)
    view = view_of_trace(trace, cfg)
    assert view.run is trace and np.shares_memory(view.y, trace.data)
    cut = crop(view, 0.2, 0.4)
    keep = (trace.t >= 0.2) & (trace.t <= 0.4)
    assert np.array_equal(cut.run.data, trace.data[keep]) and 0 < len(cut.run) < len(trace)


class _Link(Link):
    """test_loop's link, keeping what each process publishes as a recorder's
    tap would: states, commands, internals."""

    def __init__(self, drop=lambda i: False):
        super().__init__(drop)
        self.taken = {"state": [], "command": [], "internals": [], "missed": []}

    def publish(self, state, true_state, clock) -> bool:
        self.taken["state"].append(state)
        return super().publish(state, true_state, clock)

    def command(self, data: bytes) -> None:
        self.taken["command"].append(data)
        super().command(data)


def _loop(cfg, schedule, samples, drop=lambda i: False):
    from has_control.loop.controller import ControllerProcess
    from has_control.loop.guards import Conflicts
    from has_control.loop.log import ListLog
    from has_control.loop.plant import PlantProcess
    from has_control.loop.ports import HasControlPort, Outputs
    from has_control.loop.schedule import run_loop
    link, log = _Link(drop), ListLog()
    plant = PlantProcess(cfg, schedule, link, log, samples=samples)
    plant.log, plant.on_unanswered = [], link.taken["missed"].append
    controller = ControllerProcess(cfg, log)
    out = Outputs(link.command, link.command, link.taken["internals"].append, lambda b: None, lambda b: None)
    link.plant, link.port = plant, HasControlPort(controller, out, Conflicts(log))
    plant.start()
    stats = run_loop(plant, link.spin_once, plant.schedule)
    return link, plant, stats


def _run(link, cfg):
    from has_control.wire.run_messages import run_of_messages
    t = link.taken
    return run_of_messages(t["state"], t["command"], t["internals"], t["missed"], cfg.episode.step,
                           cfg.episode.step_ns, EpisodeArrays.from_config(cfg).reference)


def test_the_run_a_recorder_takes_from_the_loops_messages_is_the_library_run():
    """Lock-step: the states, commands and controller states the loop
    exchanged make the run :func:`simulate` gives, bit for bit (the node
    stack's run and score come from these messages)."""
    from has_control.config import with_horizon
    from has_control.core.cost import score_arrays
    from has_control.core.episode import simulate
    from has_control.core.params import Config
    from has_control.loop.schedule import LockStep
    cfg = with_horizon(Config(), 1.5)
    n = cfg.episode.samples
    link, plant, _ = _loop(cfg, LockStep(timeout=60.0, startup_timeout=60.0), n)
    run, ref = _run(link, cfg), simulate(cfg)
    assert plant.finished and len(run) == n and not link.taken["missed"]
    assert np.array_equal(run.data, ref.data)
    assert score_arrays(run.e1, run.u, cfg.episode.as_array()) == ref.score


def test_a_paced_runs_held_and_centred_samples_are_in_its_run():
    """Paced with commands lost: the plant reports each sample it ran without
    its answer (held, then centred), and the run has the command it ran with
    there (not the controller's late answer) and the states it went through."""
    from has_control.config import with_horizon
    from has_control.core.params import Config
    from has_control.core.run import Col
    from has_control.loop.schedule import Paced
    cfg, n, lost = with_horizon(Config(), 1.5), 300, range(100, 150)
    link, plant, stats = _loop(cfg, Paced(failsafe_samples=10), n, drop=lambda i: i in lost)
    run = _run(link, cfg)
    ran = np.array(plant.log)                       # (sample, y, ẏ, P1, P2, u): what the plant itself ran
    assert len(run) == n == len(ran) and stats.missed >= len(lost)
    assert np.array_equal(run.u, ran[:, 5]) and np.array_equal(run.data[:, Col.y:Col.P2 + 1], ran[:, 1:5])
    assert np.any(run.u[100:110] != 0.0) and np.all(run.u[111:150] == 0.0)      # held, then the valve centred
    missed = np.array([MISSED_LAYOUT.read(m) for m in link.taken["missed"]])
    at = np.rint(missed[:, 0] / cfg.episode.step).astype(int)
    assert set(lost) <= set(at) and set(at[missed[:, 2] == 1.0]) == set(range(110, 150))
    sent = np.array([COMMAND_LAYOUT.read(c)[0] for c in link.taken["command"]])
    assert np.isfinite(run.a1_hat).all() and np.all(sent[111:150] != 0.0)   # answered, but lost on the way


def test_the_loops_reports_without_ros():
    """Lock-step: the rate since the last report, well unless in an outage;
    paced: the loop's figures with the plant's counts, well at a real-time
    factor of 0.99 without fail-safe samples."""
    from types import SimpleNamespace
    from has_control.loop.report import LoopReports
    from has_control.loop.schedule import LoopStats
    now = [10.0]
    process = SimpleNamespace(sample=0, fail_safe=SimpleNamespace(in_outage=False),
                              figures=lambda: {"failsafe_samples": 2.0, "malformed_commands": 0.0, "conflicts": 0.0})
    reports = LoopReports(process, clock=lambda: now[0])
    process.sample, now[0] = 5000, 10.5
    r = reports.lockstep()
    assert r.values["rate_hz"] == 10_000.0 and r.ok and r.message == "rate_hz 10000, failsafe_samples 2"
    process.fail_safe.in_outage, now[0] = True, 11.5
    assert not reports.lockstep().ok
    stats = LoopStats(300_000, samples=3334, sim_ns=3333 * 300_000, wall_ns=1_000_000_000)
    p = reports.paced(stats)
    assert p.ok and p.values["failsafe_events"] == 2.0 and reports.realtime_stats is p.values
    stats.failsafe = 1
    assert not reports.paced(stats).ok


def test_messages_of_another_layout_are_refused_not_misread():
    """A recorder's chunks of joined messages read as the messages; a message
    of another layout (here a command among the states) is refused, naming the topic."""
    from has_control.config import with_horizon
    from has_control.core.params import Config
    from has_control.loop.schedule import LockStep
    from has_control.wire.run_messages import run_of_messages
    cfg = with_horizon(Config(), 1.5)
    link, _, _ = _loop(cfg, LockStep(timeout=60.0, startup_timeout=60.0), 200)
    t, ep, rp = link.taken, cfg.episode, EpisodeArrays.from_config(cfg).reference
    whole = _run(link, cfg)
    chunked = run_of_messages([b"".join(t["state"][:64]), *t["state"][64:]], [b"".join(t["command"])],
                              t["internals"], [], ep.step, ep.step_ns, rp)
    assert len(whole) == 200 and np.array_equal(chunked.data, whole.data)
    with pytest.raises(ValueError, match="state: a message of another layout"):
        run_of_messages(t["state"][:10] + t["command"][:1], t["command"], t["internals"], [], ep.step, ep.step_ns, rp)


def test_a_recorder_without_a_bag_keeps_what_the_run_needs_in_chunks():
    """The stack's recorder without --record: the topics it keeps, every message
    in order, joined into one chunk per hand-over (no object per message); the
    topics it does not record get no tap at all."""
    from has_control.nodes.recorder import BATCH, Recorder
    from has_control.wire.topics import COMMAND, JOINT_STATE, STATE, STATE_LAYOUT
    topics = {STATE: JOINT_STATE, COMMAND: JOINT_STATE}
    rec = Recorder(subscribe=False, topics=topics, keep=topics)
    state, command = rec.sink("/state"), rec.sink("/command")
    assert rec.sink("/clock") is None
    states = [STATE_LAYOUT.encode(range(9), i * 300_000) for i in range(BATCH + 5)]
    commands = [COMMAND_LAYOUT.encode([i * 1e-6], i * 300_000) for i in range(BATCH + 5)]
    for s, c in zip(states, commands):
        state(s)
        command(c)
    assert len(rec.taken(STATE)) == 1 + 5 and b"".join(rec.taken(STATE)) == b"".join(states)
    assert b"".join(rec.taken(COMMAND)) == b"".join(commands) and rec.count(STATE) == rec.count(COMMAND) == BATCH + 5
    assert rec.close() is None and b"".join(rec.taken(STATE)) == b"".join(states)    # no bag; kept after close
