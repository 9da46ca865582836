"""What a patient's measurements pin down: the sensitivity at a fit and profile likelihoods.

Measurement model (ours, illustrative; replace it with your laboratory's values): each target
k is measured with an independent Gaussian error of standard deviation σ_k (:data:`NOISE`,
internal units), so a parameter set's misfit is χ²(θ) = Σ_k ((o_k(θ) − t_k) / σ_k)².

:func:`sensitivity`: S = diag(1/σ) dM/dθ · dθ/du at a parameter set, by :func:`lvenv.jacobian`,
per unit-cube coordinate u of :class:`lvenv.identification.ParameterSpace` (log axes where
marked): its singular values (χ per unit-cube step) and the directions that change no target to
first order (singular value below 1e-3 of the largest), by parameter name.

:func:`profile`: for each parameter θ_j, a grid over its whole identification bound; at each grid
value the other parameters are refitted (Raue A et al., Bioinformatics 25:1923, 2009). All
the constrained fits of all parameters go through one vector env as one cohort
(:func:`optim.cohort.fit_reports`, CMA-ES per fit, weights w_k = (t_k/σ_k)² so that the env's
objective is χ² up to a constant factor), and the profile is χ² of each fit's confirmed steady
state. With Δ = 3.84 (the 95 % point of χ² with one degree of freedom), each parameter is

* ``identified``: the profile rises more than Δ above its minimum on both sides within the
  bounds (the 95 % interval is finite);
* ``practically non-identifiable``: it rises above Δ on at most one side, but is not flat;
* ``structurally non-identifiable``: it stays flat (max − min < :data:`FLAT` = 1) over the whole
  bound, and the parameter has a component above 0.1 in a null direction of the sensitivity;
* ``no usable fit``: every constrained fit of it failed.

The constrained fits' objective also holds the env's plausibility bands (:mod:`lvenv.plausibility`,
``CohortOptions.plausibility``), which are 0 wherever the filling pressures are physiological.
Profiles are as good as the constrained fits: a fit stuck above its true minimum raises the
profile at that grid point. Use a larger ``budget`` where profiles look ragged.

:func:`posterior`: samples of p(θ | targets) ∝ exp(−χ²(θ)/2) · prior(θ), with the prior uniform
in the unit cube of the identification bounds (log-uniform on log axes: weak, inside the physical
bounds), times the factor exp(−½ Σ_b (d_b / 5 mmHg)²) over the bands b of every other method's
objective (:mod:`lvenv.plausibility`: d_b is how far the mean aortic pressure lies outside
80–120 mmHg and, with ``plausibility`` (default), the mean atrial pressure or EDP outside 4–25
mmHg; 5 mmHg is the pressure σ of :data:`NOISE`, :data:`PLAUSIBILITY_SD`). Without the aortic
band the posterior spread along the τ2–Sa ridge into hearts no other method would accept, and
the 90 % intervals of synthetic truths drawn inside it missed the truth too often
(``scripts/calibration.py``).
Sampler: the ensemble sampler of ``emcee`` (Foreman-Mackey D et al., PASP 125:306,
2013) with differential-evolution moves by default, vectorised: each half-ensemble of proposals is one step of a
vector env (:func:`optim.fit.make_env`), so the walkers run through the batched heart. This is
the issue's fallback sampler; a gradient-based NUTS is not built (see README). Diagnostics:
acceptance fraction, emcee's integrated autocorrelation time τ per parameter and the effective
sample size (walkers × kept steps / τ), and the split R-hat of Gelman et al. (BDA3, §11.4)
computed with the walkers as chains (walkers of an ensemble are not independent, so R-hat is
optimistic; trust τ first). :func:`probability_lower` compares two patients' posteriors.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

import lvenv
from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.metrics import FRAME_NAMES
from lvenv.patients import Patient
from lvenv.plausibility import Band, distance
from lvenv.plausibility import resolve as resolve_bands
from lvenv.units import mmhg_to_kpa
from lvenv.validation import InputError, integer
from optim.cohort import CohortOptions, Report, fit_reports

__all__ = ["NOISE", "PLAUSIBILITY_SD", "DELTA_95", "FLAT", "Sensitivity", "Profiles", "Posterior", "sensitivity", "profile", "posterior",
           "probability_lower", "chi2"]

#: Standard deviation of each target's measurement error, internal units (ours, illustrative):
#: EF 0.05, time intervals 10 ms, pressures 5 mmHg (filling pressures included), volumes 5 ml
#: (each frame of a volume trace too).
NOISE: dict[str, float] = {
    "EF": 0.05, "IVCT": 0.010, "ET": 0.010, "IVRT": 0.010, "filling_time": 0.010,
    "P_ao_sys": float(mmhg_to_kpa(5.0)), "P_ao_dia": float(mmhg_to_kpa(5.0)), "P_ao_mean": float(mmhg_to_kpa(5.0)),
    "P_ao_pulse": float(mmhg_to_kpa(5.0)), "P_lv_peak": float(mmhg_to_kpa(5.0)), "EDV": 5.0, "ESV": 5.0, "SV": 5.0,
    "EDP": float(mmhg_to_kpa(5.0)), "P_at_mean": float(mmhg_to_kpa(5.0)), **dict.fromkeys(FRAME_NAMES, 5.0),
}
#: Standard deviation (kPa) of the posterior's plausibility factor: 5 mmHg outside a filling band
#: costs as much as a pressure measured 1 σ off.
PLAUSIBILITY_SD = float(mmhg_to_kpa(5.0))
#: 95 % point of χ² with one degree of freedom: the profile-likelihood threshold.
DELTA_95 = 3.84
#: A profile whose range stays below this (χ² units) over the whole bound is flat.
FLAT = 1.0
_NULL_COMPONENT = 0.1


def _sigma(patient: Patient, noise: Mapping[str, float]) -> np.ndarray:
    missing = [k for k in patient.targets if k not in noise]
    if missing:
        raise InputError(f"no measurement error for the target(s) {missing}; give noise={{name: sd}} in internal units")
    return np.array([float(noise[k]) for k in patient.targets])


def chi2(patient: Patient, observation: Mapping[str, float], noise: Mapping[str, float] = NOISE) -> float:
    """Σ_k ((o_k − t_k) / σ_k)² over the patient's targets (module docstring)."""
    o = np.array([observation[k] for k in patient.targets])
    t = np.array(list(patient.targets.values()))
    return float(np.sum(((o - t) / _sigma(patient, noise)) ** 2))


