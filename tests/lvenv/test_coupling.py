"""LO maps: the passive law's slope, the passive equilibrium, and the delayed calcium input."""

import numpy as np
import pytest

from lvenv import cell, coupling, presets
from lvenv.params import CellParams, LOParams


def test_delayed_calcium_is_the_cell_transient_shifted():
    p, t = CellParams(), np.linspace(0.0, 1.0, 2001)
    np.testing.assert_allclose(coupling.calcium(t, LOParams(), p), cell.calcium(t, p), rtol=1e-14)
    delayed = np.asarray(coupling.calcium(t, LOParams(delay=0.05), p))
    assert np.all(delayed[t < 0.05] == p.Cdia)
    np.testing.assert_allclose(delayed[t >= 0.05], cell.calcium(t[t >= 0.05] - 0.05, p), rtol=1e-14)
    rate = np.asarray(coupling.calcium_rate(t, LOParams(delay=0.05), p))
    inner = (t > 0.06) & (t < 0.99)
    np.testing.assert_allclose(rate[inner], np.gradient(delayed, t)[inner], rtol=2e-3, atol=1e-2)


def test_passive_slope_is_the_derivative_of_the_passive_law():
    lo, v0 = presets.N_LO, 35.8
    v = np.linspace(20.0, 70.0, 101)
    h = 1e-6
    fd = (np.asarray(coupling.passive_pressure(v + h, v0, lo)) - np.asarray(coupling.passive_pressure(v - h, v0, lo))) / (2 * h)
    away = np.abs(v - v0) > 1e-3
    np.testing.assert_allclose(np.asarray(coupling.passive_pressure_slope(v, v0, lo))[away], fd[away], rtol=1e-6)


@pytest.mark.parametrize("p", [-0.7, 0.0, 0.33, 1.5, 4.0])
def test_passive_volume_inverts_the_passive_law(p):
    lo, v0 = presets.N_LO, 35.8
    v = coupling.passive_volume(np.array([p]), v0, lo)[0]
    assert float(coupling.passive_pressure(v, v0, lo)) == pytest.approx(p, abs=1e-12)
