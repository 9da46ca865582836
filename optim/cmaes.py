"""CMA-ES through the `cma` package (pycma) on the unit cube, with IPOP / BIPOP restarts.

CMA-ES: Hansen N (2016) The CMA evolution strategy: a tutorial, arXiv:1604.00772.
IPOP: Auger A, Hansen N (2005) A restart CMA evolution strategy with increasing population
size, CEC 2005, 1769-1776 — after each stop, λ_{r+1} = incpopsize · λ_r.
BIPOP: Hansen N (2009) Benchmarking a BI-population CMA-ES on the BBOB-2009 function testbed,
GECCO 2009 — alternate the IPOP regime with a small regime of
λ_s = ⌊λ_0 (λ_large / (2 λ_0))^(U²)⌋, σ_s = σ_0 · 10^(-2U), U ~ U(0, 1), choosing whichever
regime has used fewer evaluations so far.

Here λ_0 = popsize_factor · batch_size and every λ is rounded up to a multiple of batch_size,
so that one generation is a whole number of vector-env steps; the generation is asked in chunks
of batch_size and told to pycma when complete. Bounds are handled by pycma's `BoundTransform`
on [0, 1]^n; sigma0 is in unit-cube units. Failed points (merit +inf) get the worst finite merit
of their generation plus one, i.e. they are ranked last (CMA-ES is rank-based).

pycma samples with `np.random.randn` after `np.random.seed(seed)`. The wrapper hands it the
`randn` of a private `RandomState(seed)` instead (the same stream), and swaps a private global
`numpy.random` state in around every call into pycma for its few other draws, so runs are
reproducible, independent of other users of `numpy.random`, and resumable from a pickle.
pycma reads seed 0 as "seed from the clock", so the first run uses `cma_seed = seed + 1`.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from typing import Any, Literal

import cma
import numpy as np
from numpy.typing import ArrayLike

from optim.protocol import BatchEvaluation, Bounds, FloatArray, Optimizer

RestartStrategy = Literal["ipop", "bipop"]


@dataclasses.dataclass(frozen=True)
class CmaOptions:
    """sigma0 in unit-cube units; restarts = how many restarts after the first run."""

    sigma0: float = 0.25
    popsize_factor: int = 1
    restarts: int = 0
    restart_strategy: RestartStrategy = "ipop"
    incpopsize: int = 2
    tolfun: float = 1e-11
    tolx: float = 1e-11


class CmaEs(Optimizer):
    """Ask/tell wrapper over `cma.CMAEvolutionStrategy`; one generation = λ/batch_size steps."""

    def __init__(
        self,
        bounds: Bounds,
        batch_size: int,
        seed: int = 0,
        options: CmaOptions | None = None,
        penalty: float = 1.0,
        x0: ArrayLike | None = None,
    ) -> None:
        super().__init__(bounds, batch_size, seed, penalty, x0)
        o = self.options = options or CmaOptions()
        if self.dimension < 2:
            raise ValueError("CMA-ES (pycma) needs at least 2 parameters; use 'mads' in 1-D")
        if not 0.0 < o.sigma0 <= 1.0:
            raise ValueError(f"sigma0 must lie in (0, 1], got {o.sigma0}")
        if o.popsize_factor < 1 or o.restarts < 0 or o.incpopsize < 1:
            raise ValueError("popsize_factor and incpopsize must be >= 1 and restarts >= 0")
        if o.restart_strategy not in ("ipop", "bipop"):
            raise ValueError(f"unknown restart_strategy {o.restart_strategy!r}; use 'ipop' or 'bipop'")
        self.popsize0 = o.popsize_factor * self.batch_size
        self.restart = 0
        self._large_runs = 0
        self._evals_regime = {"large": 0, "small": 0}
        self._regime = "large"
        self._run_evals = 0
        self._np_state = np.random.RandomState(0).get_state()
        self._generation: list[FloatArray] | None = None
        self._told: list[float] = []
        self.es = self._new_es(self.u0, o.sigma0, self.popsize0, self.cma_seed)

    @property
    def cma_seed(self) -> int:
        """Seed of the first pycma run (pycma treats 0 as the clock, hence + 1)."""
        return self.seed + 1

    @property
    def min_budget(self) -> int:
        """One generation of the first run, popsize_factor · batch_size."""
        return self.popsize0

    def options_fingerprint(self) -> tuple[Any, ...]:
        return dataclasses.astuple(self.options)

    @staticmethod
    def pycma_options(dimension: int, popsize: int, seed: int, o: CmaOptions) -> dict[str, Any]:
        """The options handed to pycma (public so that tests can build the same plain run)."""
        return {
            "seed": seed,
            "popsize": popsize,
            "bounds": [[0.0] * dimension, [1.0] * dimension],
            "tolfun": o.tolfun,
            "tolx": o.tolx,
            "verbose": -9,
            "verb_log": 0,
            "verb_disp": 0,
        }

    @contextlib.contextmanager
    def _own_random_state(self) -> Iterator[None]:
        outside = np.random.get_state()
        np.random.set_state(self._np_state)
        try:
            yield
        finally:
            self._np_state = np.random.get_state()
            np.random.set_state(outside)

    def _new_es(
        self, u0: FloatArray, sigma0: float, popsize: int, seed: int
    ) -> cma.CMAEvolutionStrategy:
        opts = self.pycma_options(self.dimension, popsize, seed, self.options)
        # np.random.seed(seed) + np.random.randn, as pycma does, but on a private generator that
        # pickles with the strategy (a pickled np.random.randn would be a detached copy)
        opts["seed"], opts["randn"] = np.nan, np.random.RandomState(seed).randn
        with self._own_random_state():
            return cma.CMAEvolutionStrategy(list(u0), sigma0, opts)

    def _restart(self) -> None:
        """Next run: IPOP doubles λ; BIPOP picks the regime that used fewer evaluations."""
        o = self.options
        self._evals_regime[self._regime] += self._run_evals
        self._run_evals = 0
        self.restart += 1
        large_popsize = self.popsize0 * o.incpopsize ** (self._large_runs + 1)
        sigma, popsize = o.sigma0, large_popsize
        self._regime = "large"
        small_is_behind = self._evals_regime["small"] < self._evals_regime["large"]
        if o.restart_strategy == "bipop" and small_is_behind:
            self._regime = "small"
            u = self.rng.random()
            last_large = self.popsize0 * o.incpopsize**self._large_runs
            popsize = int(self.popsize0 * (0.5 * last_large / self.popsize0) ** (u * u))
            sigma = o.sigma0 * 10.0 ** (-2.0 * u)
        else:
            self._large_runs += 1
        popsize = -(-max(popsize, self.batch_size) // self.batch_size) * self.batch_size
        u0 = self.rng.random(self.dimension)
        self.es = self._new_es(u0, sigma, popsize, int(self.rng.integers(1, 2**31 - 1)))

    def _es_stop(self) -> dict[str, float]:
        with self._own_random_state():
            return {str(k): float(v) if np.isscalar(v) else 1.0 for k, v in self.es.stop().items()}

    def ask(self, budget_left: int | None = None) -> FloatArray:
        """Next chunk of the current generation; empty if a new generation does not fit the budget."""
        if self._generation is None:
            if self._es_stop() and self.restart < self.options.restarts:
                self._restart()
            if budget_left is not None and budget_left < self.es.popsize:
                return np.empty((0, self.dimension))
        return super().ask(budget_left)

    def _ask_unit(self, max_points: int) -> FloatArray:
        if self._generation is None:
            with self._own_random_state():
                self._generation = self.es.ask()
            self._told = []
        start = len(self._told)
        return np.array(self._generation[start : start + min(self.batch_size, max_points)])

    def _tell_unit(self, u: FloatArray, merit: FloatArray, evaluation: BatchEvaluation) -> None:
        self._told.extend(float(m) for m in merit)
        assert self._generation is not None
        if len(self._told) < len(self._generation):
            return
        values = np.array(self._told)
        finite = np.isfinite(values)
        worst = values[finite].max() if finite.any() else 0.0
        values = np.where(finite, values, worst + 1.0)
        with self._own_random_state():
            self.es.tell(self._generation, values.tolist())
        self._run_evals += len(values)
        self._generation = None

    def _stop(self) -> dict[str, float]:
        if self._generation is not None:
            return {}
        reasons = self._es_stop()
        if reasons and self.restart < self.options.restarts:
            return {}
        return reasons

    def _info(self) -> dict[str, float]:
        return {
            "sigma": float(self.es.sigma),
            "popsize": float(self.es.popsize),
            "restarts": float(self.restart),
        }