@dataclasses.dataclass(frozen=True)
class Sensitivity:
    """S (targets × parameters), its singular values and null directions by parameter name."""

    names: tuple[str, ...]
    targets: tuple[str, ...]
    matrix: np.ndarray
    singular_values: np.ndarray
    null_directions: list[dict[str, float]]

    def null_component(self, name: str) -> float:
        """Length of parameter ``name``'s part of the null space (0: locally pinned)."""
        return float(np.sqrt(sum(d[name] ** 2 for d in self.null_directions)))


def sensitivity(patient: Patient, parameters: Mapping[str, float] | None = None, *, noise: Mapping[str, float] = NOISE,
                steps_per_beat: int = 1000) -> Sensitivity:
    """S at ``parameters`` (default: the patient's own values) of :data:`DEFAULT_ACTION_PARAMS`."""
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    heart = patient.heart.replace(**dict(parameters or {}))
    targets = tuple(patient.targets)
    jac = lvenv.jacobian(heart, wrt=space.names, metrics=targets, steps_per_beat=steps_per_beat)
    if jac.status != "ok":
        raise InputError(f"the heart at these parameters has no usable steady state (status {jac.status!r})")
    x = np.array([float(heart.get(n)) for n in space.names])
    matrix = jac.values * space.rate(x)[None, :] / _sigma(patient, noise)[:, None]
    _, sv, vt = np.linalg.svd(matrix)
    rank = int(np.sum(sv > 1e-3 * sv[0]))
    null = [dict(zip(space.names, map(float, v))) for v in vt[rank:]]
    return Sensitivity(space.names, targets, matrix, sv, null)


