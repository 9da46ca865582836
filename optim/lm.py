"""Gradient-based fit: multi-start bounded least squares with Jacobians through the LO heart.

`fit_lm(patient)` minimises the env's objective (`optim.minimize`) written as a sum of squares,

    f(θ) = Σ_k r_k²,   r_k = sqrt(w_k / Σ w) (o_k − t_k) / t_k,   plus r_b = d_b / s_b per band b,

the residuals of :func:`lvenv.env.core.residuals` (f is minus the env's reward),
with the plausibility bands b of :mod:`lvenv.plausibility` (``plausibility``, default on), over
the identification parameters (default τ2, Sa, R2, R3, C, Cat) in the unit cube of
`lvenv.identification.ParameterSpace` (log axes where marked), with `scipy.optimize.least_squares`
(trust-region reflective, bounds [0, 1], `x_scale="jac"`). Residuals are those of the steady
state of `lvenv.simulate` from a cold start (rtol 1e-6); their Jacobian comes from
`lvenv.jacobian` (forward mode through one beat and the implicit-function theorem) and the chain
rule through the unit-cube map. One steady state and its tangents serve both the residual and the
Jacobian of a point. A point whose steady state fails gets residuals of 10 (the trust region
then shrinks away from it) and is infeasible in the history.

Multi-start: the patient's own values, then a Latin hypercube (`scipy.stats.qmc`, seeded) of
further starts, each with an equal share of the evaluation budget; the best point over all
starts is the result. The starts run together: each start's solver runs in its own thread and
asks for its next point; once every running solver has asked, one batched `lvenv.jacobian`
call answers them all (:class:`_Batch`). Each start's path is the one it takes alone, since the
batch's members do not interact. One evaluation (a cold-start steady state at rtol 1e-6 and its
tangents) takes 0.1–0.4 s for one heart on 2 cores, and a batch of 4 about twice as long: 4 starts
on the built-in patients finish 2.1–2.4× sooner than one after another (README).

Limits (README, "Derivatives"): the residuals are only piecewise smooth. Valve events are
interpolated between steps, which puts O(h) kinks into them: at 250 steps per beat the trust
region stalled near 1 % mismatch, at the default 1000 near 0.1 % (measured while the valves'
yes/no switch in the integrator still made IVRT jump by up to a step near the trained N preset;
the valve weights of :func:`lvenv.model.jacobian` removed those jumps). A start may still stall
at a kink, and the other starts are what gets past it. Returned as the same `MinimizeResult` as the other
methods (method "lm"; one history row per evaluation, by start within each batched evaluation;
the env history's `batch` counts those, the optimiser history's is the start's index).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping, Sequence

import numpy as np
from scipy import optimize, stats

import lvenv
from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.metrics import OBS_NAMES
from lvenv.patients import Patient, builtin
from lvenv.env.core import residual_slopes, residuals
from lvenv.plausibility import Band, resolve
from lvenv.validation import integer
from optim.minimize import MinimizeResult, _result
from optim.protocol import History, OptimResult

__all__ = ["fit_lm", "FAILED_RESIDUAL"]

FAILED_RESIDUAL = 10.0


class _Problem:
    """Residuals and their Jacobians at unit-cube points, a batch at a time, with a record of each batch."""

    def __init__(self, patient: Patient, space: ParameterSpace, steps_per_beat: int, max_beats: int,
                 bands: tuple[Band, ...]) -> None:
        self.patient, self.space, self.bands = patient, space, bands
        self.targets = list(patient.targets)
        weights = np.array([patient.weight(k) for k in self.targets])
        self.weights = weights / weights.max()  # as the env scales them (lvenv.env.core.env_params)
        self.t = np.array([patient.targets[k] for k in self.targets])
        self.metrics = tuple(dict.fromkeys([*self.targets, *(b.metric for b in bands), *OBS_NAMES]))
        self.depends = [self.metrics.index(k) for k in (*self.targets, *(b.metric for b in bands))]  # each residual's metric
        self.settings = {"steps_per_beat": steps_per_beat, "max_beats": max_beats}
        self.records: list[dict[str, np.ndarray]] = []
        self.elapsed: list[float] = []  # s from the fit's start to the end of each evaluation
        self.clock = time.perf_counter()

    def evaluate(self, points: Sequence[np.ndarray], starts: Sequence[int]) -> list[tuple[np.ndarray, np.ndarray]]:
        """(residual, Jacobian per unit-cube coordinate) at each point, one batched steady state and
        tangent computation; ``starts``: the start each point belongs to, for the records."""
        xs = [self.space.clip(self.space.from_unit(u)) for u in points]
        hearts = [self.patient.heart.replace(**dict(zip(self.space.names, map(float, x)))) for x in xs]
        jac = lvenv.jacobian(hearts, wrt=self.space.names, metrics=self.metrics, **self.settings)
        at = {k: np.asarray(v, float) for k, v in jac.metrics_at.items()}  # (batch,) each
        r, mismatches = residuals(np.stack([at[k] for k in self.targets], axis=1), self.t, self.weights, at, self.bands)
        slopes = np.asarray(residual_slopes(self.t, self.weights, at, self.bands))
        r, mismatches = np.asarray(r), np.asarray(mismatches)
        n_res = len(self.targets) + len(self.bands)
        out, rows_f, rows_ok, rows_mismatch, rows_obs = [], [], [], [], []
        for b, x in enumerate(xs):
            ok = jac.status[b] == "ok"
            if ok:
                d_metrics = jac.values[b] * self.space.rate(x)[None, :]  # (m, k) per unit-cube coordinate
                residual, jacobian = r[b], slopes[b][:, None] * d_metrics[self.depends]
                obs = np.array([at[k][b] for k in OBS_NAMES])
                mismatch = float(mismatches[b])
            else:
                residual, jacobian = np.full(n_res, FAILED_RESIDUAL), np.zeros((n_res, self.space.dimension))
                obs, mismatch = np.full(len(OBS_NAMES), np.nan), np.inf
            out.append((residual, jacobian))
            rows_f.append(float(residual @ residual) if ok else np.inf)
            rows_ok.append(ok)
            rows_mismatch.append(mismatch)
            rows_obs.append(obs)
        self.records.append({"x": np.stack(xs), "f": np.array(rows_f), "feasible": np.array(rows_ok), "mismatch": np.array(rows_mismatch),
                             "obs": np.stack(rows_obs), "status": np.asarray(jac.status, str), "start": np.asarray(starts, np.int64)})
        self.elapsed.append(time.perf_counter() - self.clock)
        return out


class _Batch:
    """The starts' solvers, one thread each, ask for points; when every running solver has asked,
    one :meth:`_Problem.evaluate` call answers them all (ordered by start). Each solver's last
    point is cached, since `least_squares` asks for the Jacobian where it has just evaluated."""

    def __init__(self, problem: _Problem, running: int) -> None:
        self.problem, self.running = problem, running
        self.lock = threading.Condition()
        self.asked: dict[int, np.ndarray] = {}
        self.answers: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.last: dict[int, tuple[bytes, np.ndarray, np.ndarray]] = {}
        self.error: BaseException | None = None

    def _answer_if_all_asked(self) -> None:
        if not self.asked or len(self.asked) < self.running or self.error is not None:
            return
        starts = sorted(self.asked)
        try:
            results = self.problem.evaluate([self.asked[i] for i in starts], starts)
        except BaseException as exc:  # handed to every waiting solver, raised once by fit_lm
            self.error = exc
        else:
            self.answers.update(zip(starts, results))
        self.asked.clear()
        self.lock.notify_all()

    def evaluate(self, start: int, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = np.asarray(u, float).tobytes()
        if start in self.last and self.last[start][0] == key:
            return self.last[start][1], self.last[start][2]
        with self.lock:
            self.asked[start] = np.array(u, float)
            self._answer_if_all_asked()
            while start not in self.answers and self.error is None:
                self.lock.wait()
            if self.error is not None:
                raise self.error
            residual, jacobian = self.answers.pop(start)
        self.last[start] = (key, residual, jacobian)
        return residual, jacobian

    def finished(self) -> None:
        with self.lock:
            self.running -= 1
            self._answer_if_all_asked()


def fit_lm(
    patient: str | Patient,
    *,
    budget: int = 240,
    starts: int = 8,
    seed: int = 0,
    names: Sequence[str] = DEFAULT_ACTION_PARAMS,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    steps_per_beat: int = 1000,
    max_beats: int = 200,
    plausibility: bool | Sequence[Band] = True,
) -> MinimizeResult:
    """Fit ``names`` of ``patient`` (a built-in name or a Patient) by multi-start least squares
    (module docstring). ``budget``: steady-state evaluations over all starts (each with its
    Jacobian), an equal share each; ``starts``: at most this many starts (fewer where the budget
    gives less than 2 evaluations a start); ``plausibility``: the objective's bands
    (:func:`lvenv.plausibility.resolve`)."""
    patient = builtin(patient) if isinstance(patient, str) else patient
    budget, starts, seed = integer("budget", budget, 1), integer("starts", starts, 1), integer("seed", seed, 0)
    space = ParameterSpace.for_names(names, bounds)
    problem = _Problem(patient, space, steps_per_beat, max_beats, resolve(plausibility))
    own = space.to_unit(space.clip(np.array([float(patient.heart.get(n)) for n in space.names])))
    spread = stats.qmc.LatinHypercube(space.dimension, seed=seed).random(max(starts - 1, 1))
    points = np.vstack([own, spread])[:starts]
    t0 = problem.clock = time.perf_counter()
    points = points[: max(1, min(len(points), budget // 2))]  # at least 2 evaluations per start
    share = budget // len(points)
    together = _Batch(problem, len(points))
    reasons: dict[str, float] = {}
    failures: list[BaseException] = []

    def solve(i: int, u0: np.ndarray) -> None:
        try:
            sol = optimize.least_squares(lambda u: together.evaluate(i, u)[0], u0, jac=lambda u: together.evaluate(i, u)[1],
                                         bounds=(0.0, 1.0), method="trf", x_scale="jac", max_nfev=share, xtol=1e-10, ftol=1e-12, gtol=1e-10)
            reasons[f"start {i}"] = float(sol.status)
        except BaseException as exc:  # raised in the caller's thread below
            failures.append(exc)
        finally:
            together.finished()

    threads = [threading.Thread(target=solve, args=(i, u0), name=f"lm start {i}") for i, u0 in enumerate(points)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if failures:
        raise failures[0]
    reasons = dict(sorted(reasons.items(), key=lambda kv: int(kv[0].split()[1])))
    records = problem.records
    evaluations = sum(len(r["x"]) for r in records)
    x = np.concatenate([r["x"] for r in records])
    f = np.concatenate([r["f"] for r in records])
    feasible = np.concatenate([r["feasible"] for r in records])
    merit = np.where(feasible, f, np.inf)
    batch = np.concatenate([r["start"] for r in records]).astype(np.int64)
    history = History(space.to_unit(x), f, feasible, np.zeros(len(f)), merit, batch)
    best = int(np.argmin(merit)) if np.isfinite(merit).any() else None
    res = OptimResult(
        x_best=space.to_unit(x[best]) if best is not None else np.full(space.dimension, np.nan),
        f_best=float(f[best]) if best is not None else np.inf, merit_best=float(merit[best]) if best is not None else np.inf,
        evaluations=evaluations, batches=len(records), history=history,
        stop_reason=reasons, wall_time=time.perf_counter() - t0, info={"starts": float(len(reasons))},
    )
    kept = [{k: v for k, v in r.items() if k != "start"} for r in records]
    return _result("lm", patient, space, kept, problem.elapsed, res)

