"""Congruency training (DESIGN §3): fit the LO heart's maps to an oracle, and check fidelity.

`train(geometry, backend=...)` asks the oracle (`fe_oracle.run`, 3-D DOLFINx or the
multi-element LO models) for the passive inflation curve and the three Table 2 training beats,
all from the documented initial state, then

1. **Passive.** {α, β, a, b, c} with γ = 1 by Levenberg–Marquardt (`scipy.optimize.least_squares`,
   method "lm") on Σ_p (V_FE(p) − V_LO(p))² over the oracle's curve (`TRAINING_PASSIVE`: inflation
   0 → 4 kPa and deflation 0 → −0.75 kPa, which pins the compression branch V < V0 too).
2. **Active.** {μ1, μ2, γ} minimising

       C² = 1/3 Σ_i [ ∫(V_FE − V_LO)² dt / ∫V_FE² dt + ∫(P_FE − P_LO)² dt / ∫P_FE² dt ]_i

   over the training beats i = ①②③, by OrthoMADS with its kriging search step (`optim.mads`),
   restarted from random points while budget is left, then polished by bounded least squares
   on the residuals of C² (a sum of squares). Each optimiser batch of candidates × the three
   conditions is one batched `lvenv.simulate` call (one beat at `steps_per_beat`); the LO traces
   are interpolated linearly onto the oracle's time samples and the integrals taken by the
   trapezoidal rule there. `fit_maps` is this fit on any beats (`fit_active`: the training beats;
   `optim.studies.retune`: one unseen scenario's beat).
3. **Activation delay** (ours, DESIGN §3). If C stays at or above `TARGET_C` (1 %), the active
   fit is repeated with the LO activation delay d (`lvenv.coupling.calcium`) trained alongside
   {μ1, μ2, γ}, and kept if it lowers C; both C are reported.

**Multi-element LO hearts.** `lo_beats`, `run_congruency` and `fit_active` take an
``arrangement`` (`lvenv.params.Arrangement`): the training hearts then carry it
(``Heart.elements``) and `lvenv.simulate` runs that multi-element heart, for comparing candidate
low-order hearts against the same oracle runs (`scripts/candidate_study.py`). `wall_arrangement`
sets the cells' calcium onsets from the wall's own activation times, and `train_model` trains
the maps of a model of `lvenv.presets.LO_MODELS` from a single-cell record.

The result, `lvenv.trained.TrainedLO`, holds the nine parameters, C per training beat, the
passive fit's residual and the provenance (backend, mesh size, time step, the oracle runs' cache
keys and the code versions); it saves to and loads from JSON, and `TrainedLO.heart()` builds a
`Heart`.

`check_fidelity(heart)` runs the oracle at a heart's parameters in its closed loop, started from
the LO heart's steady state (the capacitor and atrial pressures at the start of a steady beat;
the wall at its own passive equilibrium with that atrial pressure), so that a few oracle beats
suffice, and compares the last beat with the LO steady state per target (`FIDELITY_TOLERANCE`).
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import importlib.metadata
import pathlib
import subprocess
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from scipy.optimize import least_squares

import fe_oracle
from fe_oracle import cache as oracle_cache
from fe_oracle.cases import Passive
from lvenv import coupling, lo_model, multielement, presets
from lvenv.geometry import Geometry, cavity_volume
from lvenv.metrics import METRICS
from lvenv.params import Arrangement, CellParams, Heart, LOParams, validate
from lvenv.simulation import simulate
from lvenv.status import is_usable
from lvenv.trained import TrainedLO
from lvenv.validation import InputError, choice, integer, real
from optim.mads import MadsOptions
from optim.methods import make_optimizer
from optim.protocol import Bounds, padded, run

__all__ = [
    "TRAINING_PASSIVE", "CONDITIONS", "PASSIVE_NAMES", "ACTIVE_NAMES", "MAP_NAMES", "ACTIVE_BOUNDS", "PASSIVE_FREEDOM", "TARGET_C",
    "FIDELITY_TOLERANCE", "passive_bounds", "map_refit", "difference_unit", "format_difference",
    "OracleData", "TrainedLO", "Fidelity", "residuals", "training_hearts", "congruency", "one_beat", "lo_beats", "run_congruency", "overall", "congruency_dict", "oracle_data", "passive_residual", "fit_passive", "fit_active", "fit_maps", "passes_validation",
    "train", "train_on", "check_fidelity",
]

TRAINING_PASSIVE = Passive(p_max=4.0, n_points=17, p_min=-0.75)
CONDITIONS = (1, 2, 3)
#: The passive maps: the parameters of the LO law's Ppass(V) (DESIGN §1), fitted to the oracle's
#: inflation (:func:`fit_passive`).
PASSIVE_NAMES = ("alpha", "beta", "a", "b", "c")
ACTIVE_NAMES = ("mu1", "mu2", "gamma")
#: The maps with the activation delay: what the delayed active fit, `train_model` and the refits
#: of the maps on other beats (`optim.studies.retune`, `check_fidelity`'s ``retune``) move.
MAP_NAMES = (*ACTIVE_NAMES, "delay")
#: Search box of the active parameters (the delay in s).
ACTIVE_BOUNDS = {"mu1": (0.02, 0.6), "mu2": (0.02, 1.5), "gamma": (0.2, 30.0), "delay": (0.0, 0.2)}
#: A refit of the passive maps {α, β, a, b, c} on beats searches each within its value fitted to
#: the inflation ÷ and × this factor (:func:`passive_bounds`).
PASSIVE_FREEDOM = 10.0
TARGET_C = 0.01
#: MADS for the active fit evaluates each iteration whole: a candidate costs one member of a
#: batched `lvenv.simulate` call, so fewer calls matter more than fewer candidates (the trained
#: presets and the figures in the README were made this way).
WHOLE_ITERATIONS = MadsOptions(poll_chunk=None, search_first=False)


# ---------------------------------------------------------------------------- data
@dataclasses.dataclass(frozen=True)
class OracleData:
    """The oracle runs congruency training fits: the passive curve and one beat per condition."""

    geometry: Geometry
    cell: CellParams
    passive: fe_oracle.OracleResult
    beats: dict[int, fe_oracle.OracleResult]
    backend: str
    options: dict[str, Any]

    @property
    def keys(self) -> dict[str, str]:
        """The oracle runs' cache keys by case ("passive", "1", "2", "3")."""
        return {"passive": self.passive.metadata["key"], **{str(k): r.metadata["key"] for k, r in self.beats.items()}}


