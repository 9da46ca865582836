"""Protocol, driver, checkpoint/resume and bad-input tests for every method."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import optim
from optim import BatchEvaluation, Bounds, CmaOptions, KrigingOptions, MadsOptions

BOUNDS = Bounds(np.array([-2.0, -1.0, 0.0]), np.array([2.0, 3.0, 5.0]), names=("a", "b", "c"))
TARGET = np.array([0.7, 1.9, 1.2])


def sphere(x: np.ndarray) -> np.ndarray:
    return np.sum((x - TARGET) ** 2, axis=1)


# small, fast configurations that still exercise every state: MADS with its GP search and
# chunked polls, CMA with chunked generations and BIPOP restarts, EGO with a multi-round design
CONFIGS = {
    "mads": (3, MadsOptions(refit_every=2, n_candidates=128), 60),
    "cma": (3, CmaOptions(popsize_factor=2, restarts=3, restart_strategy="bipop", tolx=0.1), 120),
    "kriging": (3, KrigingOptions(n_initial=7, n_candidates=128, n_restarts=0), 19),
}


def make(method: str, seed: int = 3) -> optim.Optimizer:
    batch, options, _ = CONFIGS[method]
    return optim.make_optimizer(method, BOUNDS, batch, seed=seed, options=options)


def assert_same_result(a: optim.OptimResult, b: optim.OptimResult) -> None:
    np.testing.assert_array_equal(a.x_best, b.x_best)
    assert a.f_best == b.f_best
    assert a.evaluations == b.evaluations and a.batches == b.batches
    for field in ("x", "f", "feasible", "violation", "merit", "batch"):
        np.testing.assert_array_equal(getattr(a.history, field), getattr(b.history, field))
    assert a.stop_reason == b.stop_reason
    assert a.info == b.info


class Interrupt(Exception):
    pass


@pytest.mark.parametrize("method", sorted(CONFIGS))
def test_resume_after_interrupt_reaches_the_same_result(method: str, tmp_path: Path) -> None:
    budget = CONFIGS[method][2]
    reference = optim.run(make(method), sphere, budget)
    assert reference.evaluations > 0

    ckpt = tmp_path / "fit.npz"
    for stop_at in (1, 2, reference.batches // 2):
        ckpt.unlink(missing_ok=True)

        def callback(opt: optim.Optimizer, stop_at: int = stop_at) -> None:
            if opt.result.batches == stop_at:
                raise Interrupt

        with pytest.raises(Interrupt):
            optim.run(make(method), sphere, budget, callback=callback, checkpoint=ckpt)
        resumed = optim.run(make(method), sphere, budget, checkpoint=ckpt)
        assert_same_result(reference, resumed)
    assert [p.name for p in tmp_path.iterdir()] == ["fit.npz"]  # atomic write left no temp file


@pytest.mark.parametrize("method", sorted(CONFIGS))
def test_resume_after_a_crash_inside_the_objective(method: str, tmp_path: Path) -> None:
    budget = CONFIGS[method][2]
    reference = optim.run(make(method), sphere, budget)
    calls = {"n": 0}

    def flaky(x: np.ndarray) -> np.ndarray:
        calls["n"] += 1
        if calls["n"] == 3:
            raise Interrupt
        return sphere(x)

    ckpt = tmp_path / "fit.npz"
    with pytest.raises(Interrupt):
        optim.run(make(method), flaky, budget, checkpoint=ckpt)
    assert_same_result(reference, optim.run(make(method), flaky, budget, checkpoint=ckpt))


class _Payload:
    """A pickle that would create a file when unpickled."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty", "pickle"])
