"""Gaussian-process (kriging) toolkit on the unit cube: design, fit, predict, EI, batch proposals.

Used by `optim.kriging` (EGO and its trust-region variant) and by the search step of `optim.mads`.

Surrogate: scikit-learn's `GaussianProcessRegressor` (Rasmussen & Williams 2006, Alg. 2.1) with
an anisotropic Matérn kernel times a constant and a small nugget α, on normalised targets
(y - mean) / std:

    k(u, u') = s² · M_ν( sqrt( Σ_i (u_i - u'_i)² / ℓ_i² ) ),   ν = 5/2 by default,
    μ(u) = k(u)ᵀ (K + αI)⁻¹ y,    σ²(u) = k(u, u) - k(u)ᵀ (K + αI)⁻¹ k(u).

u is dimensionless (a fraction of each parameter's range), so the length scales ℓ_i are too.

Expected improvement over the best value f_min (Jones, Schonlau & Welch 1998, eq. 15):

    EI(u) = (f_min - μ) Φ(z) + σ φ(z),   z = (f_min - μ) / σ.

A batch of q points comes from greedy sequential EI maximisation with fantasised values
(Ginsbourger, Le Riche & Carraro 2010): the kriging believer sets y(u_j) = μ(u_j), the constant
liar (CL-min) sets y(u_j) = min y; the GP is then re-conditioned with its hyperparameters fixed.
EI can be maximised over the whole cube or over a box inside it (a trust region). Alternatively a
batch comes from Thompson sampling (Thompson 1933; batched as in TuRBO, Eriksson et al. 2019):
q joint posterior draws g_j ~ GP on one candidate set, point j = argmin g_j over the candidates
not yet taken. The initial design is a Latin hypercube (McKay, Beckman & Conover 1979).
"""

from __future__ import annotations

import contextlib
import functools
import warnings
from collections.abc import Callable
from typing import Literal

import numpy as np
from scipy.linalg import cholesky, solve_triangular
from scipy.special import erfcx, ndtr
from scipy.stats import qmc
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Kernel, Matern
from threadpoolctl import ThreadpoolController

from optim.protocol import FloatArray

BatchStrategy = Literal["believer", "liar"]
#: A box lower <= u <= upper inside the unit cube, (lower (n,), upper (n,)).
Box = tuple[FloatArray, FloatArray]


@functools.cache
def _blas_controller() -> ThreadpoolController:
    """The process's thread pools, found at the first use (after this module's imports have loaded
    every BLAS it calls) and kept: finding them reads the process's memory map, which cost more
    than a MADS iteration's own work when done at every iteration."""
    return ThreadpoolController()


def single_threaded_blas() -> contextlib.AbstractContextManager:
    """Context limiting BLAS to one thread: the GP matrices (a few hundred rows) factorise
    several times faster without thread start-up, and the cores stay free for the environment."""
    return _blas_controller().limit(limits=1, user_api="blas")


def latin_hypercube(n_points: int, dimension: int, rng: np.random.Generator) -> FloatArray:
    """n_points × dimension Latin hypercube in [0, 1)^dimension (one point per stratum per axis)."""
    return qmc.LatinHypercube(d=dimension, rng=rng).random(n_points)


def expected_improvement(mean: FloatArray, std: FloatArray, f_min: float) -> FloatArray:
    """EI = σ h(z), h(z) = φ(z) + z Φ(z), z = (f_min - μ)/σ; max(f_min - μ, 0) where σ = 0.

    h is evaluated as exp(-z²/2) (1/√(2π) + z erfcx(-z/√2)/2), which stays accurate far in the
    lower tail (z ≈ -30) where φ and Φ underflow separately.
    """
    mean, std = np.asarray(mean, np.float64), np.asarray(std, np.float64)
    gain = f_min - mean
    safe = np.where(std > 0, std, 1.0)
    z = gain / safe
    with np.errstate(over="ignore", invalid="ignore"):
        tail = np.exp(-0.5 * z * z) * (1.0 / np.sqrt(2.0 * np.pi) + 0.5 * z * erfcx(-z / np.sqrt(2.0)))
    h = np.where(z < 0, tail, z * ndtr(z) + np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi))
    return np.where(std > 0, np.maximum(safe * h, 0.0), np.maximum(gain, 0.0))


def matern_kernel(
    dimension: int,
    nu: float = 2.5,
    length_scale: float = 0.3,
    length_scale_bounds: tuple[float, float] = (1e-2, 1e2),
) -> Kernel:
    """s² · Matern(ℓ_1..ℓ_n, ν): one length scale per unit-cube axis, s² in [1e-3, 1e3]."""
    return ConstantKernel(1.0, (1e-3, 1e3)) * Matern(
        length_scale=np.full(dimension, length_scale), length_scale_bounds=length_scale_bounds, nu=nu
    )


