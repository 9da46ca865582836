"""Progressive barrier (Audet & Dennis 2009): classification, h_max, and constrained MADS."""

from __future__ import annotations

import numpy as np
import pytest

import optim
from optim import BatchEvaluation, Bounds, MadsOptions
from optim.barrier import BarrierPoint, ProgressiveBarrier


def point(f: float, h: float) -> BarrierPoint:
    return BarrierPoint(np.array([f, h]), f, h)


def test_iteration_status_and_threshold_updates() -> None:
    pb = ProgressiveBarrier(rho=0.1)
    pb.start_iteration()
    assert pb.insert(point(5.0, 2.0)) == "improving"  # first infeasible point: no incumbent yet
    assert pb.insert(point(3.0, 4.0)) == "improving"
    assert pb.end_iteration() == "improving"
    assert pb.h_max == 4.0 and pb.infeasible is not None and pb.infeasible.f == 3.0

    pb.start_iteration()  # x^I = (f 3, h 4)
    assert pb.insert(point(9.0, 5.0)) == "unsuccessful"  # h > h_max: rejected
    assert pb.insert(point(4.0, 3.0)) == "improving"  # less violation, worse f
    assert pb.end_iteration() == "improving"
    assert pb.h_max == 3.0  # largest filter h below h(x^I) = 4
    assert [(q.f, q.h) for q in pb.filter] == [(5.0, 2.0), (4.0, 3.0)]
    assert pb.infeasible is not None and (pb.infeasible.f, pb.infeasible.h) == (4.0, 3.0)

    pb.start_iteration()
    assert pb.insert(point(3.5, 2.5)) == "dominating"  # dominates x^I = (4, 3)
    assert pb.insert(point(1.0, 0.0)) == "dominating"  # first feasible point
    assert pb.end_iteration() == "dominating" and pb.h_max == 3.0
    assert pb.feasible is not None and pb.feasible.f == 1.0

    pb.start_iteration()
    assert pb.insert(point(2.0, 0.0)) == "unsuccessful"
    assert pb.end_iteration() == "unsuccessful" and pb.h_max == 2.5  # h(x^I) at the start
    assert [c.f for c in pb.poll_centres()] == [1.0, 3.5]  # f(x^I) is not below f(x^F) - rho


def test_failed_points_are_rejected() -> None:
    pb = ProgressiveBarrier()
    pb.start_iteration()
    assert pb.insert(point(np.inf, 0.0)) == "unsuccessful"
    assert pb.insert(BarrierPoint(np.zeros(2), 1.0, np.inf)) == "unsuccessful"
    assert pb.end_iteration() == "unsuccessful" and pb.poll_centres() == []


BOUNDS = Bounds(np.full(2, -3.0), np.full(2, 3.0))


def kink(x: np.ndarray) -> BatchEvaluation:
    """min (x0 - 2)² + x1² s.t. x0 <= 1: the solution (1, 0) sits on the constraint."""
    f = (x[:, 0] - 2.0) ** 2 + x[:, 1] ** 2
    return BatchEvaluation.coerce(f, len(x), violation=np.maximum(x[:, 0] - 1.0, 0.0))


def disc(x: np.ndarray) -> BatchEvaluation:
    """min x0 + x1 s.t. x0² + x1² <= 1: the solution is -(1, 1)/√2."""
    h = np.maximum(np.sum(x**2, axis=1) - 1.0, 0.0)
    return BatchEvaluation.coerce(x[:, 0] + x[:, 1], len(x), violation=h)


@pytest.mark.parametrize(("problem", "solution"), [(kink, [1.0, 0.0]), (disc, [-(2**-0.5), -(2**-0.5)])])
def test_progressive_barrier_solves_constrained_problems(problem, solution) -> None:  # type: ignore[no-untyped-def]
    # a spread first batch, so that the barrier starts with infeasible points on both problems
    options = MadsOptions(constraint="progressive_barrier", kriging_search=False, min_poll_size=1e-7, initial_design=True)
    opt = optim.Mads(BOUNDS, 6, seed=0, options=options)
    h_max: list[float] = []
    res = optim.run(opt, problem, 1500, callback=lambda o: h_max.append(o.barrier.h_max) and None)
    np.testing.assert_allclose(res.x_best, solution, atol=3e-3)
    i = int(np.argmin(res.history.merit))
    assert res.history.violation[i] == 0.0  # the reported point is feasible
    assert np.all(np.isinf(res.history.merit[res.history.violation > 0]))
    finite = np.array(h_max)[np.isfinite(h_max)]
    assert len(finite) and np.all(np.diff(finite) <= 0)  # the barrier only tightens
    assert res.history.violation.max() > 0  # it did go through infeasible points


def test_barrier_reduces_to_plain_mads_without_violations() -> None:
    """Without violations the barrier is plain MADS evaluating each iteration whole (it does
    not split polls into chunks: with them it stopped short of both problems above)."""

    def sphere(x: np.ndarray) -> np.ndarray:
        return np.sum((x - 0.4) ** 2, axis=1)

    whole = {"n_candidates": 64, "poll_chunk": None, "search_first": False}
    runs = [
        optim.run(optim.Mads(BOUNDS, 6, seed=2, options=MadsOptions(constraint=c, **whole)), sphere, 120)  # type: ignore[arg-type]
        for c in ("penalty", "progressive_barrier")
    ]
    np.testing.assert_array_equal(runs[0].history.x, runs[1].history.x)
    barrier = optim.run(optim.Mads(BOUNDS, 6, seed=2, options=MadsOptions(constraint="progressive_barrier", n_candidates=64)), sphere, 120)
    np.testing.assert_array_equal(barrier.history.x, runs[1].history.x)  # the chunk options do not apply


def test_unknown_constraint_mode() -> None:
    with pytest.raises(ValueError, match="unknown constraint"):
        optim.Mads(BOUNDS, 2, options=MadsOptions(constraint="filter"))  # type: ignore[arg-type]


def test_barrier_run_resumes_exactly(tmp_path) -> None:  # type: ignore[no-untyped-def]
    def make() -> optim.Mads:
        options = MadsOptions(constraint="progressive_barrier", n_candidates=64, refit_every=2)
        return optim.Mads(BOUNDS, 6, seed=4, options=options)

    reference = optim.run(make(), disc, 90)

    def interrupt(o: optim.Optimizer) -> None:
        if o.evaluations >= 40:
            raise KeyboardInterrupt

    ckpt = tmp_path / "pb.pkl"
    with pytest.raises(KeyboardInterrupt):
        optim.run(make(), disc, 90, callback=interrupt, checkpoint=ckpt)
    resumed = optim.run(make(), disc, 90, checkpoint=ckpt)
    np.testing.assert_array_equal(reference.history.x, resumed.history.x)
    assert reference.info == resumed.info and reference.f_best == resumed.f_best