def oracle_data(geometry: Geometry, backend: str = "dolfinx", *, cell: CellParams | None = None, progress: bool | None = None,
                **oracle_options: Any) -> OracleData:
    """Run (or read from the cache) the oracle's passive curve and the three training beats."""
    cell = CellParams() if cell is None else cell
    passive = fe_oracle.run(geometry, TRAINING_PASSIVE, backend, progress=progress, **oracle_options)
    # the training circulations themselves (the same records as cases 1–3, without a preset heart)
    beats = {k: fe_oracle.run(geometry, presets.training_circulation(k), backend, cell=cell, progress=progress, **oracle_options) for k in CONDITIONS}
    return OracleData(geometry, cell, passive, beats, backend, dict(oracle_options))


# ---------------------------------------------------------------------------- congruency
def residuals(oracle: Mapping[str, np.ndarray], t: np.ndarray, v: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Weighted pointwise differences whose squares sum to :func:`congruency`, per LO member.

    With trapezoidal weights ω_j on the oracle's samples t_j: r = [√ω_j (V_LO − V_FE)_j / ‖V_FE‖,
    √ω_j (P_LO − P_FE)_j / ‖P_FE‖], ‖f‖² = Σ_j ω_j f_j²; shape (members, 2 × samples).
    """
    return np.concatenate([trace_residuals(oracle, "V", t, v), trace_residuals(oracle, "P_lv", t, p)], axis=1)


def trace_residuals(oracle: Mapping[str, np.ndarray], name: str, t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """√ω_j (X_LO − X_FE)_j / ‖X_FE‖ of the oracle's trace ``name`` (X), per LO member: the LO
    traces ``values`` (members, samples) on the time axis ``t`` (s), interpolated linearly onto
    the oracle's samples t_j, with trapezoidal weights ω_j there; shape (members, samples)."""
    t_fe, x_fe = (np.asarray(oracle[k], float) for k in ("t", name))
    dt = np.diff(t_fe)
    omega = 0.5 * (np.concatenate([dt, [0.0]]) + np.concatenate([[0.0], dt]))
    x_lo = np.stack([np.interp(t_fe, t, row) for row in np.atleast_2d(values)])
    return np.sqrt(omega) * (x_lo - x_fe) / np.sqrt(np.sum(omega * x_fe**2))


