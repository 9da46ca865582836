"""OrthoMADS: directions (Abramson et al. 2009), mesh rules, convergence with mesh size -> 0."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import optim
from optim import Bounds, MadsOptions
from optim.mads import adjusted_halton_direction, first_primes, halton_point, householder_basis


def test_halton_points_are_radical_inverses() -> None:
    assert first_primes(5) == [2, 3, 5, 7, 11]
    np.testing.assert_allclose(halton_point(1, 3), [1 / 2, 1 / 3, 1 / 5])
    # 5 = 101 (base 2) -> 0.101 = 5/8;  5 = 12 (base 3) -> 0.21 = 2/3 + 1/9;  5 = 10 (base 5) -> 1/25
    np.testing.assert_allclose(halton_point(5, 3), [5 / 8, 2 / 3 + 1 / 9, 1 / 25])


@settings(max_examples=60, deadline=None)
@given(t=st.integers(0, 2000), level=st.integers(-3, 24), n=st.integers(1, 8))
def test_householder_directions_are_orthogonal_on_the_poll_frame(t: int, level: int, n: int) -> None:
    bound = 2.0 ** (abs(level) / 2)
    q = adjusted_halton_direction(first_primes(n)[-1] + t, bound, n)
    assert 1 <= np.linalg.norm(q) <= bound + 1e-12
    # α is maximal: q is within rounding of the sphere of radius 2^(|ℓ|/2)
    assert np.linalg.norm(q) >= bound - np.sqrt(n)
    h = householder_basis(q)
    assert h.dtype == np.int64
    np.testing.assert_array_equal(h.T @ h, (q @ q) ** 2 * np.eye(n, dtype=np.int64))


def mesh_and_poll_sizes(options: MadsOptions, levels: tuple[int, ...]) -> list[tuple[float, float]]:
    opt = optim.Mads(Bounds(np.zeros(2), np.ones(2)), 4, options=options)
    sizes = []
    for level in levels:
        opt.level = level
        sizes.append((opt.mesh_size, opt.poll_size))
    assert opt.min_level == -int(np.floor(np.log2(1 / options.initial_poll_size)))  # poll size never exceeds the box
    return sizes


def test_mesh_and_poll_size_rules() -> None:
    # mesh_scale = s0: OrthoMADS's δm = s0 min(1, 4^-ℓ), δp = s0 2^-ℓ
    orthomads = mesh_and_poll_sizes(MadsOptions(initial_poll_size=0.5, mesh_scale=0.5), (-1, 0, 1, 2, 3))
    np.testing.assert_allclose(orthomads, [(0.5, 1.0), (0.5, 0.5), (0.125, 0.25), (0.5 / 16, 0.125), (0.5 / 64, 0.0625)])
    # default mesh_scale = 1: δm = min(s0, δp²), finer than the frame by c/δp = 2^ℓ / s0
    finer = mesh_and_poll_sizes(MadsOptions(initial_poll_size=0.1), (-3, 0, 1, 4))
    np.testing.assert_allclose(finer, [(0.1, 0.8), (0.01, 0.1), (0.0025, 0.05), (0.1**2 / 256, 0.1 / 16)])
    assert all(m <= p for m, p in orthomads + finer)
    with pytest.raises(ValueError, match="mesh_scale"):
        optim.Mads(Bounds(np.zeros(2), np.ones(2)), 4, options=MadsOptions(initial_poll_size=0.5, mesh_scale=0.25))


@pytest.mark.parametrize("options", [MadsOptions(), MadsOptions(initial_poll_size=0.25, mesh_scale=0.25)])
def test_poll_points_lie_on_the_mesh_at_the_poll_distance(options: MadsOptions) -> None:
    opt = optim.Mads(Bounds(np.zeros(4), np.ones(4)), 8, options=options)
    for level in range(0, 12, 3):
        opt.level = level
        d = opt.poll_directions()
        assert d.shape == (8, 4) and np.linalg.matrix_rank(d) == 4
        lengths = opt.mesh_size * np.linalg.norm(d, axis=1)
        assert np.all(lengths <= opt.poll_size * (1 + 1e-12)) and np.all(lengths >= 0.25 * opt.poll_size)


def run_mads(f, bounds: Bounds, budget: int, batch: int, **options: object) -> optim.OptimResult:
    opts = MadsOptions(**{"min_poll_size": 1e-5, **options})  # type: ignore[arg-type]
    return optim.run(optim.Mads(bounds, batch, seed=0, options=opts), f, budget)


def test_sphere_with_kriging_search_converges_and_the_mesh_shrinks() -> None:
    centre = np.array([0.31, -0.77, 0.45])

    def sphere(x: np.ndarray) -> np.ndarray:
        return np.sum((x - centre) ** 2, axis=1)

    res = run_mads(sphere, Bounds(np.full(3, -1.0), np.full(3, 1.0)), 400, 8, refit_every=3, n_candidates=128)
    assert res.stop_reason == {"min_poll_size": res.info["poll_size"]}
    assert res.info["mesh_size"] < 1e-9
    np.testing.assert_allclose(res.x_best, centre, atol=2e-4)
    assert res.info["search_successes"] >= 1
    assert np.all(res.history.batch[:-1] <= res.history.batch[1:])


@pytest.mark.parametrize("opportunistic", [True, False])
def test_rosenbrock_converges(opportunistic: bool) -> None:
    def rosenbrock(x: np.ndarray) -> np.ndarray:
        return 100.0 * (x[:, 1] - x[:, 0] ** 2) ** 2 + (1.0 - x[:, 0]) ** 2

    res = run_mads(
        rosenbrock, Bounds(np.array([-2.0, -1.0]), np.array([2.0, 3.0])), 6000, 2,
        kriging_search=False, opportunistic=opportunistic, min_poll_size=1e-7,
    )
    assert "min_poll_size" in res.stop_reason and res.info["mesh_size"] < 1e-12
    np.testing.assert_allclose(res.x_best, [1.0, 1.0], atol=1e-3)


def test_bound_constrained_problem_converges_to_the_active_bounds() -> None:
    """min Σ w_i (x_i - c_i)² on a box that excludes c: the solution is clip(c, lower, upper)."""
    lower, upper = np.array([0.0, -1.0, 0.5, 0.0]), np.array([1.0, 1.0, 2.0, 3.0])
    c, w = np.array([1.8, 0.3, -0.4, 4.0]), np.array([1.0, 2.0, 0.5, 3.0])

    def quadratic(x: np.ndarray) -> np.ndarray:
        return (x - c) ** 2 @ w

    res = run_mads(quadratic, Bounds(lower, upper), 2000, 10, refit_every=5, n_candidates=128)
    assert "min_poll_size" in res.stop_reason and res.info["mesh_size"] < 1e-9
    np.testing.assert_allclose(res.x_best, np.clip(c, lower, upper), atol=1e-4)
    assert np.all(res.history.x >= lower) and np.all(res.history.x <= upper)  # extreme barrier


def shifted_sphere(x: np.ndarray) -> np.ndarray:
    return np.sum((x - 0.123) ** 2, axis=1)


def test_whole_poll_set_is_one_batch_and_opportunism_saves_batches() -> None:
    """Without poll chunks and with batch >= 2n + n_search every iteration is one batch; with
    small batches the opportunistic strategy stops polling after an improving chunk."""
    bounds = Bounds(np.zeros(3), np.ones(3))
    res = run_mads(shifted_sphere, bounds, 300, 8, kriging_search=False, initial_design=False, poll_chunk=None)
    assert res.batches <= res.info["iterations"] + 1  # + the batch holding x0
    assert np.bincount(res.history.batch).max() == 6  # a whole poll set in one batch
    greedy = run_mads(shifted_sphere, bounds, 300, 2, kriging_search=False, min_poll_size=1e-3)
    full = run_mads(shifted_sphere, bounds, 300, 2, kriging_search=False, opportunistic=False, min_poll_size=1e-3)
    per_iteration = [r.evaluations / r.info["iterations"] for r in (greedy, full)]
    assert per_iteration[0] < per_iteration[1]


def test_search_first_and_poll_chunks_end_an_iteration_at_its_first_success() -> None:
    """The search point goes alone, the poll in chunks of poll_chunk; an improving chunk ends
    the iteration, so an iteration costs fewer evaluations than the whole trial list."""
    bounds = Bounds(np.zeros(3), np.ones(3))
    chunked = run_mads(shifted_sphere, bounds, 300, 8, poll_chunk=2, refit_every=3, n_candidates=128)
    whole = run_mads(shifted_sphere, bounds, 300, 8, poll_chunk=None, search_first=False, refit_every=3, n_candidates=128)
    sizes = np.bincount(chunked.history.batch)
    assert sizes.max() <= 2 and np.bincount(whole.history.batch).max() == 7  # search point + 2n poll points
    assert np.sum(sizes[1:] == 1) >= chunked.info["iterations"] // 2  # search points went alone
    per_iteration = [r.evaluations / r.info["iterations"] for r in (chunked, whole)]
    assert per_iteration[0] < 0.75 * per_iteration[1]
    np.testing.assert_allclose(chunked.x_best, 0.123, atol=1e-3)


def test_bad_options() -> None:
    b = Bounds(np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="initial_poll_size"):
        optim.Mads(b, 2, options=MadsOptions(initial_poll_size=2.0))
    with pytest.raises(ValueError, match="poll_order"):
        optim.Mads(b, 2, options=MadsOptions(poll_order="random"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="gp_points"):
        optim.Mads(b, 2, options=MadsOptions(gp_points=3))
    with pytest.raises(ValueError, match="refit_every"):
        optim.Mads(b, 2, options=MadsOptions(refit_every=0))
    for chunk in (0, 2.5, True):
        with pytest.raises(ValueError, match=f"poll_chunk must be None or an integer >= 1, got {chunk!r}"):
            optim.Mads(b, 2, options=MadsOptions(poll_chunk=chunk))  # type: ignore[arg-type]
