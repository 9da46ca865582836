"""Gradient-based fit: multi-start bounded least squares with Jacobians through the LO heart.

`fit_lm(patient)` minimises the env's objective (`optim.minimize`) written as a sum of squares,

    f(θ) = Σ_k r_k²,   r_k = sqrt(w_k / Σ w) (o_k − t_k) / t_k,   plus r_b = d_b / s_b per band b,

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
further starts, run one after another (not batched) until the total evaluation budget is used;
the best point over all starts is the result. One evaluation (a cold-start steady state at
rtol 1e-6 and its tangents) takes 0.1–0.4 s for one heart on 2 cores.

Limits (README, "Derivatives"): the residuals are only piecewise smooth. Valve events are
interpolated between steps, which puts O(h) kinks into them: at 250 steps per beat the trust
region stalls near 1 % mismatch, at the default 1000 near 0.1 %. And near the trained N preset
(Cat ≈ 2 ml/kPa) IVRT jumps by about a step, because P_lv − P_at grazes zero at mitral opening;
a start there may stall, and the other starts are what gets past it. Returned as the same `MinimizeResult` as the other
methods (method "lm"; one history row per evaluation, `batch` = the start's index).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence

import numpy as np
from scipy import optimize, stats

import lvenv
from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.metrics import OBS_NAMES
from lvenv.patients import Patient, builtin
from lvenv.plausibility import Band, distance, resolve
from lvenv.validation import integer
from optim.minimize import MinimizeResult, _result
from optim.protocol import History, OptimResult

__all__ = ["fit_lm", "FAILED_RESIDUAL"]

FAILED_RESIDUAL = 10.0


class _Problem:
    """Residuals and their Jacobian at unit-cube points, cached per point, with a record of each."""

    def __init__(self, patient: Patient, space: ParameterSpace, steps_per_beat: int, max_beats: int,
                 bands: tuple[Band, ...]) -> None:
        self.patient, self.space, self.bands = patient, space, bands
        self.targets = list(patient.targets)
        weights = np.array([patient.weight(k) for k in self.targets])
        weights = weights / weights.max()
        self.sqrt_w = np.sqrt(weights / weights.sum())
        self.t = np.array([patient.targets[k] for k in self.targets])
        self.metrics = tuple(dict.fromkeys([*self.targets, *(b.metric for b in bands), *OBS_NAMES]))
        self.settings = {"steps_per_beat": steps_per_beat, "max_beats": max_beats}
        self.records: list[dict[str, np.ndarray]] = []
        self.elapsed: list[float] = []  # s from the fit's start to the end of each evaluation
        self.clock = time.perf_counter()
        self.start = 0
        self._cache: tuple[bytes, np.ndarray, np.ndarray] | None = None

    def _evaluate(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = np.asarray(u, float).tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        x = self.space.clip(self.space.from_unit(u))
        heart = self.patient.heart.replace(**dict(zip(self.space.names, map(float, x))))
        jac = lvenv.jacobian(heart, wrt=self.space.names, metrics=self.metrics, **self.settings)
        ok = jac.status == "ok"
        n_res = len(self.targets) + len(self.bands)
        if ok:
            m = np.array([jac.metrics_at[k] for k in self.targets])
            rel = (m - self.t) / self.t
            d_metrics = jac.values * self.space.rate(x)[None, :]  # (m, k) per unit-cube coordinate
            rows = [self.sqrt_w[i] / self.t[i] * d_metrics[self.metrics.index(k)] for i, k in enumerate(self.targets)]
            band_res, band_rows = [], []
            for b in self.bands:
                value = jac.metrics_at[b.metric]
                side = -1.0 if value < b.low else 1.0 if value > b.high else 0.0  # d d_b / d o_b
                band_res.append(float(distance(b, value)) / b.scale)
                band_rows.append(side / b.scale * d_metrics[self.metrics.index(b.metric)])
            residual = np.concatenate([self.sqrt_w * rel, band_res])
            jacobian = np.vstack([*rows, *band_rows])
            obs = np.array([jac.metrics_at[k] for k in OBS_NAMES])
            mismatch = float(np.sum(self.sqrt_w**2 * np.abs(rel)) / np.sum(self.sqrt_w**2))
        else:
            residual, jacobian = np.full(n_res, FAILED_RESIDUAL), np.zeros((n_res, self.space.dimension))
            obs, mismatch = np.full(len(OBS_NAMES), np.nan), np.inf
        f = float(residual @ residual)
        self.records.append({"x": x[None], "f": np.array([f if ok else np.inf]), "feasible": np.array([ok]),
                             "mismatch": np.array([mismatch]), "obs": obs[None], "status": np.array([str(jac.status)]),
                             "start": np.array([self.start])})
        self.elapsed.append(time.perf_counter() - self.clock)
        self._cache = (key, residual, jacobian)
        return residual, jacobian

    def residual(self, u: np.ndarray) -> np.ndarray:
        return self._evaluate(u)[0]

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        return self._evaluate(u)[1]


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
    Jacobian); ``starts``: at most this many starts; ``plausibility``: the objective's bands
    (:func:`lvenv.plausibility.resolve`)."""
    patient = builtin(patient) if isinstance(patient, str) else patient
    budget, starts, seed = integer("budget", budget, 1), integer("starts", starts, 1), integer("seed", seed, 0)
    space = ParameterSpace.for_names(names, bounds)
    problem = _Problem(patient, space, steps_per_beat, max_beats, resolve(plausibility))
    own = space.to_unit(space.clip(np.array([float(patient.heart.get(n)) for n in space.names])))
    spread = stats.qmc.LatinHypercube(space.dimension, seed=seed).random(max(starts - 1, 1))
    points = np.vstack([own, spread])[:starts]
    t0 = problem.clock = time.perf_counter()
    reasons: dict[str, float] = {}
    for i, u0 in enumerate(points):
        left = budget - len(problem.records)
        if left < 2:
            break
        problem.start = i
        sol = optimize.least_squares(problem.residual, u0, jac=problem.jacobian, bounds=(0.0, 1.0), method="trf",
                                     x_scale="jac", max_nfev=left, xtol=1e-10, ftol=1e-12, gtol=1e-10)
        reasons[f"start {i}"] = float(sol.status)
    records = problem.records
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
        evaluations=len(records), batches=int(batch.max()) + 1 if len(batch) else 0, history=history,
        stop_reason=reasons, wall_time=time.perf_counter() - t0, info={"starts": float(len(reasons))},
    )
    kept = [{k: v for k, v in r.items() if k != "start"} for r in records]
    return _result("lm", patient, space, kept, problem.elapsed, res)