@dataclasses.dataclass(frozen=True)
class Profiles:
    """Profile likelihoods: per parameter its grid (physical units), χ² of the constrained fits
    (NaN where a fit failed) and their parameters, the overall minimum, the 95 % interval (None on a side where the
    profile stays below the threshold up to the bound) and the class (module docstring)."""

    grid: dict[str, np.ndarray]
    chi2: dict[str, np.ndarray]
    fits: dict[str, list[dict[str, float]]]  # the constrained fits' parameters, per grid value
    chi2_min: float
    interval: dict[str, tuple[float | None, float | None]]
    classification: dict[str, str]
    sensitivity: Sensitivity | None
    evaluations: int

    def to_dict(self) -> dict[str, Any]:
        return {"grid": {k: v.tolist() for k, v in self.grid.items()}, "chi2": {k: v.tolist() for k, v in self.chi2.items()}, "fits": self.fits,
                "chi2_min": self.chi2_min, "interval": self.interval, "classification": self.classification,
                "evaluations": self.evaluations}


def _interval(grid: np.ndarray, values: np.ndarray, level: float) -> tuple[float | None, float | None]:
    """Grid values where the profile first exceeds ``level`` on each side of its minimum."""
    i = int(np.nanargmin(values))
    above = np.where(np.isfinite(values), values > level, False)
    left = [j for j in range(i - 1, -1, -1) if above[j]]
    right = [j for j in range(i + 1, len(grid)) if above[j]]
    return (float(grid[left[0]]) if left else None, float(grid[right[0]]) if right else None)


def profile(
    patient: Patient,
    *,
    names: Sequence[str] = DEFAULT_ACTION_PARAMS,
    grid: int = 9,
    fit: Mapping[str, float] | None = None,
    noise: Mapping[str, float] = NOISE,
    options: CohortOptions | None = None,
) -> Profiles:
    """Profile likelihoods of ``names`` for ``patient`` (module docstring), ``grid`` values per
    parameter spread uniformly over its bound in the unit cube (log-uniform on log axes).
    ``fit``: the best parameters, if known, for the sensitivity (default: the best profile point).
    ``options``: of the constrained fits (default: `CohortOptions(budget=480, stop_mismatch=0)`,
    i.e. every fit uses its whole budget)."""
    grid = integer("grid", grid, 3)
    options = options or CohortOptions(budget=480, stop_mismatch=0.0)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    unknown = [n for n in names if n not in space.names]
    if unknown or not names:
        raise InputError(f"names = {list(names)}: profile parameters must be among {space.names}")
    sigma = _sigma(patient, noise)
    weights = {k: (t / s) ** 2 for (k, t), s in zip(patient.targets.items(), sigma)}
    weighted = dataclasses.replace(patient, weights=weights)
    unit = np.linspace(0.0, 1.0, grid)
    reports, points = [], {}
    for name in names:
        j = space.names.index(name)
        values = space.from_unit(np.outer(unit, np.eye(space.dimension)[j]) + 0.5 * (1 - np.eye(space.dimension)[j]))[:, j]
        points[name] = values
        for g, value in enumerate(values):
            reports.append(Report(g, f"{name}[{g}]", weighted, {}, {name: float(value)}))
    results = {r["id"]: r for r in fit_reports(reports, options)}
    profiles = {}
    for name in names:
        profiles[name] = np.array([
            chi2(patient, results[f"{name}[{g}]"]["observation"], noise) if np.isfinite(results[f"{name}[{g}]"]["mismatch"]) else np.nan
            for g in range(grid)])
    chi2_min = float(np.nanmin(np.concatenate(list(profiles.values()))))
    if fit is None:
        name, g = min(((n, g) for n in names for g in range(grid)), key=lambda ng: np.nan_to_num(profiles[ng[0]][ng[1]], nan=np.inf))
        fit = results[f"{name}[{g}]"]["parameters"]
    try:
        sens = sensitivity(patient, fit, noise=noise, steps_per_beat=options.steps_per_beat)
    except InputError:
        sens = None
    interval, classes = {}, {}
    for name in names:
        values = profiles[name]
        if not np.isfinite(values).any():
            interval[name], classes[name] = (None, None), "no usable fit"
            continue
        interval[name] = _interval(points[name], values, chi2_min + DELTA_95)
        flat = np.nanmax(values) - np.nanmin(values) < FLAT
        if flat and sens is not None and sens.null_component(name) > _NULL_COMPONENT:
            classes[name] = "structurally non-identifiable"
        elif None in interval[name]:
            classes[name] = "practically non-identifiable"
        else:
            classes[name] = "identified"
    evaluations = int(sum(r["evaluations"] for r in results.values()))
    fits = {name: [results[f"{name}[{g}]"]["parameters"] for g in range(grid)] for name in names}
    return Profiles(points, profiles, fits, chi2_min, interval, classes, sens, evaluations)


