"""Reference trajectories: each derivative is the derivative of the one before."""
import numpy as np
import pytest

from has_control.core.params import Reference
from has_control.core.reference import reference


@pytest.mark.parametrize("ref", [
    Reference(),
    Reference(kind="step", amplitude=0.05, t0=0.2, rise=0.3),
    Reference(kind="chirp", amplitude=0.02, f0=0.5, f1=3.0, sweep=2.0),
])
def test_derivatives_are_consistent(ref):
    rp = ref.as_array()
    t = np.linspace(0.05, 1.5, 400)
    h = 1e-6
    for order in range(3):
        plus = np.array([reference(rp, x + h)[order] for x in t])
        minus = np.array([reference(rp, x - h)[order] for x in t])
        exact = np.array([reference(rp, x)[order + 1] for x in t])
        scale = max(np.max(np.abs(exact)), 1e-12)
        assert np.max(np.abs((plus - minus) / (2 * h) - exact)) < 1e-4 * scale


def test_step_reaches_its_amplitude_smoothly():
    rp = Reference(kind="step", amplitude=0.05, t0=0.1, rise=0.2).as_array()
    assert reference(rp, 0.0) == (0.0, 0.0, 0.0, 0.0)
    assert reference(rp, 0.5) == (0.05, 0.0, 0.0, 0.0)
    assert reference(rp, 0.2)[0] == pytest.approx(0.025)
