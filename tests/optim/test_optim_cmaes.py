"""The CMA-ES wrapper against plain pycma with the same seed, and its restarts."""

from __future__ import annotations

import cma
import numpy as np
import pytest

import optim
from optim import Bounds, CmaEs, CmaOptions

LOWER, UPPER = np.array([-1.0, 0.0, 2.0, -5.0]), np.array([3.0, 1.0, 4.0, 5.0])
BOUNDS = Bounds(LOWER, UPPER)


def rosenbrock_physical(x: np.ndarray) -> np.ndarray:
    z = (x - LOWER) / (UPPER - LOWER) * 2.0 - 0.5  # optimum inside the box
    return np.sum(100.0 * (z[:, 1:] - z[:, :-1] ** 2) ** 2 + (1.0 - z[:, :-1]) ** 2, axis=1)


def plain_cma(seed: int, popsize: int, budget: int, options: CmaOptions) -> list[np.ndarray]:
    """The documented pycma loop on the unit cube; returns every generation asked."""
    opts = CmaEs.pycma_options(4, popsize, seed, options)
    es = cma.CMAEvolutionStrategy([0.5] * 4, options.sigma0, opts)
    generations = []
    while not es.stop() and es.countevals + popsize <= budget:
        u = es.ask()
        x = LOWER + np.array(u) * (UPPER - LOWER)
        es.tell(u, rosenbrock_physical(x).tolist())
        generations.append(x)
    return generations


@pytest.mark.parametrize(("batch", "factor"), [(6, 1), (4, 3)])
def test_wrapper_equals_plain_cma_with_the_same_seed(batch: int, factor: int) -> None:
    options = CmaOptions(popsize_factor=factor)
    opt = CmaEs(BOUNDS, batch, seed=7, options=options)
    np.random.seed(123)
    outside = np.random.get_state()
    res = optim.run(opt, rosenbrock_physical, 600)
    assert np.array_equal(np.random.get_state()[1], outside[1])  # global RNG left alone
    reference = plain_cma(opt.cma_seed, batch * factor, 600, options)
    np.testing.assert_array_equal(res.history.x, np.concatenate(reference))
    assert res.evaluations == sum(len(g) for g in reference) == 600 // (batch * factor) * batch * factor
    assert np.bincount(res.history.batch).max() == batch
    assert res.f_best == pytest.approx(float(np.min(rosenbrock_physical(np.concatenate(reference)))), abs=0)


def rastrigin(x: np.ndarray) -> np.ndarray:
    z = (x - LOWER) / (UPPER - LOWER) * 10.24 - 5.12 - 0.3
    return 10.0 * z.shape[1] + np.sum(z**2 - 10.0 * np.cos(2.0 * np.pi * z), axis=1)


@pytest.mark.parametrize("strategy", ["ipop", "bipop"])
def test_restarts_grow_the_population_in_batch_multiples(strategy: str) -> None:
    options = CmaOptions(restarts=4, restart_strategy=strategy, tolfun=1e-3, tolx=1e-4)  # type: ignore[arg-type]
    opt = CmaEs(BOUNDS, 4, seed=1, options=options)
    runs: list[tuple[int, int, float]] = []

    def record(o: optim.Optimizer) -> None:
        assert isinstance(o, CmaEs)
        runs.append((o.restart, o.es.popsize, o.es.sigma0))

    res = optim.run(opt, rastrigin, 3000, callback=record)
    starts = sorted(set(runs))
    popsizes = [p for _, p, _ in starts]
    assert opt.restart >= 2 and all(p % 4 == 0 for p in popsizes)
    if strategy == "ipop":
        assert popsizes == [4 * 2**r for r in range(len(starts))]
        assert {s for _, _, s in starts} == {0.25}
    else:  # the small regime keeps λ = batch and shrinks σ0 = 0.25 · 10^(-2U)
        assert any(p == 4 and s < 0.25 for _, p, s in starts[1:])
        assert any(p == 8 for p in popsizes)
    assert res.f_best < 10.0


def test_sigma0_is_in_unit_cube_units() -> None:
    opt = CmaEs(BOUNDS, 4, seed=0, options=CmaOptions(sigma0=0.1))
    assert opt.es.sigma == 0.1
    x = opt.ask()
    spread = np.std((x - LOWER) / (UPPER - LOWER), axis=0)
    assert np.all(spread < 0.5)


def test_budget_below_one_generation() -> None:
    with pytest.raises(ValueError, match="below one batch of 12"):
        optim.run(CmaEs(BOUNDS, 4, options=CmaOptions(popsize_factor=3)), rastrigin, 8)


def test_bad_options() -> None:
    with pytest.raises(ValueError, match="sigma0"):
        CmaEs(BOUNDS, 4, options=CmaOptions(sigma0=0.0))
    with pytest.raises(ValueError, match="at least 2 parameters"):
        CmaEs(Bounds(np.zeros(1), np.ones(1)), 4)
    with pytest.raises(ValueError, match="restart_strategy"):
        CmaEs(BOUNDS, 4, options=CmaOptions(restart_strategy="lpop"))  # type: ignore[arg-type]