def congruency(oracle: Mapping[str, np.ndarray], t: np.ndarray, v: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The bracket of C² for one beat, per LO member: ∫(V_FE − V_LO)²/∫V_FE² + ∫(P_FE − P_LO)²/∫P_FE².

    ``oracle``: traces ``t`` (s), ``V`` (ml), ``P_lv`` (kPa); ``t``, ``v``, ``p``: the LO traces,
    shape (members, samples) with one time axis (s). The LO traces are interpolated linearly onto
    the oracle's samples; the integrals use the trapezoidal rule there (:func:`residuals`).
    """
    return np.sum(residuals(oracle, t, v, p) ** 2, axis=1)


def training_hearts(geometry: Geometry, cell: CellParams, los: Sequence[LOParams], elements: Arrangement | None = None) -> list[Heart]:
    """One heart per (LO candidate, condition), candidate-major, of the LO heart model ``elements``."""
    base = [presets.training_circulation(k) for k in CONDITIONS]
    return [Heart(geometry=geometry, lo=lo, cell=cell, circulation=circ, elements=elements) for lo in los for circ in base]


def one_beat(hearts: Sequence[Heart], steps_per_beat: int = 1000,
             beats: int | None = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The last of ``beats`` beats of each of ``hearts`` from the training-protocol state (None:
    its steady beat), one batched simulation (`lvenv.simulate`, of the model the hearts carry):
    (status names (members,), t (s), V (ml), P_lv (kPa), P_ao (kPa), each (members, samples))."""
    sim = simulate(hearts, beats=beats, steps_per_beat=steps_per_beat)
    return np.asarray(sim.status), sim.traces.t, sim.traces.V, sim.traces.P_lv, sim.traces.P_ao


def lo_beats(data: OracleData, los: Sequence[LOParams], steps_per_beat: int = 1000,
             arrangement: Arrangement | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One LO beat per (candidate, condition) of :func:`training_hearts` (:func:`one_beat`; a
    multi-element heart with ``arrangement``): (usable (members,), t (s), V (ml), P_lv (kPa),
    each (members, samples))."""
    status, t, v, p, _ = one_beat(training_hearts(data.geometry, data.cell, los, arrangement), steps_per_beat)
    return is_usable(status), t, v, p


def _beat_c(oracles: Sequence[Mapping[str, np.ndarray]], usable: np.ndarray, t: np.ndarray, v: np.ndarray, p: np.ndarray) -> np.ndarray:
    """C per (candidate, beat) of candidate-major LO beats against ``oracles``; NaN where unusable."""
    return _per_beat(oracles, usable, lambda oracle, rows: congruency(oracle, t[rows[0]], v[rows], p[rows]))


def _beat_aortic(oracles: Sequence[Mapping[str, np.ndarray]], usable: np.ndarray, t: np.ndarray, p_ao: np.ndarray) -> np.ndarray:
    """The aortic pressure's misfit √(∫(P_ao,LO − P_ao,FE)² / ∫P_ao,FE²) per (candidate, beat) of
    candidate-major LO beats against ``oracles`` (:func:`trace_residuals`); NaN where unusable."""
    return _per_beat(oracles, usable, lambda oracle, rows: np.sum(trace_residuals(oracle, "P_ao", t[rows[0]], p_ao[rows]) ** 2, axis=1))


def _per_beat(oracles: Sequence[Mapping[str, np.ndarray]], usable: np.ndarray, squared: Callable) -> np.ndarray:
    """√``squared(oracle, rows)`` per (candidate, beat), ``rows`` the candidate-major members of
    that oracle's beat; NaN where unusable."""
    n = len(oracles)
    out = np.full((len(usable) // n, n), np.nan)
    for j, oracle in enumerate(oracles):
        rows = np.arange(j, len(usable), n)
        out[:, j] = np.where(usable[rows], np.sqrt(squared(oracle, rows)), np.nan)
    return out


def run_congruency(data: OracleData, los: Sequence[LOParams], steps_per_beat: int = 1000,
                   arrangement: Arrangement | None = None) -> np.ndarray:
    """C per (candidate, condition) of LO candidates against ``data``, shape (len(los), 3),
    one batched simulation (:func:`lo_beats`); NaN where the LO beat failed."""
    return _beat_c([data.beats[k].traces for k in CONDITIONS], *lo_beats(data, los, steps_per_beat, arrangement))


def overall(c_runs: np.ndarray) -> np.ndarray:
    """C = sqrt(mean over conditions of C_i²) (DESIGN §3)."""
    return np.sqrt(np.mean(np.asarray(c_runs) ** 2, axis=-1))


# ---------------------------------------------------------------------------- passive
def passive_residual(data: OracleData, lo: LOParams, arrangement: Arrangement | None = None) -> np.ndarray:
    """V_LO(p) − V_FE(p) (ml) on the oracle's quasi-static inflation curve p (kPa), of the LO
    passive map of ``lo`` (with γ = 1: the inflation never compresses the wall), or of the
    multi-element heart ``arrangement`` with those maps (:func:`lvenv.multielement.passive_volume`:
    cells in series of unequal weights inflate unlike one cell)."""
    pressure, volume = (np.asarray(data.passive.traces[k], float) for k in ("P_lv", "V"))
    lo, v0 = dataclasses.replace(lo, gamma=1.0), cavity_volume(data.geometry)
    lv = coupling.passive_volume(pressure, v0, lo) if arrangement is None else multielement.passive_volume(pressure, v0, lo, arrangement)
    return lv - volume


def fit_passive(data: OracleData, start: LOParams) -> tuple[LOParams, float]:
    """{α, β, a, b, c} with γ = 1 by Levenberg–Marquardt on the oracle's V(p); returns the LO
    parameters (``start`` otherwise) and the RMS volume residual (ml)."""
    base = dataclasses.replace(start, gamma=1.0)

    def with_values(x) -> LOParams:
        return dataclasses.replace(base, **dict(zip(PASSIVE_NAMES, map(float, x))))

    def residual(x) -> np.ndarray:
        return passive_residual(data, with_values(x))

    x0 = np.array([getattr(start, n) for n in PASSIVE_NAMES])
    fit = least_squares(residual, x0, method="lm", x_scale=np.abs(x0))
    lo = with_values(fit.x)
    if not fit.success or not np.all(np.isfinite(fit.fun)):
        raise RuntimeError(f"the passive fit did not converge ({fit.message})")
    return lo, float(np.sqrt(np.mean(fit.fun**2)))


def passive_bounds(lo: LOParams, factor: float = PASSIVE_FREEDOM) -> dict[str, tuple[float, float]]:
    """The boxes of a refit of the passive maps {α, β, a, b, c} on beats: each within its value
    in ``lo`` (fitted to the inflation) ÷ and × ``factor``, in the units of
    :class:`~lvenv.params.LOParams` (for ``bounds`` of :func:`fit_maps` and :func:`check_fidelity`)."""
    return {n: tuple(sorted((getattr(lo, n) / factor, getattr(lo, n) * factor))) for n in PASSIVE_NAMES}


def map_refit(lo: LOParams, passive: bool = False) -> tuple[tuple[str, ...], dict[str, tuple[float, float]] | None]:
    """The LO parameters a refit of ``lo``'s maps on beats moves, and the boxes of those outside
    :data:`ACTIVE_BOUNDS` (None: none): :data:`MAP_NAMES`, and with ``passive`` also
    :data:`PASSIVE_NAMES` in :func:`passive_bounds` of ``lo``."""
    return ((*MAP_NAMES, *PASSIVE_NAMES), passive_bounds(lo)) if passive else (MAP_NAMES, None)


# ---------------------------------------------------------------------------- active
def fit_active(data: OracleData, start: LOParams, names: Sequence[str] = ACTIVE_NAMES, *, budget: int = 960, batch: int = 16,
               seed: int = 0, steps_per_beat: int = 1000, progress: bool | None = None,
               arrangement: Arrangement | None = None, bounds: Mapping[str, tuple[float, float]] | None = None) -> tuple[LOParams, np.ndarray]:
    """Minimise C² over ``names`` (⊆ {μ1, μ2, γ, delay} and the parameters ``bounds`` boxes) on the
    training beats (:func:`fit_maps`), from ``start``; returns the best LO parameters and C per
    training beat. ``arrangement``: train a multi-element LO heart (:func:`lo_beats`). ``bounds``:
    search boxes of further LO parameters, or other boxes for these, name → (lower, upper) in the
    units of :class:`~lvenv.params.LOParams` (default :data:`ACTIVE_BOUNDS`)."""
    return fit_maps(lambda lo: training_hearts(data.geometry, data.cell, [lo], arrangement), [data.beats[k].traces for k in CONDITIONS],
                    start, names, budget=budget, batch=batch, seed=seed, steps_per_beat=steps_per_beat, progress=progress, bounds=bounds)


def fit_maps(hearts: Callable[[LOParams], Sequence[Heart]], oracles: Sequence[Mapping[str, np.ndarray]], start: LOParams,
             names: Sequence[str] = ACTIVE_NAMES, *, budget: int = 960, batch: int = 16, seed: int = 0, steps_per_beat: int = 1000,
             progress: bool | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
             run_beats: int | None = 1, aortic_weight: float = 0.0) -> tuple[LOParams, np.ndarray]:
    """Minimise C² = mean over beats of C_i² over the LO parameters ``names`` by OrthoMADS with
    kriging search, from ``start`` (clipped into the boxes), then polish by bounded least squares
    on the residuals of C²; returns the best LO parameters and C per beat. ``hearts(lo)``: the LO
    hearts of one candidate, one per beat of ``oracles`` (traces ``t`` s, ``V`` ml, ``P_lv`` kPa);
    each batch of candidates is one `lvenv.simulate` call (:func:`one_beat`: the last of
    ``run_beats`` beats, None: the steady beat, as the oracle's beats were run). ``bounds``: as in
    :func:`fit_active`. :func:`fit_active` fits the training beats; `optim.studies.retune` one
    unseen scenario's beat; :func:`check_fidelity` the beat of a heart's closed loop.

    ``aortic_weight`` w ≥ 0: minimise C² + w A² instead, A² the mean over beats of the aortic
    pressure's ∫(P_ao,LO − P_ao,FE)² / ∫P_ao,FE² (:func:`trace_residuals`; each oracle's traces need
    ``P_ao``, kPa, as a closed-loop beat has). C² weighs only the LV's volume and pressure, which
    can leave the ejection's shape, and so the aortic pulse pressure, off (docs/congruency.md).
    The returned C per beat is C either way.

    A candidate whose hearts fail `lvenv.params.validate` (a box of the passive maps can hold
    maps with a non-monotone Ppass) counts as a failed beat: when `lvenv.simulate` refuses a
    batch, its candidates are checked one by one and ``start``'s hearts run in place of those
    refused, so the batch keeps its size.

    C² can have several local minima (seen against the series multi-element model). When a MADS
    run converges (poll size below its minimum) before the budget is spent, MADS restarts from a
    uniformly drawn point of the box with the budget left, and the best point over all runs wins.
    """
    names = tuple(names)
    aortic_weight = real("aortic_weight", aortic_weight, 0.0)
    if aortic_weight and not all("P_ao" in o and np.all(np.isfinite(o["P_ao"])) for o in oracles):
        raise InputError(f"aortic_weight = {aortic_weight:g} weighs the aortic pressure in: every oracle beat needs a finite P_ao trace "
                         "(a closed-loop beat), and one has none")
    box = {**ACTIVE_BOUNDS, **(bounds or {})}
    lower = np.array([box[n][0] for n in names])
    upper = np.array([box[n][1] for n in names])
    x0 = np.clip([getattr(start, n) for n in names], lower, upper)

    def candidates(x: np.ndarray) -> list[LOParams]:
        return [dataclasses.replace(start, **dict(zip(names, map(float, row)))) for row in x]

    def beats(los: Sequence[LOParams]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        built = [hearts(lo) for lo in los]
        valid = np.ones(len(los), bool)
        try:
            status, t, v, p, p_ao = one_beat([h for members in built for h in members], steps_per_beat, run_beats)
        except InputError:  # `lvenv.simulate` refuses the whole batch: find the candidates it refuses
            valid = np.array([all(map(passes_validation, members)) for members in built])
            fallback = hearts(start)
            status, t, v, p, p_ao = one_beat([h for members, ok in zip(built, valid) for h in (members if ok else fallback)], steps_per_beat,
                                             run_beats)
        return is_usable(status) & np.repeat(valid, len(built[0])), t, v, p, p_ao

    def objective(x: np.ndarray) -> np.ndarray:
        usable, t, v, p, p_ao = beats(candidates(x))
        f = overall(_beat_c(oracles, usable, t, v, p)) ** 2
        if aortic_weight:
            f = f + aortic_weight * np.mean(_beat_aortic(oracles, usable, t, p_ao) ** 2, axis=-1)
        return np.log10(f + 1e-14)  # the kriging search models log C² far better than C²

    rng = np.random.default_rng(seed)
    best_x, best_f, left = x0, np.inf, budget
    while left >= batch:
        opt = make_optimizer("mads", Bounds(lower, upper, names), batch, seed=int(rng.integers(2**31 - 1)), x0=x0, options=WHOLE_ITERATIONS)
        res = run(opt, padded(objective, batch), left, progress=progress)
        if res.merit_best < best_f:
            best_x, best_f = res.x_best, res.merit_best
        left -= res.evaluations
        x0 = lower + rng.random(len(names)) * (upper - lower)
    lo = _polish(beats, oracles, candidates(best_x[None])[0], names, lower, upper, aortic_weight)
    return lo, _beat_c(oracles, *beats([lo])[:4])[0]


def passes_validation(heart: Heart) -> bool:
    """Whether ``heart`` passes `lvenv.params.validate`."""
    try:
        validate(heart)
    except ValueError:
        return False
    return True


def _polish(beats: Callable, oracles: Sequence[Mapping[str, np.ndarray]], lo: LOParams, names: tuple[str, ...], lower: np.ndarray,
            upper: np.ndarray, aortic_weight: float = 0.0) -> LOParams:
    """Refine MADS's best point by bounded least squares on the residuals of C² (+ w A² with
    ``aortic_weight`` w, :func:`fit_maps`; trust-region reflective, `scipy.optimize.least_squares`);
    kept only if that objective falls."""

    def with_values(x) -> LOParams:
        return dataclasses.replace(lo, **dict(zip(names, map(float, x))))

    def fun(x) -> np.ndarray:
        usable, t, v, p, p_ao = beats([with_values(x)])
        if not np.all(usable):
            return np.full(sum((3 if aortic_weight else 2) * len(o["t"]) for o in oracles), 1e3)
        parts = [residuals(o, t[j], v[j], p[j])[0] for j, o in enumerate(oracles)]
        if aortic_weight:
            parts += [np.sqrt(aortic_weight) * trace_residuals(o, "P_ao", t[j], p_ao[j])[0] for j, o in enumerate(oracles)]
        return np.concatenate(parts) / np.sqrt(len(oracles))

    x0 = np.clip([getattr(lo, n) for n in names], lower, upper)
    fit = least_squares(fun, x0, bounds=(lower, upper), x_scale=upper - lower, diff_step=1e-6, max_nfev=50 * len(names))
    return with_values(fit.x) if 2.0 * fit.cost < np.sum(fun(x0) ** 2) else lo


def _code_version(backend: str) -> dict[str, str | None]:
    root = pathlib.Path(__file__).resolve().parent.parent
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"lvenv": importlib.metadata.version("lvenv"), "git": commit, "oracle": oracle_cache.code_version(backend)}


def congruency_dict(c_runs: np.ndarray) -> dict[str, float]:
    """C per training condition (keys "1", "2", "3") and overall ("C"), as plain floats."""
    return {**{str(k): float(c) for k, c in zip(CONDITIONS, c_runs)}, "C": float(overall(c_runs))}


def train(
    geometry: Geometry,
    backend: str = "dolfinx",
    *,
    cell: CellParams | None = None,
    start: LOParams | None = None,
    delay: str = "auto",
    budget: int = 960,
    batch: int = 16,
    seed: int = 0,
    steps_per_beat: int = 1000,
    progress: bool | None = None,
    **oracle_options: Any,
) -> TrainedLO:
    """Congruency-train the LO maps of ``geometry`` against ``backend`` (module docstring).

    ``start``: initial LO parameters (default: the paper's Table 3 values of the preset geometry,
    else its N values). ``delay``: "auto" (train the activation delay only if C ≥ 1 % without
    it), "never" or "always". ``budget``: MADS evaluations per active fit (``batch`` candidates,
    × 3 conditions, per simulate call). ``oracle_options`` go to :func:`fe_oracle.run` (e.g.
    ``mesh_size``, ``dt``, ``arrangement``, ``lo``, ``cache_dir``).
    """
    choice("delay", delay, ("auto", "never", "always"))
    budget, batch, seed = integer("budget", budget, 1), integer("batch", batch, 1), integer("seed", seed, 0)
    data = oracle_data(geometry, backend, cell=cell, progress=progress, **oracle_options)
    return train_on(data, start=start, delay=delay, budget=budget, batch=batch, seed=seed, steps_per_beat=steps_per_beat, progress=progress)


def train_on(data: OracleData, *, start: LOParams | None = None, delay: str = "auto", budget: int = 960, batch: int = 16, seed: int = 0,
             steps_per_beat: int = 1000, progress: bool | None = None) -> TrainedLO:
    """Congruency-train against oracle runs already at hand (:func:`train` without the oracle
    calls), e.g. the FE traces of a campaign's dataset (:mod:`optim.campaign`)."""
    choice("delay", delay, ("auto", "never", "always"))
    budget, batch, seed = integer("budget", budget, 1), integer("batch", batch, 1), integer("seed", seed, 0)
    if start is None:
        start = {presets.HF_UNLOADED: presets.HF_LO}.get(data.geometry, presets.N_LO)
    start = dataclasses.replace(start, delay=0.0)
    lo_passive, rmse = fit_passive(data, start)
    fit = functools.partial(fit_active, data, budget=budget, batch=batch, seed=seed, steps_per_beat=steps_per_beat, progress=progress)
    lo, c_runs = fit(dataclasses.replace(lo_passive, gamma=start.gamma)) if delay != "always" else (None, None)
    without = None
    if delay == "always" or (delay == "auto" and not overall(c_runs) < TARGET_C):
        base = lo if lo is not None else dataclasses.replace(lo_passive, gamma=start.gamma)
        lo_s, c_s = fit(dataclasses.replace(base, delay=0.04), MAP_NAMES)
        without = None if c_runs is None else congruency_dict(c_runs)
        if c_runs is None or overall(c_s) < overall(c_runs):
            lo, c_runs = lo_s, c_s
    provenance = _provenance(data, budget=budget, batch=batch, seed=seed, steps_per_beat=steps_per_beat)
    return TrainedLO(data.geometry, lo, data.cell, congruency_dict(c_runs), without, rmse, provenance)


def _provenance(data: OracleData, **training: Any) -> dict[str, Any]:
    """Where a record trained on ``data`` came from: the oracle's backend, mesh size, time step,
    cache keys and options, the code versions, the training's settings and the time."""
    mesh = None if data.backend != "dolfinx" else float(data.options.get("mesh_size", fe_oracle.DEFAULT_MESH_SIZE))
    return {
        "backend": data.backend, "mesh_size_mm": mesh, "dt_s": data.beats[CONDITIONS[0]].metadata.get("dt_s"),
        "oracle_keys": data.keys, "oracle_options": {k: v for k, v in data.options.items() if k != "cache_dir" and isinstance(v, (int, float, str))},
        "code_version": _code_version(data.backend), **training,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


@functools.cache
def wall_onsets(geometry: Geometry, mesh_size_mm: float, cells: int) -> tuple[float, ...]:
    """The calcium onsets (s, relative to the LO delay) of ``cells`` cells: the activation times
    of ``geometry``'s oracle wall at :func:`lvenv.presets.onset_quantiles`, less their median
    (`fe_oracle.activation.activation_quantiles`: meshing and an eikonal solve, about a second;
    computed once per wall and cell count)."""
    from fe_oracle.activation import activation_quantiles

    q = activation_quantiles(geometry, mesh_size_mm, presets.onset_quantiles(cells))
    return tuple(float(x) for x in q - np.median(q))


def wall_arrangement(kind: str, cells: int, spread: tuple[float, float], data: OracleData) -> Arrangement:
    """A multi-element arrangement whose cells start at the activation times of ``data``'s wall
    (:func:`wall_onsets` at the mesh of its training beats)."""
    return Arrangement(kind, cells, spread=spread, onsets=wall_onsets(data.geometry, data.beats[CONDITIONS[1]].metadata["mesh_size_mm"], cells))


def train_model(data: OracleData, single: TrainedLO, model: str, *, budget: int = 480, batch: int = 16, seed: int = 0,
                steps_per_beat: int = 1000, progress: bool | None = None) -> TrainedLO:
    """The maps of the LO heart model ``model`` (:data:`lvenv.presets.LO_MODELS`) of ``data``'s
    wall, trained from the single cell's record ``single`` of the same wall: its cells' onsets
    from the wall (:func:`wall_arrangement`), then {μ1, μ2, γ, delay} refitted by
    :func:`fit_active` (MADS ``budget``) from ``single``'s values; the passive maps, and so the
    passive fit's residual, stay ``single``'s (the models' passive curves are equal for equal
    volume shares, w = 1)."""
    choice("model", model, presets.MULTI_ELEMENT_MODELS)
    if single.elements is not None or single.geometry != data.geometry:
        raise InputError(f"train_model starts from a single-cell record of the same wall (got elements = {single.elements!r}, "
                         f"geometry {single.geometry} for data of {data.geometry})")
    arrangement = wall_arrangement(*presets.LO_MODELS[model], data)
    lo, c_runs = fit_active(data, single.lo, MAP_NAMES, budget=budget, batch=batch, seed=seed, steps_per_beat=steps_per_beat,
                            progress=progress, arrangement=arrangement)
    provenance = _provenance(data, budget=budget, batch=batch, seed=seed, steps_per_beat=steps_per_beat, model=model,
                             start=dataclasses.asdict(single.lo), onset_quantiles=list(presets.onset_quantiles(arrangement.n_elements)))
    return TrainedLO(data.geometry, lo, data.cell, congruency_dict(c_runs), None, single.passive_rmse_ml, provenance, elements=arrangement)


#: Fidelity targets and their tolerance: (kind, bound) with kind "abs" (internal units) or "rel".
FIDELITY_TOLERANCE = {
    "EF": ("abs", 0.02), "IVCT": ("abs", 0.010), "ET": ("abs", 0.010), "IVRT": ("abs", 0.010),
    "P_ao_sys": ("rel", 0.03), "P_ao_dia": ("rel", 0.03), "P_ao_pulse": ("rel", 0.03), "P_ao_mean": ("rel", 0.03),
}


def difference_unit(name: str) -> str:
    """The unit in which FE − LO of the fidelity target ``name`` is shown: % for the pressures
    (relative to the oracle), points for EF, the display unit (ms) for the phase durations."""
    return "%" if FIDELITY_TOLERANCE[name][0] == "rel" else "points" if name == "EF" else METRICS[name].display_units


def format_difference(name: str, diff: float, unit: bool = False) -> str:
    """FE − LO of the fidelity target ``name`` (a :class:`Fidelity` row's difference, internal
    units), signed, in :func:`difference_unit`; followed by that unit if ``unit``."""
    text = f"{100 * diff:+.2f}" if difference_unit(name) in ("%", "points") else f"{METRICS[name].to_display(diff):+.1f}"
    return f"{text} {difference_unit(name)}" if unit else text


@dataclasses.dataclass(frozen=True)
class Fidelity:
    """LO against oracle at one heart. ``rows[name] = (lo, oracle, difference)`` in internal units
    (difference = oracle − LO; relative to the oracle for pressures, see :data:`FIDELITY_TOLERANCE`);
    ``within[name]``: inside the tolerance; ``C``: congruency of the last beat's V and P traces.
    ``retuned`` (None unless :func:`check_fidelity` was asked to retune): the same comparison
    with the LO parameters ``retune`` refitted on the oracle's last beat: ``lo`` (name → value),
    ``rows``, ``within``, ``C``, ``lo_status`` and the refit's ``aortic_weight``."""

    rows: dict[str, tuple[float, float, float]]
    within: dict[str, bool]
    C: float
    oracle_valid: bool
    lo_status: str
    provenance: dict[str, Any]
    retuned: dict[str, Any] | None = None

    @property
    def ok(self) -> bool:
        return self.oracle_valid and all(self.within.values())

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self) | {"ok": self.ok}


def _compare(lo_run, fe: Mapping[str, float], traces: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """An LO steady state ``lo_run`` against the oracle's beat metrics ``fe`` and its last beat's
    ``traces``: rows, within and C as :class:`Fidelity` holds them."""
    rows, within = {}, {}
    for name, (kind, bound) in FIDELITY_TOLERANCE.items():
        lo_value, fe_value = float(lo_run.metrics[name]), float(fe[name])
        diff = fe_value - lo_value if kind == "abs" else (fe_value - lo_value) / fe_value
        rows[name] = (lo_value, fe_value, diff)
        within[name] = bool(abs(diff) <= bound)
    c = float(np.sqrt(congruency(traces, lo_run.traces.t, lo_run.traces.V, lo_run.traces.P_lv)[0]))
    return {"rows": rows, "within": within, "C": c}


def check_fidelity(heart: Heart, backend: str = "dolfinx", *, beats: int = 2, steps_per_beat: int = 1000,
                   progress: bool | None = None, retune: Sequence[str] = (), retune_budget: int = 480,
                   bounds: Mapping[str, tuple[float, float]] | None = None, aortic_weight: float = 0.0,
                   **oracle_options: Any) -> Fidelity:
    """Run the oracle at ``heart`` (closed loop, from the LO steady state, ``beats`` beats) and
    compare its last beat with the LO steady state (module docstring).

    ``retune``: LO parameters (⊆ {μ1, μ2, γ, delay} and those ``bounds`` boxes, e.g. the passive
    maps in :func:`passive_bounds`) to refit on that last beat by :func:`fit_maps` (MADS
    ``retune_budget`` evaluations from the heart's own values, then least squares), and the
    comparison repeated with them (``Fidelity.retuned``): how close the LO model can come to the
    oracle at this heart at all, against how close its trained maps come. ``aortic_weight``: the
    refit weighs the aortic pressure trace in (:func:`fit_maps`; needs ``retune``)."""
    beats = integer("beats", beats, 1)
    retune = tuple(retune)
    aortic_weight = real("aortic_weight", aortic_weight, 0.0)
    if aortic_weight and not retune:
        raise InputError(f"aortic_weight = {aortic_weight:g} weighs the aortic pressure into the refit of the maps: name the maps in retune")
    allowed = [*MAP_NAMES, *(n for n in bounds or {} if n not in MAP_NAMES)]
    unknown = sorted(set(retune) - set(allowed))
    if unknown:
        raise InputError(f"retune = {unknown}: only the active maps, the delay and the parameters `bounds` boxes can be refitted ({allowed})")
    lo_run = simulate(heart, steps_per_beat=steps_per_beat)
    if not is_usable(lo_run.status):
        raise InputError(f"the LO heart has no usable steady state (status {lo_run.status!r}); nothing to check")
    y = lo_run.final_state
    _, i_pc, i_pat = lo_model.circulation_index(heart)
    circ = dataclasses.replace(heart.circulation, Pc0=float(y[i_pc]), Pat=float(y[i_pat]))
    result = fe_oracle.run(heart.geometry, circ, backend, cell=heart.cell, beats=beats, progress=progress, **oracle_options)
    fe = fe_oracle.beat_metrics(result)
    period = float(result.metadata["period_s"])
    last = result.traces["t"] >= result.traces["t"][-1] - period - 1e-9
    traces = {k: result.traces[k][last] for k in ("V", "P_lv", "P_ao")} | {"t": result.traces["t"][last] - result.traces["t"][last][0]}
    frozen = _compare(lo_run, fe, traces)
    retuned = None
    if retune:
        lo, _ = fit_maps(lambda lo: [dataclasses.replace(heart, lo=lo)], [traces], heart.lo, retune, budget=retune_budget,
                         steps_per_beat=steps_per_beat, progress=progress, bounds=bounds, run_beats=None, aortic_weight=aortic_weight)
        rerun = simulate(dataclasses.replace(heart, lo=lo), steps_per_beat=steps_per_beat)
        retuned = {"lo": {n: float(getattr(lo, n)) for n in retune}, "lo_status": str(rerun.status), "aortic_weight": aortic_weight,
                   **_compare(rerun, fe, traces)}
    provenance = {"backend": backend, "oracle_key": result.metadata["key"], "beats": beats, "circulation": dataclasses.asdict(circ),
                  "oracle_options": {k: v for k, v in oracle_options.items() if isinstance(v, (int, float, str))}}
    return Fidelity(frozen["rows"], frozen["within"], frozen["C"], bool(fe["valid"]), str(lo_run.status), provenance, retuned)
