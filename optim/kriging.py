"""Kriging (Gaussian-process) surrogate and batch EGO on the unit cube.

Surrogate: scikit-learn's `GaussianProcessRegressor` (Rasmussen & Williams 2006, Alg. 2.1) with
an anisotropic Matérn kernel times a constant and a small nugget, on normalised targets
(y - mean) / std:

    k(u, u') = s² · M_ν( sqrt( Σ_i (u_i - u'_i)² / ℓ_i² ) ),   ν = 5/2 by default,
    μ(u) = k(u)ᵀ (K + αI)⁻¹ y,    σ²(u) = k(u, u) - k(u)ᵀ (K + αI)⁻¹ k(u).

Expected improvement over the best value f_min (Jones, Schonlau & Welch 1998, eq. 15):

    EI(u) = (f_min - μ) Φ(z) + σ φ(z),   z = (f_min - μ) / σ.

A batch of q points comes from greedy sequential EI maximisation with fantasised values
(Ginsbourger, Le Riche & Carraro 2010): the kriging believer sets y(u_j) = μ(u_j), the constant
liar (CL-min) sets y(u_j) = min y; the GP is then re-conditioned with its hyperparameters fixed.
The initial design is a Latin hypercube (McKay, Beckman & Conover 1979).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import erfcx, ndtr
from scipy.stats import qmc
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Kernel, Matern
from threadpoolctl import threadpool_limits

from optim.protocol import BatchEvaluation, Bounds, FloatArray, Optimizer

BatchStrategy = Literal["believer", "liar"]


def single_threaded_blas() -> threadpool_limits:
    """Context limiting BLAS to one thread: the GP matrices (a few hundred rows) factorise
    several times faster without thread start-up, and the cores stay free for the environment."""
    return threadpool_limits(limits=1, user_api="blas")


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


def matern_kernel(dimension: int, nu: float = 2.5, length_scale: float = 0.3) -> Kernel:
    """s² · Matern(ℓ_1..ℓ_n, ν): one length scale per unit-cube axis."""
    return ConstantKernel(1.0, (1e-3, 1e3)) * Matern(
        length_scale=np.full(dimension, length_scale), length_scale_bounds=(1e-2, 1e2), nu=nu
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
) -> tuple[FloatArray, float]:
    """Minimise a vectorised fun over [0, 1]^n (ours): uniform candidates plus anchors, then one
    round of Gaussian perturbations of the best point per radius. Every round is a single
    vectorised call, which beats gradient polishing through sklearn's per-call overhead; the
    result is rounded onto a mesh or used as a batch proposal, so high accuracy is not needed."""
    cand = rng.random((n_candidates, dimension))
    if anchors is not None and len(anchors):
        cand = np.vstack([np.clip(anchors, 0.0, 1.0), cand])
    values = fun(cand)
    i = int(np.argmin(values))
    best_u, best_v = cand[i].copy(), float(values[i])
    n_local = max(n_candidates // 4, 8)
    for radius in radii:
        local = np.clip(best_u + radius * rng.standard_normal((n_local, dimension)), 0.0, 1.0)
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
) -> FloatArray:
    """q points maximising EI: the first max_sequential by kriging believer / constant liar.

    Each sequential point costs a GP re-conditioning and an EI maximisation, so for large q
    (ours, after the local penalisation of González et al. 2016, AISTATS) the remaining points
    are picked greedily from one candidate set scored once under the fantasised GP: pick the EI
    maximiser, then multiply every candidate's EI by 1 - exp(-½ Σ_i ((c_i - p_i)/ℓ_i)²), which
    vanishes at the picked point p and fades beyond a length scale.
    """
    if strategy not in ("believer", "liar"):
        raise ValueError(f"unknown batch strategy {strategy!r}; use 'believer' or 'liar'")
    n, lie = u.shape[1], float(np.min(y))
    u_aug, y_aug, out = u.copy(), y.copy(), []
    model = gp
    for _ in range(min(q, max(max_sequential, 1))):
        f_min = float(np.min(y_aug))

        def neg_ei(c: FloatArray, model: GaussianProcessRegressor = model) -> FloatArray:
            return -expected_improvement(*predict(model, c), f_min)

        best = u_aug[np.argsort(y_aug, kind="stable")[:2]]
        point, _ = minimise_on_cube(neg_ei, n, rng, n_candidates, best)
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
        local = np.clip(local + 0.5 * ell * rng.standard_normal(local.shape), 0.0, 1.0)
        cand = np.vstack([rng.random((4 * n_candidates, n)), local])
        score = expected_improvement(*predict(model, cand), float(np.min(y_aug)))
        for _ in range(q - len(out)):
            i = int(np.argmax(score))
            out.append(cand[i].copy())
            score = score * -np.expm1(-0.5 * np.sum(((cand - cand[i]) / ell) ** 2, axis=1))
    return np.array(out).reshape(q, n)


@dataclasses.dataclass(frozen=True)
class KrigingOptions:
    """EGO settings. n_initial: Latin-hypercube size (default max(batch_size, 4n))."""

    n_initial: int | None = None
    strategy: BatchStrategy = "believer"
    nu: float = 2.5
    nugget: float = 1e-6
    n_restarts: int = 1
    n_candidates: int = 512


class Kriging(Optimizer):
    """Batch EGO: Latin-hypercube design, then q = batch_size EI proposals per round.

    The first design point is x0 (box centre by default). Failed points enter the GP with the
    worst observed merit. If the GP cannot be fitted, the round falls back to uniform points.
    """

    def __init__(
        self,
        bounds: Bounds,
        batch_size: int,
        seed: int = 0,
        options: KrigingOptions | None = None,
        penalty: float = 1.0,
        x0: ArrayLike | None = None,
    ) -> None:
        super().__init__(bounds, batch_size, seed, penalty, x0)
        self.options = options or KrigingOptions()
        if self.options.strategy not in ("believer", "liar"):
            raise ValueError(f"unknown batch strategy {self.options.strategy!r}")
        n = self.dimension
        n_init = self.options.n_initial or max(self.batch_size, 4 * n)
        if n_init < 2:
            raise ValueError(f"n_initial must be >= 2, got {n_init}")
        design = latin_hypercube(n_init - 1, n, self.rng)
        self._queue = np.vstack([self.u0, design])
        self._u = np.empty((0, n))
        self._y = np.empty(0)
        self._kernel = matern_kernel(n, self.options.nu)
        self._fallbacks = 0

    def options_fingerprint(self) -> tuple[Any, ...]:
        return dataclasses.astuple(self.options)

    def _ask_unit(self, max_points: int) -> FloatArray:
        if len(self._queue):
            out, self._queue = self._queue[:max_points], self._queue[max_points:]
            return out
        o = self.options
        with single_threaded_blas():
            try:
                y = impute_infeasible(self._y)
                gp = fit_gp(self._u, y, self._kernel, o.nugget, o.n_restarts, self._draw_seed())
            except (ValueError, np.linalg.LinAlgError):
                self._fallbacks += 1
                return self.rng.random((max_points, self.dimension))
            self._kernel = gp.kernel_
            return propose_batch(gp, self._u, y, max_points, self.rng, o.strategy, o.n_candidates)

    def _draw_seed(self) -> int:
        return int(self.rng.integers(0, 2**31 - 1))

    def _tell_unit(self, u: FloatArray, merit: FloatArray, evaluation: BatchEvaluation) -> None:
        self._u = np.vstack([self._u, u])
        self._y = np.append(self._y, merit)

    def _stop(self) -> dict[str, float]:
        return {}

    def _info(self) -> dict[str, float]:
        return {"gp_points": float(len(self._y)), "fallback_rounds": float(self._fallbacks)}