@dataclasses.dataclass(frozen=True)
class Posterior:
    """Posterior samples by parameter name (physical units, burn-in removed, walkers × steps
    flattened), their medians and 90 % credible intervals, and the diagnostics (module docstring)."""

    samples: dict[str, np.ndarray]
    median: dict[str, float]
    interval_90: dict[str, tuple[float, float]]
    acceptance: float
    autocorr_time: dict[str, float]
    ess: dict[str, float]
    rhat: dict[str, float]
    evaluations: int
    failed: int

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if k != "samples"}

    def widths(self) -> dict[str, float]:
        """Width of each 90 % interval as a fraction of the parameter's identification bound
        (on its log scale for log axes), so widths compare across parameters and data sets."""
        space = ParameterSpace.for_names(tuple(self.samples))
        lo, hi = (space.to_unit(np.array([self.interval_90[n][i] for n in space.names])) for i in (0, 1))
        return dict(zip(space.names, map(float, hi - lo)))


def _split_rhat(chains: np.ndarray) -> float:
    """Split R-hat of (chains, draws) (Gelman et al., BDA3 §11.4)."""
    half = chains.shape[1] // 2
    split = np.concatenate([chains[:, :half], chains[:, half:2 * half]])
    n = split.shape[1]
    within = np.mean(np.var(split, axis=1, ddof=1))
    between = n * np.var(np.mean(split, axis=1), ddof=1)
    return float(np.sqrt(((n - 1) / n * within + between / n) / within)) if within > 0 else float("nan")


