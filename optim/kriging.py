"""Kriging optimiser: batch EGO, by default inside a TuRBO trust region, on the unit cube.

The GP surrogate, expected improvement (EI), the q-point EI batch (kriging believer / constant
liar) and batched Thompson sampling are those of `optim.gp`. Both variants start from a
Latin-hypercube design whose first point is x0, and impute failed points with the worst merit.

Global EGO (`KrigingOptions(trust_region=False)`; Jones, Schonlau & Welch 1998): one GP on every
evaluated point, q-point EI maximised over the whole cube [0, 1]^n.

Trust region (default; TuRBO-1 of Eriksson, Pearce, Gardner, Turner & Poloczek 2019, "Scalable
global optimization via local Bayesian optimization", NeurIPS 32, Alg. 1 and §2). A local GP is
fitted to the points evaluated since the last restart, and the batch is chosen only inside the box

    lower_i = clip(c_i - w_i L / 2, 0, 1),      upper_i = clip(c_i + w_i L / 2, 0, 1),
    w_i = (ℓ_i / ℓ̄) / (Π_j ℓ_j / ℓ̄)^(1/n),      ℓ̄ = mean_j ℓ_j,   so Π_i w_i = 1,

around the centre c = the best point since the restart, with the GP's Matérn length scales ℓ_i
(bounded to [0.005, 2] as in TuRBO) stretching the box along the axes the objective varies slowly
on, at an unchanged volume L^n before clipping. L is a fraction of the unit cube. The batch is q
Thompson samples (TuRBO's acquisition; default) or q-point EI. After each batch that holds
proposals (TuRBO §2, "Trust regions")::

    success  ⇔  min_batch y < y* - ε |y*|,   y* = best merit since the restart, ε = 1e-3;
    τ_succ consecutive successes:  L ← min(2 L, L_max), the success count restarts at 0;
    τ_fail consecutive failures:   L ← L / 2,           the failure count restarts at 0;
    L < L_min:  restart: a fresh Latin hypercube of n_initial points, L ← L_init, and the local GP
                forgets every earlier point (the result still keeps the best point of the run).

Constants: TuRBO's L_init = 0.8, L_max = 1.6, τ_succ = 3 and τ_fail = ⌈max(4/q, n/q)⌉ for
batches of q points. Ours, tuned on the inverse problem (6 parameters, 16 per batch, 48 to 480
evaluations; `scripts/bench_kriging.py`): L_min = 1e-4 instead of 0.5⁷ (with 0.5⁷ the region
restarts after about 300 evaluations and the fresh one seldom catches up within 480: the median
best mismatch after 480 was 6 (normal) and 17 (heart failure) times worse), n_initial = n + 2
instead of 2n (more rounds in the region early), and Thompson sampling rather than EI (EI in the
region moved less in the first 48 evaluations). A design round that leaves room in the batch is
filled with proposals once the current trust region holds two or more points.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from optim.gp import (
    BatchStrategy,
    Box,
    fit_gp,
    impute_infeasible,
    latin_hypercube,
    length_scales,
    matern_kernel,
    propose_batch,
    single_threaded_blas,
    thompson_batch,
)
from optim.protocol import BatchEvaluation, Bounds, FloatArray, Optimizer

Acquisition = Literal["ei", "thompson"]
#: Bounds of the Matérn length scales of the trust region's GP (TuRBO's, unit-cube fractions).
TRUST_REGION_LENGTH_SCALE_BOUNDS = (5e-3, 2.0)


@dataclasses.dataclass(frozen=True)
class KrigingOptions:
    """Kriging settings. n_initial: Latin-hypercube size (default max(batch_size, 4n) for global
    EGO, n + 2 in a trust region). strategy: q-point EI batches by kriging "believer" or constant
    "liar". n_candidates: EI search candidates, or the Thompson-sampling candidate set.

    trust_region: TuRBO-1 (module docstring) instead of global EGO. length_init, length_min,
    length_max: L_init, L_min, L_max (fractions of the unit cube). success_tolerance: τ_succ;
    failure_tolerance: τ_fail (None: ⌈max(4/q, n/q)⌉). min_improvement: ε of the success test.
    acquisition (trust region only; global EGO is EI): "thompson" (batched Thompson sampling,
    `optim.gp.thompson_batch`) or "ei" (q-point EI per `strategy`).
    """

    n_initial: int | None = None
    strategy: BatchStrategy = "believer"
    nu: float = 2.5
    nugget: float = 1e-6
    n_restarts: int = 1
    n_candidates: int = 512
    trust_region: bool = True
    length_init: float = 0.8
    length_min: float = 1e-4
    length_max: float = 1.6
    success_tolerance: int = 3
    failure_tolerance: int | None = None
    min_improvement: float = 1e-3
    acquisition: Acquisition = "thompson"


@dataclasses.dataclass(frozen=True)
class TrustRegion:
    """TuRBO trust-region state: base side `length` L (fraction of the unit cube) and the counts
    of consecutive successful and failed batches (module docstring)."""

    length: float
    successes: int = 0
    failures: int = 0

    def after_batch(
        self, improved: bool, success_tolerance: int, failure_tolerance: int, length_max: float
    ) -> TrustRegion:
        """The state after one batch: count it, then double L after τ_succ successes in a row
        (at most L_max) or halve it after τ_fail failures in a row."""
        successes, failures = (self.successes + 1, 0) if improved else (0, self.failures + 1)
        length = self.length
        if successes == success_tolerance:
            length, successes = min(2.0 * length, length_max), 0
        elif failures == failure_tolerance:
            length, failures = 0.5 * length, 0
        return TrustRegion(length, successes, failures)

    def box(self, centre: FloatArray, scales: FloatArray) -> Box:
        """clip(c ∓ w L/2, 0, 1) with w_i = (ℓ_i/ℓ̄) / (Π_j ℓ_j/ℓ̄)^(1/n), so Π_i w_i = 1."""
        weights = scales / np.mean(scales)
        weights = weights / np.prod(weights ** (1.0 / len(weights)))
        half = 0.5 * self.length * weights
        return np.clip(centre - half, 0.0, 1.0), np.clip(centre + half, 0.0, 1.0)


class Kriging(Optimizer):
    """Batch EGO, in a TuRBO trust region by default (module docstring): a Latin-hypercube
    design, then q = batch_size proposals per round (Thompson samples or q-point EI).

    The first design point is x0 (box centre by default). Failed points enter the GP with the
    worst observed merit. If the GP cannot be fitted, the round falls back to uniform points
    (in the current trust region, or the whole cube).
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
        o = self.options = options or KrigingOptions()
        if o.strategy not in ("believer", "liar"):
            raise ValueError(f"unknown batch strategy {o.strategy!r}")
        if o.acquisition not in ("ei", "thompson"):
            raise ValueError(f"unknown acquisition {o.acquisition!r}; use 'ei' or 'thompson'")
        n = self.dimension
        if o.trust_region:
            if not 0.0 < o.length_min < o.length_init <= o.length_max:
                raise ValueError(
                    "trust region lengths must satisfy 0 < length_min < length_init <= length_max, "
                    f"got {o.length_min}, {o.length_init}, {o.length_max}"
                )
            if o.success_tolerance < 1 or (o.failure_tolerance is not None and o.failure_tolerance < 1):
                raise ValueError(
                    f"success_tolerance = {o.success_tolerance} and failure_tolerance = "
                    f"{o.failure_tolerance} must be >= 1"
                )
            if not o.min_improvement >= 0.0:
                raise ValueError(f"min_improvement must be >= 0, got {o.min_improvement}")
        default_initial = n + 2 if o.trust_region else max(self.batch_size, 4 * n)
        self.n_initial = o.n_initial or default_initial
        if self.n_initial < 2:
            raise ValueError(f"n_initial must be >= 2, got {self.n_initial}")
        design = latin_hypercube(self.n_initial - 1, n, self.rng)
        self._queue = np.vstack([self.u0, design])
        self._u = np.empty((0, n))
        self._y = np.empty(0)
        self._fallbacks = 0
        if o.trust_region:
            self._initial_kernel = matern_kernel(n, o.nu, length_scale_bounds=TRUST_REGION_LENGTH_SCALE_BOUNDS)
        else:
            self._initial_kernel = matern_kernel(n, o.nu)
        self._kernel = self._initial_kernel
        self.failure_tolerance = o.failure_tolerance or int(np.ceil(max(4.0, n) / self.batch_size))
        self._region = TrustRegion(o.length_init) if o.trust_region else None
        self._region_start = 0  # index of the first evaluation of the current trust region
        self._restarts = 0
        self._box: Box | None = None
        self._n_proposed = 0

    def options_fingerprint(self) -> tuple[Any, ...]:
        return dataclasses.astuple(self.options)

    @property
    def trust_region(self) -> TrustRegion | None:
        """The current trust-region state (None for global EGO)."""
        return self._region

    @property
    def restarts(self) -> int:
        """Trust-region restarts so far (L fell below L_min)."""
        return self._restarts

    @property
    def proposal_box(self) -> Box | None:
        """(lower, upper) unit-cube box of the last round's proposals; None if it had none or
        the run is global EGO. Proposals are the last `proposals_in_round` points of the round."""
        return self._box

    @property
    def proposals_in_round(self) -> int:
        """How many points of the last round were proposals (the others are design points)."""
        return self._n_proposed

    def _ask_unit(self, max_points: int) -> FloatArray:
        if not self.options.trust_region:
            return self._ask_global(max_points)
        design, self._queue = self._queue[:max_points], self._queue[max_points:]
        self._box, self._n_proposed = None, 0
        room = max_points - len(design)
        if room == 0 or len(self._y) - self._region_start < 2:
            return design
        proposals = self._propose_in_region(room)
        self._n_proposed = len(proposals)
        return np.vstack([design, proposals])

    def _ask_global(self, max_points: int) -> FloatArray:
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

    def _propose_in_region(self, q: int) -> FloatArray:
        """q points in the trust region around the best point since the restart, chosen by the
        acquisition on a GP fitted to the points since the restart; uniform points in the region
        (sides L) if the GP cannot be fitted or sampled, or in the cube if no point succeeded."""
        o, n = self.options, self.dimension
        assert self._region is not None
        u, y = self._u[self._region_start :], self._y[self._region_start :]
        if not np.isfinite(y).any():
            self._fallbacks += 1
            self._box = (np.zeros(n), np.ones(n))
            return self.rng.random((q, n))
        y = impute_infeasible(y)
        centre = u[int(np.argmin(y))]
        with single_threaded_blas():
            try:
                gp = fit_gp(u, y, self._kernel, o.nugget, o.n_restarts, self._draw_seed())
                self._box = self._region.box(centre, length_scales(gp, n))
                if o.acquisition == "thompson":
                    points = thompson_batch(gp, q, self.rng, o.n_candidates, box=self._box)
                else:
                    points = propose_batch(gp, u, y, q, self.rng, o.strategy, o.n_candidates, box=self._box)
            except (ValueError, np.linalg.LinAlgError):
                self._fallbacks += 1
                lower, upper = self._box = self._region.box(centre, np.ones(n))
                return lower + (upper - lower) * self.rng.random((q, n))
        self._kernel = gp.kernel_
        return points

    def _draw_seed(self) -> int:
        return int(self.rng.integers(0, 2**31 - 1))

    def _tell_unit(self, u: FloatArray, merit: FloatArray, evaluation: BatchEvaluation) -> None:
        region_y = self._y[self._region_start :]
        best = float(np.min(region_y)) if len(region_y) else np.inf
        self._u = np.vstack([self._u, u])
        self._y = np.append(self._y, merit)
        if self._region is None or self._n_proposed == 0:
            return
        o = self.options
        threshold = best - o.min_improvement * abs(best) if np.isfinite(best) else np.inf
        improved = bool(np.min(merit) < threshold)
        self._region = self._region.after_batch(
            improved, o.success_tolerance, self.failure_tolerance, o.length_max
        )
        if self._region.length < o.length_min:
            self._restart()

    def _restart(self) -> None:
        """A fresh trust region: new Latin-hypercube design, L = L_init, GP history cleared."""
        o = self.options
        self._queue = np.vstack([self._queue, latin_hypercube(self.n_initial, self.dimension, self.rng)])
        self._region = TrustRegion(o.length_init)
        self._region_start = len(self._y)
        self._kernel = self._initial_kernel
        self._restarts += 1

    def _stop(self) -> dict[str, float]:
        return {}

    def _info(self) -> dict[str, float]:
        info = {"gp_points": float(len(self._y) - self._region_start), "fallback_rounds": float(self._fallbacks)}
        if self._region is not None:
            info |= {
                "trust_region_length": self._region.length,
                "trust_region_successes": float(self._region.successes),
                "trust_region_failures": float(self._region.failures),
                "trust_region_restarts": float(self._restarts),
            }
        return info
