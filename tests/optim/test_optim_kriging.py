"""GP surrogate against scikit-learn and the closed-form kriging equations; EI; LHS; EGO."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, stats
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern

import optim
from optim import Bounds, KrigingOptions
from optim.kriging import (
    expected_improvement,
    fit_gp,
    latin_hypercube,
    matern_kernel,
    predict,
    propose_batch,
)


def branin_unit(u: np.ndarray) -> np.ndarray:
    x1, x2 = 15.0 * u[:, 0] - 5.0, 15.0 * u[:, 1]
    b, c, t = 5.1 / (4 * np.pi**2), 5 / np.pi, 1 / (8 * np.pi)
    return (x2 - b * x1**2 + c * x1 - 6) ** 2 + 10 * (1 - t) * np.cos(x1) + 10


def training_set(m: int = 25, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    u = latin_hypercube(m, 2, np.random.default_rng(seed))
    return u, branin_unit(u)


def test_predictions_equal_scikit_learn() -> None:
    u, y = training_set()
    test = np.random.default_rng(1).random((50, 2))
    ours = fit_gp(u, y, matern_kernel(2), nugget=1e-6, n_restarts=2, random_state=5)
    theirs = GaussianProcessRegressor(
        kernel=ConstantKernel(1.0, (1e-3, 1e3)) * Matern([0.3, 0.3], (1e-2, 1e2), nu=2.5),
        alpha=1e-6, normalize_y=True, n_restarts_optimizer=2, random_state=5,
    ).fit(u, y)
    mean, std = predict(ours, test)
    ref_mean, ref_std = theirs.predict(test, return_std=True)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(std, ref_std, rtol=1e-10, atol=1e-10)
    assert len(set(np.round(np.exp(ours.kernel_.theta[1:]), 6))) == 2  # anisotropic length scales


def test_predictions_follow_the_kriging_equations() -> None:
    """μ = m + s k*ᵀ(K + αI)⁻¹ (y - m)/s,  σ² = s² (k** - k*ᵀ(K + αI)⁻¹ k*) with fixed θ."""
    u, y = training_set(15)
    ell, var, alpha = np.array([0.2, 0.5]), 1.7, 1e-6
    kernel = ConstantKernel(var, "fixed") * Matern(ell, "fixed", nu=2.5)
    gp = fit_gp(u, y, kernel, nugget=alpha, optimise=False)
    test = np.random.default_rng(2).random((20, 2))

    def matern52(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        r = np.sqrt(np.sum(((a[:, None, :] - b[None, :, :]) / ell) ** 2, axis=2)) * np.sqrt(5.0)
        return var * (1.0 + r + r * r / 3.0) * np.exp(-r)

    m, s = y.mean(), y.std()
    k = matern52(u, u) + alpha * np.eye(len(u))
    ks = matern52(test, u)
    mean = m + s * ks @ np.linalg.solve(k, (y - m) / s)
    var_post = var - np.einsum("ij,ji->i", ks, np.linalg.solve(k, ks.T))
    got_mean, got_std = predict(gp, test)
    np.testing.assert_allclose(got_mean, mean, rtol=1e-8)
    np.testing.assert_allclose(got_std, s * np.sqrt(var_post), rtol=1e-6)


@pytest.mark.parametrize(("mu", "sigma", "f_min"), [(1.0, 0.5, 0.8), (0.0, 2.0, 1.0), (0.5, 0.1, 0.0)])
def test_expected_improvement_is_the_integral(mu: float, sigma: float, f_min: float) -> None:
    """EI = ∫ max(f_min - y, 0) N(y; μ, σ²) dy."""
    ref, _ = integrate.quad(lambda y: (f_min - y) * stats.norm.pdf(y, mu, sigma), -np.inf, f_min, epsabs=0)
    got = expected_improvement(np.array([mu]), np.array([sigma]), f_min)[0]
    assert got == pytest.approx(ref, rel=1e-7)
    assert expected_improvement(np.array([mu]), np.array([0.0]), f_min)[0] == max(f_min - mu, 0.0)


def test_expected_improvement_far_in_the_tail() -> None:
    """z -> -inf: EI = σ φ(z)/z² (1 - 3/z² + 15/z⁴ - 105/z⁶ + ...), relative error ~ 945/z⁸."""
    z = np.array([-20.0, -25.0, -30.0])
    ref = 0.1 * stats.norm.pdf(z) / z**2 * (1 - 3 / z**2 + 15 / z**4 - 105 / z**6)
    got = expected_improvement(-0.1 * z, np.full(3, 0.1), 0.0)
    np.testing.assert_allclose(got, ref, rtol=1e-7)
    assert np.all(got > 0)


def test_latin_hypercube_has_one_point_per_stratum() -> None:
    u = latin_hypercube(17, 4, np.random.default_rng(0))
    for axis in range(4):
        np.testing.assert_array_equal(np.sort(np.floor(u[:, axis] * 17)), np.arange(17))


@pytest.mark.parametrize(("strategy", "max_sequential"), [("believer", 4), ("liar", 4), ("believer", 2)])
def test_batch_proposals_are_distinct_and_promising(strategy: str, max_sequential: int) -> None:
    u, y = training_set(20)
    gp = fit_gp(u, y, matern_kernel(2), random_state=0)
    rng = np.random.default_rng(0)
    batch = propose_batch(gp, u, y, 6, rng, strategy, 256, max_sequential)  # type: ignore[arg-type]
    assert batch.shape == (6, 2) and np.all((batch >= 0) & (batch <= 1))
    gaps = np.linalg.norm(batch[:, None] - batch[None], axis=2) + np.eye(6)
    assert gaps.min() > 1e-3
    ei = expected_improvement(*predict(gp, batch[:1]), float(y.min()))
    random_ei = expected_improvement(*predict(gp, np.random.default_rng(3).random((500, 2))), float(y.min()))
    assert ei[0] >= random_ei.max()
    with pytest.raises(ValueError, match="unknown batch strategy"):
        propose_batch(gp, u, y, 2, rng, "pessimist")  # type: ignore[arg-type]


def test_ego_finds_a_branin_minimum() -> None:
    bounds = Bounds(np.array([-5.0, 0.0]), np.array([10.0, 15.0]))

    def branin(x: np.ndarray) -> np.ndarray:
        return branin_unit(bounds.to_unit(x))

    opt = optim.Kriging(bounds, 4, seed=0, options=KrigingOptions(n_initial=8, n_restarts=1, n_candidates=256))
    res = optim.run(opt, branin, 40)
    assert res.f_best < 0.397887 + 0.05  # global minimum 0.397887
    assert res.evaluations == 40 and res.batches == 10
