"""Roads (has_control.core.road, the road reference): the summed and the tabulated road are the same road,
their memory is bounded before any table is built, a cached road is found again, and road parameters far
out of range are one line naming the parameter."""
import math
import re

import numpy as np
import pytest
from conftest import one_line

from has_control.cli import main
from has_control.common.errors import ConfigError
from has_control.config import load_config, with_horizon
from has_control.core.episode import evaluate_configs
from has_control.core.params import Config, Episode, N_REFERENCE, REF_TERMS, Reference
from has_control.core.reference import check_road_memory


def _direct_sum(ref, ep):
    """The road as the docstring writes it: one component at a time."""
    from has_control.core.road import road_components
    n = ep.samples
    f, a, phi = road_components(ref, n * ep.step)
    t = np.arange(n) * ep.step
    out = np.zeros((n, 4))
    out[:, 0] = ref.offset
    for fk, ak, pk in zip(f, a, phi):
        w = 2 * math.pi * fk
        s, c = np.sin(w * t + pk), np.cos(w * t + pk)
        out[:, 0] += ak * (s - math.sin(pk))
        out[:, 1:] += np.column_stack([ak * w * c, -ak * w * w * s, -ak * w ** 3 * c])
    return out


@pytest.mark.parametrize("cutoff, road_class", [(2.0, "C"), (50.0, "A"), (1600.0, "E")])
def test_the_road_table_is_the_sum_of_its_components(cutoff, road_class):
    from has_control.core.road import road_table
    ep = Episode(horizon=1.5)
    ref = Reference(kind="road", road_class=road_class, cutoff=cutoff, seed=5, offset=0.02)
    fast, slow = road_table(ref, ep), _direct_sum(ref, ep)
    assert fast[0, 0] == ref.offset
    for d in range(4):
        assert np.max(np.abs(fast[:, d] - slow[:, d])) <= 1e-9 * np.max(np.abs(slow[:, d]))


def test_road_memory_beyond_the_limit_is_refused_before_any_table(tmp_path, capsys, monkeypatch):
    import has_control.core.reference as reference
    from has_control.core.road import MAX_ROAD_BYTES, SUM_TERMS_MAX, road_terms
    built = []
    monkeypatch.setattr(reference, "road_array", lambda *a: built.append(a) or pytest.fail("built a road"))
    assert road_terms(Reference(kind="road", cutoff=50.0), Episode()) > SUM_TERMS_MAX         # tabulated
    count = MAX_ROAD_BYTES // (32 * Episode().samples) + 2                   # 10 s roads just past the limit
    p = tmp_path / "roads.yaml"
    p.write_text("scenarios:\n" + "".join(f"  r{i}: {{reference: {{kind: road, cutoff: 50.0, seed: {i}}}}}\n"
                                          for i in range(count)))
    one_line(capsys, ["robustness", "--gains", 400, 400, 400, "--scenarios", p], p, "MiB of tables",
             "limit of 1,024 MiB")
    with pytest.raises(ConfigError, match="limit of 1,024 MiB"):
        evaluate_configs([[400.0, 400.0, 400.0]], [Config(reference=Reference(kind="road", cutoff=50.0, seed=i))
                                                   for i in range(count)])
    assert built == []


def test_a_road_at_the_shipped_cutoff_costs_about_what_a_sine_does_in_memory():
    """Summed in the kernel, a 10 s road at the shipped 2 Hz cutoff holds a few
    hundred bytes (a table would hold 1 MiB), and 100 of them cost about what
    100 sine scenarios do to evaluate (at most ~10x)."""
    import tracemalloc

    from has_control.core.reference import reference_array
    ep = Episode()
    road = reference_array(Reference(kind="road", seed=1), ep)
    assert road.nbytes <= 10 * reference_array(Reference(), ep).nbytes < 32 * ep.samples
    gains = np.full((4, 3), 400.0)
    sines = [Config(reference=Reference(omega=2.0 + 1e-3 * i)) for i in range(100)]
    roads = [Config(reference=Reference(kind="road", seed=7000 + i)) for i in range(100)]
    evaluate_configs(gains, sines[:1] + roads[:1])                             # compile / load the cache

    def peak(cfgs):
        tracemalloc.start()
        try:
            evaluate_configs(gains, cfgs)
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert peak(roads[1:]) <= 2 * peak(sines[1:])
    many = [(Reference(kind="road", seed=i), ep) for i in range(10_000)]      # the scenario limit: accepted
    check_road_memory(many)


@pytest.mark.parametrize("cutoff", [2.0, 50.0])
def test_road_bytes_are_what_the_road_array_holds(cutoff):
    from has_control.core.road import road_array, road_bytes
    ref, ep = Reference(kind="road", cutoff=cutoff, seed=3), Episode()
    assert road_array(ref, ep).nbytes == 8 * N_REFERENCE + road_bytes(ref, ep)
    assert road_bytes(Reference(), ep) == 0


def test_the_summed_road_is_the_tabulated_one(monkeypatch):
    """The two ways a road is held give the same road: the kernel's sum
    against the inverse FFT's table, forced by lowering the threshold."""
    import has_control.core.road as road
    ep = Episode(horizon=3.0)
    ref = Reference(kind="road", road_class="B", cutoff=8.0, seed=11, offset=-0.01)
    summed = road.road_table(ref, ep)
    assert road.road_array(ref, ep)[REF_TERMS] == road.road_terms(ref, ep) > 0
    monkeypatch.setattr(road, "SUM_TERMS_MAX", 0)
    assert road.road_array(ref, ep)[REF_TERMS] == -1
    table = road.road_table(ref, ep)
    assert summed[0, 0] == table[0, 0] == ref.offset
    for d in range(4):
        assert np.max(np.abs(summed[:, d] - table[:, d])) <= 1e-12 * np.max(np.abs(table[:, d]))


def test_the_road_cache_holds_more_than_32_roads():
    from has_control.core.reference import road_cached
    cfgs = [with_horizon(Config(reference=Reference(kind="road", seed=1000 + i)), 1.2) for i in range(40)]
    evaluate_configs([[400.0, 400.0, 400.0]], cfgs)
    assert all(road_cached(c.reference, c.episode) for c in cfgs)


@pytest.mark.parametrize("road,culprit", [
    ("{kind: road, speed: 1.0e300}", "reference.cutoff = 2.0: no road component"),
    ("{kind: road, cutoff: 1.0e20}", "reference.cutoff = 1e+20: must be below the Nyquist"),
    ("{kind: road, speed: 1.0e308, cutoff: 1.0}", "reference.cutoff = 1.0: no road component"),
])
def test_road_parameters_far_out_of_range_are_one_line(tmp_path, capsys, road, culprit):
    p = tmp_path / "p.yaml"
    p.write_text(f"/**:\n  ros__parameters:\n    reference: {road}\n    simulation: {{horizon: 1000.0}}\n")
    with pytest.raises(ConfigError, match=re.escape(culprit)):
        load_config([p])
    assert main(["simulate", "--config", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and culprit in err, err
