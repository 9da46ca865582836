"""OrthoMADS with a kriging search step, on the unit cube, the poll in opportunistic chunks.

References
----------
* Audet C, Dennis JE Jr (2006) Mesh adaptive direct search algorithms for constrained
  optimization. SIAM J Optim 17(1):188-217. (MADS, extreme barrier, search/poll.)
* Abramson MA, Audet C, Dennis JE Jr, Le Digabel S (2009) OrthoMADS: a deterministic MADS
  instance with orthogonal directions. SIAM J Optim 20(2):948-966. (Mesh rules, Halton and
  Householder directions, below.)

Iteration k, mesh index ℓ_k (ℓ_0 = 0), initial poll size s0 (fraction of the box), mesh scale c
(>= s0, box widths):

    poll size  δp_k = s0 · 2^(-ℓ_k),      mesh size  δm_k = min(s0, δp_k² / c),
    success (a trial point improves the incumbent):  ℓ_{k+1} = ℓ_k - 1   (mesh coarsens)
    failure (the whole poll set is worse):           ℓ_{k+1} = ℓ_k + 1   (mesh refines)

so δm_k <= δp_k and δm_k → 0 faster than δp_k (the key MADS property), and the mesh changes by a
factor 4 per level. c = s0 is OrthoMADS's rule δm = s0 · min(1, 4^(-ℓ)). (ours) The default
c = 1 makes the mesh finer relative to the frame (δp/δm = c/δp instead of s0/δp), as NOMAD 4's
granular mesh does: with OrthoMADS's rule the first few levels can only poll along (nearly)
coordinate directions, which on our inverse problems, whose minima lie in oblique valleys
(τ2 against Sa), cost 1.4× (N) and 1.7× (HF) the evaluations to 3 % (`scripts/bench_optim.py`).
ℓ is kept >= ℓ_min so that δp <= 1, the width of the box.

Poll directions (OrthoMADS §3): the Halton point u_t in [0, 1]^n (bases = first n primes) gives
the adjusted direction q = round(α (2u_t - e)/||2u_t - e||), with α the largest value such that
||q|| <= sqrt(δp/δm) (= 2^(abs(ℓ)/2) under OrthoMADS's rule); the Householder matrix

    H = ||q||² I - 2 q qᵀ        (integer, columns orthogonal, each of norm ||q||²)

gives the 2n poll directions D = [H, -H] and poll points x_k + δm_k d, d in D, which lie on the
mesh x_k + δm_k Zⁿ at distance ≈ δp_k. The Halton index is t_k = ℓ_k + p_n when ℓ_k exceeds
every earlier index, else 1 + max earlier t.

Search step (before each poll): a GP (`optim.gp`) fitted to the evaluated points nearest the
incumbent proposes the minimiser of its mean (and, if n_search > 1, expected-improvement points,
kriging believer); each is rounded onto the mesh, x_k + δm_k · round((y - x_k)/δm_k), inside the
box. (ours) When every merit is positive the GP models whichever of the merits and their log10
makes the data more likely (`optim.gp.fit_gp_or_log`): the log while a mismatch falls by
decades, the merits themselves near a zero-residual fit, where a sum of squares is nearly
quadratic. On the built-in patients this lowers the median final mismatch at 480 evaluations
1.7–3× against a GP on the log alone (`scripts/bench_optim.py`, 5 seeds).

Batching: the iteration's trial list is [search points, poll points] (poll points ordered by the
surrogate mean or by the last successful direction) and is evaluated in chunks of batch_size. In
opportunistic mode the iteration ends after the first chunk that improves the incumbent. (ours)
By default the search points are a chunk of their own and the poll goes in chunks of at most
``poll_chunk`` = 4 points, so an iteration whose search or first poll points succeed spends 1 or
5 evaluations instead of 2n + 1. On the built-in patients (16 envs, 480 evaluations, 10 seeds,
medians) this takes the evaluations to 3 % from 61 / 123 (N / HF) to 31 / 83 and the final
mismatch from 0.030 % / 0.060 % to 0.008 % / 0.006 %, for more env steps (wall time 4.2 / 3.3 s
per fit; `scripts/bench_optim.py`).
Points outside the box are never evaluated (extreme barrier); failed evaluations have merit +inf.

Constraint h >= 0: either the exact penalty f + penalty·h of `optim.protocol` (default), or the
progressive barrier of Audet & Dennis (2009, `optim.barrier`), which polls a primary and a
secondary frame centre and keeps the mesh on "improving" iterations. With h = 0 everywhere both
are plain MADS.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.gaussian_process import GaussianProcessRegressor

from optim.barrier import BarrierPoint, ProgressiveBarrier
from optim.gp import (
    fit_gp_or_log,
    impute_infeasible,
    latin_hypercube,
    matern_kernel,
    minimise_on_cube,
    predict,
    propose_batch,
    single_threaded_blas,
)
from optim.protocol import BatchEvaluation, Bounds, FloatArray, Optimizer

PollOrder = Literal["surrogate", "last_success", "none"]
Constraint = Literal["penalty", "progressive_barrier"]


class Surrogate(NamedTuple):
    """A fitted GP with the unit-cube points u and the targets y it was fitted to: the (imputed)
    merits or their log10 (`optim.gp.fit_gp_or_log`)."""

    gp: GaussianProcessRegressor
    u: FloatArray
    y: FloatArray


def first_primes(count: int) -> list[int]:
    """The first `count` primes, 2, 3, 5, ..."""
    primes: list[int] = []
    candidate = 2
    while len(primes) < count:
        if all(candidate % p for p in primes if p * p <= candidate):
            primes.append(candidate)
        candidate += 1
    return primes


def halton_point(t: int, dimension: int) -> FloatArray:
    """u_t: radical inverse of t in the bases of the first `dimension` primes."""
    out = np.empty(dimension)
    for i, base in enumerate(first_primes(dimension)):
        value, scale, k = 0.0, 1.0 / base, t
        while k > 0:
            value += (k % base) * scale
            k //= base
            scale /= base
        out[i] = value
    return out


def adjusted_halton_direction(t: int, bound: float, dimension: int) -> NDArray[np.int64]:
    """q_t = round(α v), v = (2u_t - e)/||2u_t - e||, α maximal with ||q|| <= bound (>= 1;
    OrthoMADS's bound at level ℓ is 2^(abs(ℓ)/2)).

    ||round(α v)|| is non-decreasing in α, so the largest admissible α is found by bisection.
    Rounding is half away from zero.
    """
    w = 2.0 * halton_point(t, dimension) - 1.0
    if not np.any(w):
        raise ValueError(f"Halton point {t} is the cube centre; OrthoMADS uses t >= p_n")
    if bound < 1.0:
        raise ValueError(f"bound must be >= 1 (a unit direction), got {bound}")
    v = w / np.linalg.norm(w)
    target = float(bound)

    def q_of(alpha: float) -> NDArray[np.int64]:
        return (np.sign(v) * np.floor(alpha * np.abs(v) + 0.5)).astype(np.int64)

    lo, hi = 0.5 / np.max(np.abs(v)), target + np.sqrt(dimension)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if np.linalg.norm(q_of(mid)) <= target + 1e-12:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-12 * hi:
            break
    return q_of(lo)


def householder_basis(q: NDArray[np.int64]) -> NDArray[np.int64]:
    """H = ||q||² I - 2 q qᵀ: integer, HᵀH = ||q||⁴ I."""
    return int(q @ q) * np.eye(q.size, dtype=np.int64) - 2 * np.outer(q, q)


@dataclasses.dataclass(frozen=True)
class MadsOptions:
    """OrthoMADS settings; sizes are fractions of the box width (unit-cube units).

    initial_poll_size: s0, the first poll's distance (0.1: NOMAD's default initial size, 10 % of
    the range; 0.25 cost 1.2–1.8× the evaluations to 3 % on the built-in patients).
    mesh_scale: c in δm = min(s0, δp²/c), >= s0 (see the module docstring; c = s0 is
    OrthoMADS's mesh).
    n_search: search points per iteration: the GP mean's minimiser, then kriging-believer EI
    points. Default 1 (the minimiser alone): on the built-in patients, EI points filling the
    batch cost 1.7–2× the evaluations to 3 % (`scripts/bench_optim.py`).
    None fills the batch: max(2, batch_size - n_poll) with n_poll = 2n (+ 2 secondary poll
    points under the barrier). With batch_size >= n_poll + n_search, ``poll_chunk=None`` and
    ``search_first=False`` an iteration is one step.
    gp_points: the GP is fitted to at most this many evaluated points nearest the incumbent.
    refit_every: GP hyperparameters are re-estimated every this many iterations and kept fixed
    (warm start) in between.
    initial_design: fill the first batch with x0 and a Latin hypercube. Default: x0 alone, and a
    Latin-hypercube batch only if x0 fails (a good start, such as a patient's own parameters,
    is worth more than a spread first batch).
    search_first: evaluate the search points as a batch of their own before the poll, which is
    skipped when they improve the incumbent (MADS's search-then-poll order). One more env
    step per iteration; 2n evaluations fewer per successful search.
    poll_chunk: evaluate the poll in batches of at most this many points, in poll order (the
    surrogate's ranking), ending the iteration at the first batch that improves the incumbent
    (with ``opportunistic``). None: the whole iteration in one batch, the fewest env steps.
    ``search_first`` and ``poll_chunk`` apply to the penalty mode; the progressive barrier
    evaluates each iteration (both frame centres' polls) in chunks of batch_size.
    Default 4 (with ``search_first``; module docstring, Batching, for the figures).
    constraint: "penalty" minimises f + penalty·h (`optim.protocol`); "progressive_barrier"
    treats h by the progressive barrier (`optim.barrier`) with frame-centre trigger rho (in
    objective units) and reports the best point with h = 0. The kriging search models
    f + penalty·h in both modes.
    """

    initial_poll_size: float = 0.1
    mesh_scale: float = 1.0
    min_poll_size: float = 1e-6
    opportunistic: bool = True
    poll_order: PollOrder = "surrogate"
    kriging_search: bool = True
    n_search: int | None = 1
    gp_points: int = 120
    refit_every: int = 5
    initial_design: bool = False
    constraint: Constraint = "penalty"
    rho: float = 0.1
    nu: float = 2.5
    nugget: float = 1e-6
    n_candidates: int = 512
    search_first: bool = True
    poll_chunk: int | None = 4


class Mads(Optimizer):
    """OrthoMADS (2n orthogonal directions) with a kriging search step; see module docstring."""

    def __init__(
        self,
        bounds: Bounds,
        batch_size: int,
        seed: int = 0,
        options: MadsOptions | None = None,
        penalty: float = 1.0,
        x0: ArrayLike | None = None,
    ) -> None:
        super().__init__(bounds, batch_size, seed, penalty, x0)
        o = self.options = options or MadsOptions()
        if not 0.0 < o.initial_poll_size <= 1.0:
            raise ValueError(f"initial_poll_size must lie in (0, 1], got {o.initial_poll_size}")
        if not o.initial_poll_size <= o.mesh_scale < np.inf:
            raise ValueError(f"mesh_scale must lie in [initial_poll_size, inf), got {o.mesh_scale}")
        if not 0.0 < o.min_poll_size < o.initial_poll_size:
            raise ValueError(f"min_poll_size must lie in (0, initial_poll_size), got {o.min_poll_size}")
        if o.poll_order not in ("surrogate", "last_success", "none"):
            raise ValueError(f"unknown poll_order {o.poll_order!r}")
        if o.constraint not in ("penalty", "progressive_barrier"):
            raise ValueError(
                f"unknown constraint {o.constraint!r}; use 'penalty' or 'progressive_barrier'"
            )
        if o.poll_chunk is not None and (isinstance(o.poll_chunk, bool) or not isinstance(o.poll_chunk, int) or o.poll_chunk < 1):
            raise ValueError(f"poll_chunk must be None or an integer >= 1, got {o.poll_chunk!r}")
        if (o.n_search is not None and o.n_search < 0) or o.refit_every < 1 or o.n_candidates < 1:
            raise ValueError("n_search must be >= 0, refit_every and n_candidates >= 1")
        if o.gp_points < self.dimension + 2:
            raise ValueError(f"gp_points must be >= n + 2 = {self.dimension + 2}, got {o.gp_points}")
        n = self.dimension
        self.level = 0
        self.min_level = -int(np.floor(np.log2(1.0 / o.initial_poll_size)))
        self._max_level_seen: int | None = None
        self._t_max = 0
        self._t0 = first_primes(n)[-1]
        n_poll = 2 * n + (2 if o.constraint == "progressive_barrier" else 0)
        self.n_search = o.n_search if o.n_search is not None else max(2, self.batch_size - n_poll)
        n_design = self.batch_size - 1 if o.initial_design else 0
        self._queue = np.vstack([self.u0, latin_hypercube(n_design, n, self.rng)])
        self._initial_phase = True
        self._designed = o.initial_design
        self.barrier = ProgressiveBarrier(o.rho)
        self.barrier.start_iteration()
        self._centre = self.u0.copy()
        self._last_success_dir: FloatArray | None = None
        self._evaluated: set[bytes] = set()
        self._u = np.empty((0, n))
        self._y = np.empty(0)  # penalised merit f + penalty·h, the surrogate's target
        self._kernels = (matern_kernel(n, o.nu), matern_kernel(n, o.nu))  # GP on y, on log10 y
        self.iterations = 0
        self.search_successes = 0
        self.poll_successes = 0
        self._iter_search_left = 0
        self._iter_best_from_search = False

    def options_fingerprint(self) -> tuple[Any, ...]:
        return dataclasses.astuple(self.options)

    def _merit(self, evaluation: BatchEvaluation) -> FloatArray:
        """Penalty mode: f + penalty·h. Barrier mode: f where h = 0, else inf (so the result's
        best point is the best feasible one)."""
        if self.options.constraint == "penalty":
            return super()._merit(evaluation)
        ok = evaluation.feasible & (evaluation.violation == 0.0)
        return np.where(ok, evaluation.f, np.inf)

    # ------------------------------------------------------------------ mesh
    @property
    def mesh_size(self) -> float:
        """δm = min(s0, δp²/c)."""
        return min(self.options.initial_poll_size, self.poll_size**2 / self.options.mesh_scale)

    @property
    def poll_size(self) -> float:
        """δp = s0 · 2^(-ℓ)."""
        return self.options.initial_poll_size * 2.0 ** (-self.level)

    @property
    def incumbent(self) -> FloatArray:
        """Current primary frame centre in physical units."""
        return self.bounds.from_unit(self._centre)

    def _key(self, u: FloatArray) -> bytes:
        return np.round(np.asarray(u) * 2.0**48).astype(np.int64).tobytes()

    def _to_mesh(self, y: FloatArray) -> FloatArray:
        """x_k + δm round((y - x_k)/δm), with the integer steps clipped to stay in [0, 1]^n."""
        x, dm = self._centre, self.mesh_size
        lo, hi = np.ceil(-x / dm - 1e-9), np.floor((1.0 - x) / dm + 1e-9)
        z = np.clip(np.round((y - x) / dm), lo, hi)
        return np.clip(x + dm * z, 0.0, 1.0)

    def _halton_index(self) -> int:
        if self._max_level_seen is None or self.level > self._max_level_seen:
            t = self.level + self._t0
            self._max_level_seen = self.level
        else:
            t = 1 + self._t_max
        self._t_max = max(self._t_max, t)
        return t

    def poll_directions(self) -> NDArray[np.int64]:
        """(2n, n) integer directions [H, -H] (rows) for the current level (advances t)."""
        bound = max(1.0, np.sqrt(self.poll_size / self.mesh_size))  # δm <= δp; guard the rounding
        q = adjusted_halton_direction(self._halton_index(), bound, self.dimension)
        h = householder_basis(q)
        return np.vstack([h.T, -h.T])

    # ------------------------------------------------------------------ search
    def _surrogate(self) -> Surrogate | None:
        """GP on the gp_points evaluated points nearest the centre, or None if unavailable."""
        o = self.options
        if not o.kriging_search or len(self._y) < self.dimension + 2:
            return None
        near = np.argsort(np.linalg.norm(self._u - self._centre, axis=1), kind="stable")[: o.gp_points]
        try:
            y = impute_infeasible(self._y[near])
            refit = self.iterations % o.refit_every == 0
            gp, targets, self._kernels = fit_gp_or_log(self._u[near], y, self._kernels, o.nugget, refit)
        except (ValueError, np.linalg.LinAlgError):
            return None
        return Surrogate(gp, self._u[near], targets)

    def _search_points(self, surrogate: Surrogate | None) -> FloatArray:
        """Minimiser of the GP mean, then n_search - 1 kriging-believer EI points, on the mesh."""
        if surrogate is None or self.n_search < 1:
            return np.empty((0, self.dimension))
        gp, u, y = surrogate
        n, cands = self.dimension, self.options.n_candidates

        def mean(c: FloatArray) -> FloatArray:
            return predict(gp, c)[0]

        anchors = np.vstack([self._centre, u[np.argsort(y, kind="stable")[:2]]])
        near_frame = self.poll_size * np.array([4.0, 1.0, 0.25])
        radii = tuple(sorted({0.1, 0.03, 0.01, 0.003, *near_frame.tolist()}, reverse=True))
        points = [minimise_on_cube(mean, n, self.rng, cands, anchors, radii)[0]]
        if self.n_search > 1:
            points.extend(propose_batch(gp, u, y, self.n_search - 1, self.rng, "believer", cands))
        return np.array([self._to_mesh(p) for p in points])

    # ------------------------------------------------------------------ iteration
    def _start_iteration(self) -> None:
        """Trial list: search points, 2n poll points around the primary centre (ordered), and
        the two points ±d_1 around the secondary centre when the barrier has one."""
        centres = [c.u for c in self.barrier.poll_centres()] or [self._centre]
        self._centre = centres[0]
        dirs = self.poll_directions().astype(np.float64)
        x, dm = self._centre, self.mesh_size
        with single_threaded_blas():
            surrogate = self._surrogate()
            search = self._search_points(surrogate)
            mean_at_poll = predict(surrogate.gp, x + dm * dirs)[0] if surrogate is not None else None
        order = np.arange(len(dirs))
        if self.options.poll_order == "surrogate" and mean_at_poll is not None:
            order = np.argsort(mean_at_poll, kind="stable")
        elif self.options.poll_order != "none" and self._last_success_dir is not None:
            cos = dirs @ self._last_success_dir / (np.linalg.norm(dirs, axis=1) + 1e-300)
            order = np.argsort(-cos, kind="stable")
        poll = [x + dm * dirs[order]]
        if len(centres) > 1:
            poll.append(centres[1] + dm * dirs[[0, self.dimension]])
        candidates = np.vstack([search.reshape(-1, self.dimension), *poll])
        inside = np.all((candidates >= 0.0) & (candidates <= 1.0), axis=1)  # extreme barrier
        trials: list[FloatArray] = []
        seen = set(self._evaluated)
        self._iter_search_left = 0
        for j, p in enumerate(candidates):
            k = self._key(p)
            if inside[j] and k not in seen:
                seen.add(k)
                trials.append(p)
            if j == len(search) - 1:
                self._iter_search_left = len(trials)
        self._queue = np.array(trials).reshape(-1, self.dimension)
        self._iter_best_from_search = False
        self.barrier.start_iteration()

    def _end_iteration(self) -> None:
        """Mesh update from the barrier's status: dominating ℓ - 1, improving ℓ, else ℓ + 1."""
        status = self.barrier.end_iteration()
        if status == "dominating":
            centres = self.barrier.poll_centres()
            if centres:
                self._last_success_dir = centres[0].u - self._centre
            self.level = max(self.level - 1, self.min_level)
            if self._iter_best_from_search:
                self.search_successes += 1
            else:
                self.poll_successes += 1
        elif status == "unsuccessful":
            self.level += 1
        self._queue = np.empty((0, self.dimension))
        self.iterations += 1

    def _ask_unit(self, max_points: int) -> FloatArray:
        while len(self._queue) == 0:
            if self._stop():
                return np.empty((0, self.dimension))
            self._start_iteration()
            if len(self._queue) == 0:
                self._end_iteration()
        o = self.options
        if o.constraint == "penalty" and not self._initial_phase:
            if o.search_first and self._iter_search_left > 0:
                max_points = min(max_points, self._iter_search_left)
            elif o.poll_chunk is not None:
                max_points = min(max_points, o.poll_chunk + self._iter_search_left)
        out, self._queue = self._queue[:max_points], self._queue[max_points:]
        return out

    def _barrier_point(
        self, u: FloatArray, merit: float, evaluation: BatchEvaluation, j: int
    ) -> BarrierPoint:
        if self.options.constraint == "penalty" or not evaluation.feasible[j]:
            return BarrierPoint(u, merit, 0.0)
        return BarrierPoint(u, float(evaluation.f[j]), float(evaluation.violation[j]))

    def _tell_unit(self, u: FloatArray, merit: FloatArray, evaluation: BatchEvaluation) -> None:
        penalised = super()._merit(evaluation)
        self._evaluated.update(self._key(p) for p in u)
        self._u = np.vstack([self._u, u])
        self._y = np.append(self._y, penalised)
        n_search_here = min(self._iter_search_left, len(u))  # chunks keep the queue's order
        self._iter_search_left -= n_search_here
        for j in range(len(u)):
            p = self._barrier_point(u[j].copy(), float(merit[j]), evaluation, j)
            if self.barrier.insert(p) == "dominating":
                self._iter_best_from_search = j < n_search_here
        if self._initial_phase:
            if len(self._queue) == 0 and not self._designed and not np.isfinite(self._y).any():
                self._designed = True  # x0 failed: a Latin hypercube looks for a point that does not
                self._queue = latin_hypercube(self.batch_size, self.dimension, self.rng)
                return
            if len(self._queue) == 0:
                self._initial_phase = False
                self.barrier.end_iteration()
                self._centre = next((c.u for c in self.barrier.poll_centres()), self._centre)
            return
        improved = self.barrier.status == "dominating"
        if len(self._queue) == 0 or (self.options.opportunistic and improved):
            self._end_iteration()

    def _stop(self) -> dict[str, float]:
        if self.poll_size < self.options.min_poll_size:
            return {"min_poll_size": self.poll_size}
        return {}

    def _info(self) -> dict[str, float]:
        return {
            "mesh_size": self.mesh_size,
            "poll_size": self.poll_size,
            "level": float(self.level),
            "iterations": float(self.iterations),
            "search_successes": float(self.search_successes),
            "poll_successes": float(self.poll_successes),
            "h_max": float(self.barrier.h_max),
            "filter_size": float(len(self.barrier.filter)),
        }
