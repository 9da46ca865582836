"""Profile likelihoods: which parameters a patient's measurements pin down, and how far.

:func:`profile`: for each parameter θ_j, a grid over its whole identification bound; at each grid
value the other parameters are refitted (Raue A et al., Bioinformatics 25:1923, 2009). All
the constrained fits of all parameters go through one vector env as one cohort
(:func:`optim.cohort.fit_reports`, CMA-ES per fit, weights w_k = (t_k/σ_k)² by
:func:`~optim.identify.chi2_weighted` so that the env's objective is χ² up to a constant factor),
and the profile is χ² (:func:`~optim.identify.chi2`) of each fit's confirmed steady state. With
Δ = 3.84 (:data:`DELTA_95`, the 95 % point of χ² with one degree of freedom), each parameter is

* ``identified``: the profile rises more than Δ above its minimum on both sides within the
  bounds, beyond every point that stays below (the 95 % interval is finite);
* ``practically non-identifiable``: it rises above Δ on at most one side, but is not flat;
* ``structurally non-identifiable``: it stays flat (max − min < :data:`FLAT` = 1) over the whole
  bound, and the parameter has a component above 0.1 in a null direction of the sensitivity
  (:func:`~optim.identify.sensitivity`);
* ``no usable fit``: every constrained fit of it failed.

The constrained fits' objective also holds the env's plausibility bands (:mod:`lvenv.plausibility`,
``CohortOptions.plausibility``), which are 0 wherever the filling pressures are physiological.
Profiles are as good as the constrained fits: a fit stuck above its true minimum raises the
profile at that grid point. Use a larger ``budget`` where profiles look ragged.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.patients import Patient
from lvenv.validation import InputError, integer
from optim.cohort import CohortOptions, Report, fit_reports
from optim.identify.noise import NOISE, Relative, chi2, chi2_weighted
from optim.identify.sensitivities import Sensitivity, sensitivity

__all__ = ["DELTA_95", "FLAT", "Profiles", "profile"]


#: 95 % point of χ² with one degree of freedom: the profile-likelihood threshold.
DELTA_95 = 3.84
#: A profile whose range stays below this (χ² units) over the whole bound is flat.
FLAT = 1.0
_NULL_COMPONENT = 0.1


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
    """Outer ends of the profile interval: on each side, the grid value next beyond the outermost
    point at or below ``level`` where the profile is above it (None where no point beyond is).
    Where no point is at or below ``level``, the profile's own minimum stands for them.

    Each profile point is a constrained fit's χ², an upper bound of the true profile there, so a
    point at or below ``level`` is certain and one above may be a fit that stalled: the interval
    spans every point below the level, and a stalled fit inside it cannot split or shorten it.
    """
    finite = np.isfinite(values)
    below = np.flatnonzero(finite & (values <= level))
    if not below.size:  # every constrained fit of this parameter ended above the overall best + Δ
        below = np.array([int(np.nanargmin(values))])
    above = finite & (values > level)
    left = [j for j in range(below[0] - 1, -1, -1) if above[j]]
    right = [j for j in range(below[-1] + 1, len(grid)) if above[j]]
    return (float(grid[left[0]]) if left else None, float(grid[right[0]]) if right else None)


def profile(
    patient: Patient,
    *,
    names: Sequence[str] = DEFAULT_ACTION_PARAMS,
    grid: int = 9,
    fit: Mapping[str, float] | None = None,
    noise: Mapping[str, float | Relative] = NOISE,
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
    weighted = chi2_weighted(patient, noise)
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