def fit_gp(
    u: FloatArray,
    y: FloatArray,
    kernel: Kernel,
    nugget: float = 1e-6,
    n_restarts: int = 1,
    random_state: int = 0,
    optimise: bool = True,
) -> GaussianProcessRegressor:
    """Fit a GP on normalised targets; `optimise=False` keeps the kernel's hyperparameters."""
    gp = GaussianProcessRegressor(
        kernel=kernel,
        alpha=nugget,
        normalize_y=True,
        optimizer="fmin_l_bfgs_b" if optimise else None,
        n_restarts_optimizer=n_restarts if optimise else 0,
        random_state=random_state,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return gp.fit(u, y)


def data_log_likelihood(gp: GaussianProcessRegressor, y: FloatArray, log_targets: bool) -> float:
    """log p(y) of the data y under a GP fitted (`fit_gp`, normalised) to t(y), t = identity or
    log10: the GP's log marginal likelihood of z = (t - mean)/std plus the change of variables,

        log p(y) = LML(z) - N log std(t) + Σ_i log t'(y_i),   t'(y) = 1 or 1/(y ln 10),

    so that the two transforms can be compared (Box & Cox 1964, λ = 1 against λ = 0)."""
    t = np.log10(y) if log_targets else y
    jacobian = -np.sum(np.log(y * np.log(10.0))) if log_targets else 0.0
    std = float(np.std(t)) or 1.0  # as scikit-learn's normalize_y
    return float(gp.log_marginal_likelihood_value_) - len(y) * np.log(std) + jacobian


def fit_gp_or_log(
    u: FloatArray, y: FloatArray, kernels: tuple[Kernel, Kernel], nugget: float, optimise: bool
) -> tuple[GaussianProcessRegressor, FloatArray, tuple[Kernel, Kernel]]:
    """A GP on y and, when every y > 0, one on log10 y; the one under which y is more likely
    (`data_log_likelihood`). Returns it, the targets it was fitted to, and the two fitted
    kernels (identity, log) to warm-start the next call with.

    Objectives that fall by decades (a mismatch far from a fit) are better modelled in log10;
    near a zero-residual fit a sum of squares is close to quadratic and better modelled as it is.
    """
    gp = fit_gp(u, y, kernels[0], nugget, n_restarts=0, optimise=optimise)
    if not np.all(y > 0.0):
        return gp, y, (gp.kernel_, kernels[1])
    t = np.log10(y)
    gp_log = fit_gp(u, t, kernels[1], nugget, n_restarts=0, optimise=optimise)
    fitted = (gp.kernel_, gp_log.kernel_)
    if data_log_likelihood(gp_log, y, True) > data_log_likelihood(gp, y, False):
        return gp_log, t, fitted
    return gp, y, fitted


def predict(gp: GaussianProcessRegressor, u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Posterior mean and standard deviation at the rows of u."""
    mean, std = gp.predict(np.atleast_2d(u), return_std=True)
    return np.asarray(mean, np.float64), np.asarray(std, np.float64)


def minimise_on_cube(
    fun: Callable[[FloatArray], FloatArray],
    dimension: int,
    rng: np.random.Generator,
    n_candidates: int = 512,
    anchors: FloatArray | None = None,
    radii: tuple[float, ...] = (0.1, 0.03, 0.01, 0.003),
    box: Box | None = None,
) -> tuple[FloatArray, float]:
    """Minimise a vectorised fun over the box lower <= u <= upper (default [0, 1]^n) (ours):
    uniform candidates plus anchors, then one round of Gaussian perturbations of the best point
    per radius (a fraction of the box's width per axis). Every round is a single vectorised
    call, which beats gradient polishing through sklearn's per-call overhead; the result is
    rounded onto a mesh or used as a batch proposal, so high accuracy is not needed."""
    lower, upper = (0.0, 1.0) if box is None else box
    width = upper - lower
    cand = lower + width * rng.random((n_candidates, dimension))
    if anchors is not None and len(anchors):
        cand = np.vstack([np.clip(anchors, lower, upper), cand])
    values = fun(cand)
    i = int(np.argmin(values))
    best_u, best_v = cand[i].copy(), float(values[i])
    n_local = max(n_candidates // 4, 8)
    for radius in radii:
        local = np.clip(best_u + radius * width * rng.standard_normal((n_local, dimension)), lower, upper)
        values = fun(local)
        i = int(np.argmin(values))
        if values[i] < best_v:
            best_u, best_v = local[i].copy(), float(values[i])
    return best_u, best_v


def impute_infeasible(y: FloatArray) -> FloatArray:
    """Replace non-finite merits (failed points) by the worst finite one, pushing EI away."""
    finite = np.isfinite(y)
    if not finite.any():
        raise ValueError("no finite value to fit a surrogate to")
    return np.where(finite, y, y[finite].max())


def length_scales(gp: GaussianProcessRegressor, dimension: int) -> FloatArray:
    """The fitted Matérn length scales ℓ_i (0.1 per axis for any other kernel)."""
    scale = getattr(getattr(gp.kernel_, "k2", None), "length_scale", 0.1)
    return np.broadcast_to(np.asarray(scale, np.float64), (dimension,)).copy()


def propose_batch(
    gp: GaussianProcessRegressor,
    u: FloatArray,
    y: FloatArray,
    q: int,
    rng: np.random.Generator,
    strategy: BatchStrategy = "believer",
    n_candidates: int = 512,
    max_sequential: int = 4,
    box: Box | None = None,
) -> FloatArray:
    """q points maximising EI over the box (default [0, 1]^n): the first max_sequential by
    kriging believer / constant liar, f_min = min of y and the fantasies so far.

    Each sequential point costs a GP re-conditioning and an EI maximisation, so for large q
    (ours, after the local penalisation of González et al. 2016, AISTATS) the remaining points
    are picked greedily from one candidate set scored once under the fantasised GP: pick the EI
    maximiser, then multiply every candidate's EI by 1 - exp(-½ Σ_i ((c_i - p_i)/ℓ_i)²), which
    vanishes at the picked point p and fades beyond a length scale. The candidates are uniform in
    the box and Gaussian perturbations (σ_i = ℓ_i / 2) of the four best points, clipped to it.
    """
    if strategy not in ("believer", "liar"):
        raise ValueError(f"unknown batch strategy {strategy!r}; use 'believer' or 'liar'")
    lower, upper = (0.0, 1.0) if box is None else box
    n, lie = u.shape[1], float(np.min(y))
    u_aug, y_aug, out = u.copy(), y.copy(), []
    model = gp
    for _ in range(min(q, max(max_sequential, 1))):
        f_min = float(np.min(y_aug))

        def neg_ei(c: FloatArray, model: GaussianProcessRegressor = model) -> FloatArray:
            return -expected_improvement(*predict(model, c), f_min)

        best = u_aug[np.argsort(y_aug, kind="stable")[:2]]
        point, _ = minimise_on_cube(neg_ei, n, rng, n_candidates, best, box=box)
        out.append(point)
        fantasy = predict(model, point[None])[0][0] if strategy == "believer" else lie
        u_aug = np.vstack([u_aug, point])
        y_aug = np.append(y_aug, fantasy)
        if len(out) < q:
            model = fit_gp(u_aug, y_aug, model.kernel_, gp.alpha, optimise=False)
    if len(out) < q:
        ell = length_scales(model, n)
        best = u_aug[np.argsort(y_aug, kind="stable")[:4]]
        local = best[rng.integers(0, len(best), 4 * n_candidates)]
        local = np.clip(local + 0.5 * ell * rng.standard_normal(local.shape), lower, upper)
        cand = np.vstack([lower + (upper - lower) * rng.random((4 * n_candidates, n)), local])
        score = expected_improvement(*predict(model, cand), float(np.min(y_aug)))
        for _ in range(q - len(out)):
            i = int(np.argmax(score))
            out.append(cand[i].copy())
            score = score * -np.expm1(-0.5 * np.sum(((cand - cand[i]) / ell) ** 2, axis=1))
    return np.array(out).reshape(q, n)


def thompson_batch(
    gp: GaussianProcessRegressor,
    q: int,
    rng: np.random.Generator,
    n_candidates: int = 512,
    box: Box | None = None,
) -> FloatArray:
    """q points by batched Thompson sampling over a Latin hypercube of n_candidates points c in the
    box (default [0, 1]^n), in the GP's normalised target space (same minimisers):

        g = μ + C z,  z ~ N(0, I),   μ = K_c β,   C Cᵀ = K_cc - K_c (K + αI)⁻¹ K_cᵀ + δ I,

    with β = (K + αI)⁻¹ y the fitted weights (sklearn's `alpha_`) and δ the first of 1e-10, 1e-9,
    ..., 1e-4 times the prior variance for which the Cholesky factorisation succeeds (a nearly
    certain posterior is singular in floating point). Point j minimises draw j over the
    candidates not yet taken."""
    dimension = gp.X_train_.shape[1]
    lower, upper = (0.0, 1.0) if box is None else box
    cand = lower + (upper - lower) * latin_hypercube(max(n_candidates, q), dimension, rng)
    k_cross = gp.kernel_(cand, gp.X_train_)
    mean = k_cross @ gp.alpha_
    v = solve_triangular(gp.L_, k_cross.T, lower=True, check_finite=False)
    prior = gp.kernel_(cand)
    scale = float(np.max(np.diag(prior)))
    draws = mean[:, None] + _jittered_cholesky(prior - v.T @ v, scale) @ rng.standard_normal((len(cand), q))
    out = []
    for j in range(q):
        i = int(np.argmin(draws[:, j]))
        out.append(cand[i].copy())
        draws[i, :] = np.inf
    return np.array(out).reshape(q, dimension)


def _jittered_cholesky(cov: FloatArray, scale: float) -> FloatArray:
    """Lower Cholesky factor of cov + δ I, δ = 1e-10 scale, 1e-9 scale, ..., 1e-4 scale."""
    for exponent in range(-10, -3):
        try:
            return cholesky(cov + 10.0**exponent * scale * np.eye(len(cov)), lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            continue
    raise np.linalg.LinAlgError("posterior covariance is not positive definite even with jitter 1e-4")
