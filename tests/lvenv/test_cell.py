import jax.numpy as jnp
import numpy as np
import pytest
from scipy import optimize

from lvenv import cell
from lvenv.params import CellParams


def hill(ca, tmax, ca50, n):
    return tmax / (1.0 + (ca50 / ca) ** n)


def fit_hill(p, lam):
    ca = np.logspace(-1.5, 1.5, 200)
    ta = np.asarray(cell.steady_state_tension(jnp.asarray(ca), lam, p))
    (tmax, ca50, n), _ = optimize.curve_fit(hill, ca, ta, p0=(ta.max(), 1.0, 3.0), maxfev=20000)
    return ca, ta, tmax, ca50, n


def test_force_calcium_curve_is_sigmoidal():
    ca, ta, tmax, ca50, n = fit_hill(CellParams(), 1.0)
    assert np.all(np.diff(ta) > 0), "Ta must rise monotonically with [Ca]"
    assert ta[0] < 0.02 * ta[-1] and ta[-1] > 0.97 * tmax, "flat at both ends"
    log_slope = np.gradient(np.log(ta), np.log(ca))
    assert log_slope.max() > 1.5, "cooperative (Hill slope > 1)"
    assert np.max(np.abs(hill(ca, tmax, ca50, n) - ta)) < 0.1 * tmax


def test_length_dependent_activation_lowers_ca50():
    p = CellParams()
    ca50s = [fit_hill(p, lam)[3] for lam in (0.9, 1.0, 1.1)]
    assert ca50s[0] > ca50s[1] > ca50s[2]
    tmaxs = [fit_hill(p, lam)[2] for lam in (0.9, 1.0, 1.1)]
    assert tmaxs[0] < tmaxs[1] < tmaxs[2], "h(λ) raises maximal tension with stretch"


def test_na_controls_steepness():
    hill_n = [fit_hill(CellParams(nA=na), 1.0)[4] for na in (1.0, 2.0, 5.0, 8.0)]
    assert all(a < b for a, b in zip(hill_n, hill_n[1:])), hill_n
    assert hill_n[0] == pytest.approx(2.0, abs=0.1), "nA = 1 leaves only troponin's nTRPN = 2"


def test_rest_state_is_a_fixed_point_and_ta_scales_with_sa():
    p = CellParams()
    lam = jnp.asarray([0.95, 1.0, 1.1])
    y = cell.rest_state(lam, p)
    dy = cell.derivatives(y, p.Cdia, lam, 0.0, p)
    np.testing.assert_allclose(np.asarray(dy), 0.0, atol=1e-9)
    y_act = jnp.asarray([0.6, 0.1, 0.2, 0.2, 0.1, -0.05])[:, None] * jnp.ones((1, 3))
    t1 = cell.active_tension(y_act, lam, p)
    t2 = cell.active_tension(y_act, lam, CellParams(Sa=2.0))
    np.testing.assert_allclose(np.asarray(t2), 2 * np.asarray(t1), rtol=1e-12)


def test_calcium_transient_peaks_at_cmax_and_starts_at_cdia():
    p = CellParams(tau1=0.03, tau2=0.2, Cdia=0.1, Cmax=1.5)
    t = jnp.linspace(0.0, 1.0, 100001)
    ca = np.asarray(cell.calcium(t, p))
    assert ca[0] == pytest.approx(0.1, abs=1e-12)
    assert ca.max() == pytest.approx(1.5, rel=1e-8)


def test_n0_sets_zero_force_stretch():
    for n0 in (0.5, 0.7174, 0.9):
        p = CellParams(n0=n0)
        y = jnp.asarray([0.6, 0.1, 0.2, 0.2, 0.0, 0.0])
        assert float(cell.active_tension(y, n0, p)) == pytest.approx(0.0, abs=1e-9)
        assert float(cell.active_tension(y, n0 + 0.05, p)) > 0.0
    assert float(cell.beta0(0.7174)) == pytest.approx(2.3, rel=1e-3)