def posterior(
    patient: Patient,
    *,
    start: Mapping[str, float] | None = None,
    walkers: int = 32,
    steps: int = 400,
    burn: int | None = None,
    spread: float = 0.02,
    seed: int = 0,
    noise: Mapping[str, float] = NOISE,
    steps_per_beat: int = 500,
    max_beats: int = 60,
    moves: Any = "de",
    plausibility: bool | Sequence[Band] = True,
) -> Posterior:
    """Sample the posterior of :data:`DEFAULT_ACTION_PARAMS` for ``patient`` (module docstring).

    ``start``: the walkers start in a ball of radius ``spread`` (unit-cube units) around it
    (default: the patient's own values; a fit is better). ``burn``: steps dropped (default
    ``steps // 2``). The env has ``walkers // 2`` members (emcee proposes half the ensemble at a time).
    ``moves``: ``"de"`` (default: differential-evolution moves, 80 % ``DEMove`` and 20 %
    ``DESnookerMove``, ter Braak & Vrugt 2008) or any ``moves`` emcee takes (``None``: its stretch
    move). On the built-in N patient, 32 walkers × 1000 steps, "de" reached split R-hat 1.09–1.15
    against 1.34–1.77 for the stretch move. ``plausibility``: the filling-pressure bands in the prior
    factor (module docstring; :func:`lvenv.plausibility.resolve`).
    """
    import emcee

    from optim.fit import make_env

    walkers, steps, seed = integer("walkers", walkers, 8), integer("steps", steps, 2), integer("seed", seed, 0)
    if walkers % 2:
        raise InputError(f"walkers = {walkers} must be even (emcee moves half the ensemble at a time)")
    burn = steps // 2 if burn is None else integer("burn", burn, 0, steps - 2)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    sigma = _sigma(patient, noise)
    targets = np.array(list(patient.targets.values()))
    target_names = list(patient.targets)
    bands = resolve_bands(plausibility)
    venv = make_env(patient, walkers // 2, steps_per_beat, max_beats)
    venv.reset(seed=seed)
    action_map = venv.unwrapped.config.actions
    counts = {"evaluations": 0, "failed": 0}

    def log_prob(u: np.ndarray) -> np.ndarray:
        u = np.atleast_2d(u)
        inside = np.all((u >= 0.0) & (u <= 1.0), axis=1)
        x = space.from_unit(np.clip(u, 0.0, 1.0))
        out = np.full(len(u), -np.inf)
        for start_row in range(0, len(u), walkers // 2):
            block = slice(start_row, start_row + walkers // 2)
            rows = x[block]
            padded = np.concatenate([rows, np.repeat(rows[-1:], walkers // 2 - len(rows), axis=0)])
            _, _, _, _, info = venv.step(action_map.to_action(padded))
            obs = np.stack([np.asarray(info[k], float) for k in target_names], axis=1)[: len(rows)]
            ok = np.isin(info["status"][: len(rows)], ("ok", "not_converged")) & np.all(np.isfinite(obs), axis=1)
            value = -0.5 * np.sum(((obs - targets) / sigma) ** 2, axis=1)
            value -= 0.5 * sum((np.asarray(distance(b, info[b.metric][: len(rows)])) / PLAUSIBILITY_SD) ** 2 for b in bands)
            out[block] = np.where(ok & inside[block], value, -np.inf)
            counts["evaluations"] += len(rows)
            counts["failed"] += int(np.sum(~ok))
        return out

    rng = np.random.default_rng(seed)
    centre = space.to_unit(space.clip(np.array([float((start or {}).get(n, patient.heart.get(n))) for n in space.names])))
    u0 = np.clip(centre + spread * rng.standard_normal((walkers, space.dimension)), 1e-6, 1 - 1e-6)
    if moves == "de":
        moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    sampler = emcee.EnsembleSampler(walkers, space.dimension, log_prob, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(seed).get_state()  # emcee's own generator, seeded
    sampler.run_mcmc(u0, steps, progress=False)
    venv.close()
    chain = sampler.get_chain(discard=burn)  # (kept steps, walkers, k), unit cube
    physical = space.from_unit(chain)
    tau = sampler.get_autocorr_time(discard=burn, quiet=True)
    kept = chain.shape[0] * walkers
    samples = {n: physical[..., j].T.reshape(-1) for j, n in enumerate(space.names)}
    return Posterior(
        samples=samples,
        median={n: float(np.median(v)) for n, v in samples.items()},
        interval_90={n: (float(np.percentile(v, 5)), float(np.percentile(v, 95))) for n, v in samples.items()},
        acceptance=float(np.mean(sampler.acceptance_fraction)),
        autocorr_time={n: float(t) for n, t in zip(space.names, tau)},
        ess={n: float(kept / t) for n, t in zip(space.names, tau)},
        rhat={n: _split_rhat(chain[..., j].T) for j, n in enumerate(space.names)},
        evaluations=counts["evaluations"],
        failed=counts["failed"],
    )


def probability_lower(a: Posterior, b: Posterior, name: str) -> float:
    """P(θ_a < θ_b) for parameter ``name`` of two patients with independent posteriors, over all
    pairs of one sample of each (exact for the two sample sets)."""
    other = np.sort(b.samples[name])
    above = len(other) - np.searchsorted(other, a.samples[name], side="right")  # b-samples above each a-sample
    return float(np.sum(above) / (len(a.samples[name]) * len(other)))
