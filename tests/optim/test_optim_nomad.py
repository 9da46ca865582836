"""NOMAD 4 (ORTHO 2N, block evaluation) as a reference on the batch-objective interface."""

from __future__ import annotations

import numpy as np
import pytest

import optim
from optim import Bounds, MadsOptions

import PyNomad  # noqa: E402,F401  (make test installs the nomad extra: missing NOMAD must fail, not skip)
from optim.nomad_ref import nomad_minimize  # noqa: E402

BOUNDS = Bounds(np.full(4, -2.0), np.full(4, 3.0))
CENTRE = np.array([0.37, -1.21, 1.7, 0.05])


def sphere(x: np.ndarray) -> np.ndarray:
    return np.sum((x - CENTRE) ** 2, axis=1)


def test_nomad_solves_a_sphere_with_block_evaluation() -> None:
    blocks: list[int] = []

    def objective(x: np.ndarray) -> np.ndarray:
        blocks.append(len(x))
        return sphere(x)

    res = nomad_minimize(objective, BOUNDS, budget=600, batch_size=8, seed=1)
    # NOMAD evaluates its last block whole, so it may pass MAX_BB_EVAL by less than a block
    assert max(blocks) == 8 and sum(blocks) == res.evaluations < 600 + 8
    np.testing.assert_allclose(res.x_best, CENTRE, atol=1e-3)
    assert res.f_best == pytest.approx(float(sphere(res.x_best[None])[0]))


def test_nomad_and_our_mads_agree_on_the_optimum() -> None:
    ours = optim.run(optim.Mads(BOUNDS, 8, options=MadsOptions(kriging_search=False)), sphere, 1500)
    ref = nomad_minimize(sphere, BOUNDS, budget=1500, batch_size=8)
    np.testing.assert_allclose(ours.x_best, ref.x_best, atol=1e-3)
    assert ours.f_best < 1e-8 and ref.f_best < 1e-6


def test_nomad_treats_failed_points_as_infeasible() -> None:
    def failing(x: np.ndarray) -> np.ndarray:
        f = sphere(x)
        f[x[:, 0] > 1.0] = np.nan
        return f

    res = nomad_minimize(failing, BOUNDS, budget=300, batch_size=8)
    assert np.isfinite(res.f_best) and res.x_best[0] <= 1.0
    assert not res.history.feasible[res.history.x[:, 0] > 1.0].any()