def test_a_damaged_or_foreign_checkpoint_is_refused_with_its_path_and_runs_no_code(damage: str, tmp_path: Path) -> None:
    import pickle

    ckpt = tmp_path / "fit.npz"
    optim.run(make("mads"), sphere, 9, checkpoint=ckpt)
    marker = tmp_path / "pwned"
    data = ckpt.read_bytes()
    ckpt.write_bytes({"truncated": data[: len(data) // 2], "garbage": b"not a checkpoint" * 10, "empty": b"",
                      "pickle": pickle.dumps(_Payload(marker))}[damage])
    with pytest.raises(optim.CheckpointError, match=r"fit\.npz.*(delete it|move it away)"):
        optim.run(make("mads"), sphere, 9, checkpoint=ckpt)
    assert not marker.exists(), "loading a checkpoint must never unpickle"


def test_checkpoint_of_another_configuration_is_refused(tmp_path: Path) -> None:
    ckpt = tmp_path / "fit.npz"
    optim.run(make("mads", seed=1), sphere, 9, checkpoint=ckpt)
    with pytest.raises(ValueError, match="different optimiser configuration"):
        optim.run(make("mads", seed=2), sphere, 9, checkpoint=ckpt)


def test_seed_changes_the_run() -> None:
    a = optim.run(make("kriging", seed=1), sphere, 12)
    b = optim.run(make("kriging", seed=2), sphere, 12)
    assert not np.array_equal(a.history.x, b.history.x)


@pytest.mark.parametrize("method", sorted(CONFIGS))
def test_failed_evaluations_are_infeasible_points(method: str) -> None:
    """NaN values, inf values and a False mask are infeasible points, never the best one."""

    def failing(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = sphere(x)
        f[x[:, 0] > 1.2] = np.nan
        f[x[:, 1] < 0.0] = np.inf
        return f, x[:, 2] < 4.5

    res = optim.run(make(method), failing, CONFIGS[method][2])
    h = res.history
    bad = (h.x[:, 0] > 1.2) | (h.x[:, 1] < 0.0) | (h.x[:, 2] >= 4.5)
    assert bad.any() and (~bad).any()
    np.testing.assert_array_equal(h.feasible, ~bad)
    assert np.all(np.isinf(h.merit[bad]))
    assert np.isfinite(res.f_best) and not bad[np.argmin(h.merit)]


def test_all_evaluations_failing_does_not_crash() -> None:
    res = optim.run(make("mads"), lambda x: np.full(len(x), np.nan), 30)
    assert np.isinf(res.f_best) and np.all(np.isnan(res.x_best)) and res.evaluations > 0


def test_violation_enters_the_merit_as_an_exact_penalty() -> None:
    """merit = f + penalty · h; min (x0-2)² + (x1-2)² s.t. x0, x1 <= 1 with penalty 10 (above the
    multipliers 2) has the constrained minimiser (1, 1), a sharp minimum of the merit."""
    bounds = Bounds(np.full(2, -3.0), np.full(2, 3.0))

    def constrained(x: np.ndarray) -> BatchEvaluation:
        f = np.sum((x - 2.0) ** 2, axis=1)
        h = np.sum(np.maximum(x - 1.0, 0.0), axis=1)
        return BatchEvaluation.coerce(f, len(x), violation=h)

    opt = optim.Mads(bounds, 6, seed=0, penalty=10.0, options=MadsOptions(kriging_search=False))
    res = optim.run(opt, constrained, 600)
    h = res.history
    np.testing.assert_array_equal(h.merit, h.f + 10.0 * h.violation)
    assert "min_poll_size" in res.stop_reason
    np.testing.assert_allclose(res.x_best, [1.0, 1.0], atol=1e-5)


def test_callback_returning_true_stops() -> None:
    seen: list[int] = []
    res = optim.run(make("mads"), sphere, 60, callback=lambda opt: seen.append(opt.evaluations) or opt.evaluations >= 6)
    assert "callback" in res.stop_reason and res.evaluations == seen[-1] >= 6 and max(seen[:-1]) < 6


def test_padded_objective_sees_exactly_num_envs_rows() -> None:
    seen: list[int] = []

    def env_step(x: np.ndarray) -> np.ndarray:
        seen.append(len(x))
        return sphere(x)

    res = optim.run(make("mads"), optim.padded(env_step, 5), 40)
    assert set(seen) == {5} and res.evaluations <= 40
    with pytest.raises(ValueError):
        optim.padded(env_step, 2)(np.zeros((3, 3)))


def test_unknown_method() -> None:
    with pytest.raises(ValueError, match="unknown method 'nelder'.*'mads'"):
        optim.make_optimizer("nelder", BOUNDS, 4)


@pytest.mark.parametrize("method", sorted(CONFIGS))
def test_budget_below_one_batch(method: str) -> None:
    with pytest.raises(ValueError, match=r"budget = 2 evaluations is below one batch of [36]"):
        optim.run(make(method), sphere, 2)


@pytest.mark.parametrize(
    ("lower", "upper", "message"),
    [
        ([0.0, 1.0], [1.0, 1.0], r"bounds of b: lower = 1.0 must be < upper = 1.0"),
        ([0.0, 2.0], [1.0, 1.0], r"bounds of b: lower = 2.0 must be < upper = 1.0"),
        ([0.0, np.nan], [1.0, 1.0], r"bounds of b must be finite"),
        ([0.0], [1.0, 1.0], r"equally long"),
    ],
)
def test_bad_bounds(lower: list[float], upper: list[float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Bounds(np.array(lower), np.array(upper), names=("a", "b") if len(lower) == 2 else None)


def test_bad_protocol_use() -> None:
    opt = make("mads")
    with pytest.raises(RuntimeError):
        opt.tell(np.zeros((1, 3)), [0.0])
    x = opt.ask()
    with pytest.raises(RuntimeError):
        opt.ask()
    with pytest.raises(ValueError, match="exactly the points"):
        opt.tell(x + 1.0, sphere(x))
    with pytest.raises(ValueError, match="values of f"):
        opt.tell(x, sphere(x)[:-1])
    with pytest.raises(ValueError, match="outside the bounds"):
        optim.Mads(BOUNDS, 3, x0=[0.0, 0.0, 9.0])
    with pytest.raises(ValueError, match="batch_size"):
        optim.Mads(BOUNDS, 0)
    with pytest.raises(TypeError, match="MadsOptions"):
        optim.make_optimizer("mads", BOUNDS, 3, options=CmaOptions())


def test_asks_are_physical_inside_bounds_and_batched() -> None:
    for method in CONFIGS:
        res = optim.run(make(method), sphere, CONFIGS[method][2])
        h = res.history
        assert np.all(h.x >= BOUNDS.lower) and np.all(h.x <= BOUNDS.upper)
        assert np.bincount(h.batch).max() <= 3


def test_progress_bar_can_be_forced(capsys: pytest.CaptureFixture[str]) -> None:
    optim.run(make("mads"), sphere, 9, progress=True)
    assert "Mads" in capsys.readouterr().err
    optim.run(make("mads"), sphere, 9)
    assert capsys.readouterr().err == ""


def test_checkpoint_write_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ckpt = tmp_path / "c.npz"
    opt = make("cma")
    optim.save_checkpoint(ckpt, opt, 12)
    before = ckpt.read_bytes()

    def broken_replace(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        optim.save_checkpoint(ckpt, opt, 12)
    assert ckpt.read_bytes() == before and len(list(tmp_path.iterdir())) == 1
