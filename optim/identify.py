"""What a patient's measurements pin down: the sensitivity at a fit and profile likelihoods.

Measurement model (replace it with your laboratory's values): each target k is measured with an
independent Gaussian error of standard deviation σ_k (:data:`NOISE`, internal units), so a
parameter set's misfit is χ²(θ) = Σ_k ((o_k(θ) − t_k) / σ_k)². Where the defaults come from:

* EF 0.05: two expert readers of the same 2-D echo studies (Simpson's biplane, 140 patients)
  differed by 0.96 ± 7.0 EF points (Akil S et al., Clin Physiol Funct Imaging 2024,
  doi:10.1111/cpf.12918), so one reading's error is 7.0/√2 ≈ 5 points.
* Cuff pressures 5 mmHg: a validated cuff device may differ from the reference by a mean of at
  most 5 mmHg with a standard deviation of at most 8 mmHg (AAMI/ESH/ISO 81060-2; Stergiou G et
  al., J Hypertens 36:472, 2018). 5 mmHg is a device well inside that limit; give 8 mmHg for
  the worst device the standard admits.
* Volumes (EDV, ESV, each frame of a cine volume trace) 5 % of the measured volume
  (:class:`Relative`): two observers of the same biplane cine MR studies (18 normal subjects,
  EDV 120 ± 20 ml) differed in EDV by 5.6 ± 7.8 ml (Benjelloun H et al., Am J Cardiol 67:1413,
  1991), one reading's error 7.8/√2 ≈ 5.5 ml or 4.6 % of EDV; short-axis stacks of 10 healthy
  volunteers varied between operators by 4.2 % (EDV) and 6.2 % (ESV) (PMID 15881528). A
  relative error carries these figures over to a heart of another size: 5 ml on a 23 ml ESV
  would be 22 %. Stroke volume, the difference of two readings: 10 %. The frames' errors are
  taken as independent. A reader's contouring habit also shifts all frames together
  (Suinesiaputra A et al., J Cardiovasc Magn Reson 17:63, 2015); this model leaves that shared
  part out, so it overstates what a trace tells (an added shared error can only remove
  information). Pass ``noise={**NOISE, **dict.fromkeys(VOLUME_NAMES, 5.0)}`` for 5 ml on
  every volume.
* Time intervals 10 ms and filling-pressure estimates 5 mmHg: ours, illustrative (no published
  inter-observer error was at hand for them).

:func:`sensitivity`: S = diag(1/σ) dM/dθ · dθ/du at a parameter set, by :func:`lvenv.jacobian`,
per unit-cube coordinate u of :class:`lvenv.identification.ParameterSpace` (log axes where
marked): its singular values (χ per unit-cube step) and the directions that change no target to
first order (singular value below 1e-3 of the largest), by parameter name.

:func:`profile`: for each parameter θ_j, a grid over its whole identification bound; at each grid
value the other parameters are refitted (Raue A et al., Bioinformatics 25:1923, 2009). All
the constrained fits of all parameters go through one vector env as one cohort
(:func:`optim.cohort.fit_reports`, CMA-ES per fit, weights w_k = (t_k/σ_k)² by
:func:`chi2_weighted` so that the env's objective is χ² up to a constant factor), and the
profile is χ² of each fit's confirmed steady state. With Δ = 3.84 (the 95 % point of χ² with
one degree of freedom), each parameter is

* ``identified``: the profile rises more than Δ above its minimum on both sides within the
  bounds, beyond every point that stays below (the 95 % interval is finite);
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
Sampler, in two stages:

1. *Pilot*: the ensemble sampler of ``emcee`` (Foreman-Mackey D et al., PASP 125:306, 2013) with
   differential-evolution moves by default, vectorised: each half-ensemble of proposals is one
   step of a vector env (:func:`optim.fit.make_env`), so the walkers run through the batched
   heart. It finds the posterior's region and shape, ridge included, but its walkers are not
   independent chains and move slowly along the ridge (split R-hat 1.05–1.27 after 800–2000 steps).
   From a start far from the posterior's mass (a failed fit) the walkers are still climbing after
   ``steps``; the pilot is then extended (:data:`CLIMB`).
2. *Chains*: ``chains`` independent Metropolis–Hastings chains started at pilot draws, in
   ``rounds`` rounds. Each step is, with probability 0.8, an independence proposal from a
   Gaussian mixture fitted to the draws of the stage before (the pilot's for round 1, the
   previous round's after) in logit coordinates of the unit cube (components chosen by BIC, plus a
   defensive copy with doubled standard deviations and weight 0.1, so the proposal's tails are
   heavier than the fit's), else a Gaussian random-walk step (0.1 × the covariance of the draws
   before). The proposal is fixed within a round, so each round's chains are valid MCMC chains
   of the posterior whatever the draws before found (Tierney L, Ann Stat 22:1701, 1994); a
   better fit only makes them mix faster. Only the last round is reported. The chains do not
   interact, so their split R-hat is the real diagnostic. On a curved 6-D ridge (the test's)
   with a DE pilot, one round mixed with τ ≈ 5–9 steps and R-hat up to 1.11, the second,
   refitted, with τ ≈ 2–3 and R-hat ≤ 1.03 after 300 kept steps. From a wrong pilot (a narrow
   Gaussian off the ridge) two rounds had not mixed, and R-hat (1.28) said so; four had.

With ``sampler="nuts"``, stage 2 is NUTS chains with gradients through the heart
(:mod:`optim.nuts`, BlackJAX) instead: the gradient-based sampler. Its fixed-step
log-posterior is continuous since the integrator weighs each valve's conductance by the part of
the step it is open (:func:`lvenv.model.jacobian`): along lines through the N preset (±3 % in
τ2 or Sa, 301 points) log p departs from a smooth trend by at most 0.011 between neighbours at
500 steps per beat, against 0.62 with the earlier yes/no valve switch, whose IVRT was a sawtooth
with jumps of up to a step. Step-size adaptation at 500 steps (the default
``gradient_steps_per_beat``) then settles at 0.14–0.23 in whitened units, where it collapsed to
0.016 before; each leapfrog step of all chains is a steady state plus 15 tangents (README for
the cost). The ensemble chains stay the default.

Diagnostics (of the chains; of the pilot's walkers when ``chains=0``): acceptance fraction,
emcee's integrated autocorrelation time τ per parameter and the effective sample size (chains ×
kept steps / τ), and the split R-hat of Gelman et al. (BDA3, §11.4), largest over parameters
below 1.01 in the README's runs of the built-in patients. :func:`probability_lower` compares two patients' posteriors.

Calibration: :func:`prior_draws` draws truths from this prior exactly (rejection sampling), with
their observations from the posterior's env; :func:`log_density` evaluates the unnormalised
posterior density at any parameters, to rank a truth among the samples
(``scripts/calibration.py``).

:func:`amortised`: the posterior of any number of patients from the trained flow of
:mod:`optim.amortised` (same prior, noise and observation model), one batched pass, with an
out-of-distribution flag; :func:`prior_sample` draws its training pairs.

:func:`write_report`: all of the above at a fit, as a per-patient markdown report with the profile
curves and the posterior pairs plot as PNG (``lvenv fit PATIENT --report DIR``).
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

import lvenv
from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS, ParameterSpace, from_logit, to_logit
from lvenv.metrics import FRAME_NAMES
from lvenv.patients import Patient
from lvenv.plausibility import Band, distance
from lvenv.plausibility import resolve as resolve_bands
from lvenv.status import USABLE
from lvenv.units import mmhg_to_kpa
from lvenv.validation import InputError, integer, real
from optim.cohort import CohortOptions, Report, fit_reports

__all__ = ["NOISE", "Relative", "VOLUME_NAMES", "measurement_sd", "chi2_weighted", "PLAUSIBILITY_SD", "DELTA_95", "FLAT", "Sensitivity", "Profiles", "Posterior", "sensitivity", "profile", "posterior",
           "probability_lower", "prior_draws", "prior_sample", "PriorSample", "amortised", "log_density", "chi2", "write_report", "SAMPLERS", "SAMPLER_SETTINGS", "add_sampler_options", "sampler_options"]


@dataclasses.dataclass(frozen=True)
class Relative:
    """A measurement error proportional to the measured value: σ_k = ``fraction`` × abs(t_k).

    A :data:`NOISE` entry is either this or a plain number, the standard deviation in internal
    units. Scaling by a number scales the fraction (``2 * Relative(0.05)`` is ``Relative(0.1)``).
    """

    fraction: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "fraction", real("Relative.fraction", self.fraction, 0.0, lo_open=True))

    def __mul__(self, factor: float) -> Relative:
        return Relative(self.fraction * factor)

    __rmul__ = __mul__

    def __truediv__(self, divisor: float) -> Relative:
        return Relative(self.fraction / divisor)


#: The volume metrics: their measurement errors are relative (module docstring).
VOLUME_NAMES = ("EDV", "ESV", *FRAME_NAMES)
#: Standard deviation of each target's measurement error (sources in the module docstring):
#: EF 0.05, time intervals 10 ms, pressures 5 mmHg (filling pressures included), in internal
#: units; volumes 5 % of the measured volume (each frame of a volume trace too), stroke volume 10 %.
NOISE: dict[str, float | Relative] = {
    "EF": 0.05, "IVCT": 0.010, "ET": 0.010, "IVRT": 0.010, "filling_time": 0.010,
    "P_ao_sys": float(mmhg_to_kpa(5.0)), "P_ao_dia": float(mmhg_to_kpa(5.0)), "P_ao_mean": float(mmhg_to_kpa(5.0)),
    "P_ao_pulse": float(mmhg_to_kpa(5.0)), "P_lv_peak": float(mmhg_to_kpa(5.0)), "SV": Relative(0.10),
    "EDP": float(mmhg_to_kpa(5.0)), "P_at_mean": float(mmhg_to_kpa(5.0)), **dict.fromkeys(VOLUME_NAMES, Relative(0.05)),
}
#: Standard deviation (kPa) of the posterior's plausibility factor: 5 mmHg outside a filling band
#: costs as much as a pressure measured 1 σ off.
PLAUSIBILITY_SD = float(mmhg_to_kpa(5.0))
#: 95 % point of χ² with one degree of freedom: the profile-likelihood threshold.
DELTA_95 = 3.84
#: A profile whose range stays below this (χ² units) over the whole bound is flat.
FLAT = 1.0
_NULL_COMPONENT = 0.1


def measurement_sd(targets: Mapping[str, float], noise: Mapping[str, float | Relative] = NOISE) -> np.ndarray:
    """σ_k of each target (internal units, in the targets' order): ``noise[k]``, or its fraction
    of abs(t_k) for a :class:`Relative` entry."""
    missing = [k for k in targets if k not in noise]
    if missing:
        raise InputError(f"no measurement error for the target(s) {missing}; give noise={{name: sd}} in internal units "
                         "or noise={name: Relative(fraction)}")
    sigma = np.array([noise[k].fraction * abs(float(t)) if isinstance(noise[k], Relative) else float(noise[k])
                      for k, t in targets.items()])
    bad = [f"{k} = {float(s)}" for k, s in zip(targets, sigma) if not (np.isfinite(s) and s > 0)]
    if bad:
        raise InputError(f"measurement error(s) {bad} must be finite and > 0 (a relative error of a zero target is 0)")
    return sigma


def chi2_weighted(patient: Patient, noise: Mapping[str, float | Relative] = NOISE) -> Patient:
    """``patient`` with target weights w_k = (t_k / σ_k)², so that the env's objective (relative
    errors, weighted) is χ² up to a constant factor."""
    sigma = measurement_sd(patient.targets, noise)
    return dataclasses.replace(patient, weights={k: (t / s) ** 2 for (k, t), s in zip(patient.targets.items(), sigma)})


def chi2(patient: Patient, observation: Mapping[str, float], noise: Mapping[str, float | Relative] = NOISE) -> float:
    """Σ_k ((o_k − t_k) / σ_k)² over the patient's targets (module docstring)."""
    o = np.array([observation[k] for k in patient.targets])
    t = np.array(list(patient.targets.values()))
    return float(np.sum(((o - t) / measurement_sd(patient.targets, noise)) ** 2))


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


def sensitivity(patient: Patient, parameters: Mapping[str, float] | None = None, *, noise: Mapping[str, float | Relative] = NOISE,
                steps_per_beat: int = 1000) -> Sensitivity:
    """S at ``parameters`` (default: the patient's own values) of :data:`DEFAULT_ACTION_PARAMS`."""
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    heart = patient.heart.replace(**dict(parameters or {}))
    targets = tuple(patient.targets)
    jac = lvenv.jacobian(heart, wrt=space.names, metrics=targets, steps_per_beat=steps_per_beat)
    if jac.status != "ok":
        raise InputError(f"the heart at these parameters has no usable steady state (status {jac.status!r})")
    x = np.array([float(heart.get(n)) for n in space.names])
    matrix = jac.values * space.rate(x)[None, :] / measurement_sd(patient.targets, noise)[:, None]
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


@dataclasses.dataclass(frozen=True)
class Posterior:
    """Posterior samples by parameter name (physical units, burn-in removed, walkers × steps
    flattened), their medians and 90 % credible intervals, and the diagnostics (module docstring).
    ``pilot_steps``: the pilot's steps, more than ``steps`` where it was extended (:data:`CLIMB`).
    From :func:`amortised` (``sampler="amortised"``) the samples are independent draws of the
    flow: no acceptance (NaN), autocorrelation time 1, ESS the number of samples, and the split
    R-hat of four consecutive blocks of them."""

    samples: dict[str, np.ndarray]
    median: dict[str, float]
    interval_90: dict[str, tuple[float, float]]
    acceptance: float
    autocorr_time: dict[str, float]
    ess: dict[str, float]
    rhat: dict[str, float]
    evaluations: int
    failed: int
    pilot_steps: int
    sampler: str = "ensemble"
    divergent: int = 0  # NUTS transitions that diverged (0 for the ensemble)
    out_of_distribution: str = ""  # amortised posteriors: why the observation is outside the training set ("" if inside)

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if k != "samples"}

    def widths(self) -> dict[str, float]:
        """Width of each 90 % interval as a fraction of the parameter's identification bound
        (on its log scale for log axes), so widths compare across parameters and data sets."""
        space = ParameterSpace.for_names(tuple(self.samples))
        lo, hi = (space.to_unit(np.array([self.interval_90[n][i] for n in space.names])) for i in (0, 1))
        return dict(zip(space.names, map(float, hi - lo)))

    def highest_density(self, level: float = 0.9) -> dict[str, tuple[float, float]]:
        """The narrowest interval holding ``level`` of each parameter's samples (physical units),
        narrowest in the unit-cube coordinate of its bound (log scale on log axes), where the prior
        is flat. Unlike the equal-tailed :attr:`interval_90` it reaches a bound the samples pile
        against, so it keeps the most probable values of a parameter that the data push there."""
        level = real("level", level, 0.0, 1.0, lo_open=True)
        space = ParameterSpace.for_names(tuple(self.samples))
        ordered = np.sort(np.stack([self.samples[n] for n in space.names], axis=1), axis=0)
        u, n = space.to_unit(ordered), len(ordered)
        k = max(1, int(np.ceil(level * n)))
        first = np.argmin(u[k - 1:] - u[: n - k + 1], axis=0)
        return {name: (float(ordered[i, j]), float(ordered[i + k - 1, j])) for j, (name, i) in enumerate(zip(space.names, first))}


def _split_rhat(chains: np.ndarray) -> float:
    """Split R-hat of (chains, draws) (Gelman et al., BDA3 §11.4)."""
    half = chains.shape[1] // 2
    split = np.concatenate([chains[:, :half], chains[:, half:2 * half]])
    n = split.shape[1]
    within = np.mean(np.var(split, axis=1, ddof=1))
    between = n * np.var(np.mean(split, axis=1), ddof=1)
    return float(np.sqrt(((n - 1) / n * within + between / n) / within)) if within > 0 else float("nan")


#: What samples after the pilot: :func:`posterior`'s ``sampler``.
SAMPLERS = ("ensemble", "nuts")

#: Pilot burn-in check: while the median log-posterior of the pilot's last quarter of steps is
#: more than :data:`CLIMB` above the quarter's before, the walkers are still climbing from the
#: start (a start far from the posterior's mass), and the pilot runs ``steps`` more, at most
#: :data:`PILOT_EXTENSIONS` times.
CLIMB, PILOT_EXTENSIONS = 1.0, 3


def _climbing(log_prob: np.ndarray) -> bool:
    """Whether the walkers' log-posterior (steps, walkers) still rises (:data:`CLIMB`)."""
    quarter = len(log_prob) // 4
    before, last = log_prob[-2 * quarter:-quarter], log_prob[-quarter:]
    median = lambda lp: np.median(lp[np.isfinite(lp)]) if np.isfinite(lp).any() else -np.inf
    return bool(quarter >= 1 and median(last) > median(before) + CLIMB)


#: Chain moves: the independence proposal's share, the defensive component's weight and
#: standard-deviation factor, and the random walk's covariance factor (module docstring).
INDEPENDENCE_SHARE, DEFENSIVE_WEIGHT, DEFENSIVE_SCALE, WALK_SCALE = 0.8, 0.1, 2.0, 0.1


class _Mixture:
    """Gaussian mixture on z = logit(u), with the density of u it induces on the unit cube:
    log g(u) = log g_z(z) − Σ log(u (1 − u))."""

    def __init__(self, weights: np.ndarray, means: np.ndarray, covariances: np.ndarray) -> None:
        self.weights, self.means = np.asarray(weights, float), np.asarray(means, float)
        self.chol = np.linalg.cholesky(np.asarray(covariances, float))
        d = self.means.shape[1]
        self._log_norm = np.log(self.weights) - np.sum(np.log(np.diagonal(self.chol, axis1=1, axis2=2)), axis=1) - 0.5 * d * np.log(2 * np.pi)

    @classmethod
    def fit(cls, u: np.ndarray, seed: int, max_components: int = 5) -> _Mixture:
        """Fit to unit-cube draws ``u`` (n, d), components 1..``max_components`` chosen by BIC,
        and add the defensive component (module docstring)."""
        from sklearn.mixture import GaussianMixture

        z = to_logit(u)
        fits = [GaussianMixture(k, covariance_type="full", reg_covar=1e-6, random_state=seed).fit(z)
                for k in range(1, min(max_components, max(1, len(z) // (4 * z.shape[1]))) + 1)]
        best = min(fits, key=lambda g: g.bic(z))
        w = np.concatenate([(1 - DEFENSIVE_WEIGHT) * best.weights_, DEFENSIVE_WEIGHT * best.weights_])
        return cls(w, np.concatenate([best.means_, best.means_]), np.concatenate([best.covariances_, DEFENSIVE_SCALE**2 * best.covariances_]))

    def sample(self, n: int, random: np.random.RandomState) -> np.ndarray:
        k = random.choice(len(self.weights), size=n, p=self.weights / self.weights.sum())
        z = self.means[k] + np.einsum("nij,nj->ni", self.chol[k], random.standard_normal((n, self.means.shape[1])))
        return from_logit(z)

    def log_density(self, u: np.ndarray) -> np.ndarray:
        from scipy.linalg import solve_triangular
        from scipy.special import logsumexp

        z = to_logit(u)
        per = np.stack([self._log_norm[k] - 0.5 * np.sum(solve_triangular(self.chol[k], (z - self.means[k]).T, lower=True) ** 2, axis=0)
                        for k in range(len(self.weights))], axis=1)
        return logsumexp(per, axis=1) - np.sum(np.log(u * (1.0 - u)), axis=1)


def _chain_moves(pilot: np.ndarray, seed: int) -> list:
    """emcee moves of the independent chains, built from pilot draws ``pilot`` (n, d) in the
    unit cube (module docstring). Both are Metropolis–Hastings moves of each walker alone, so
    every walker is its own chain."""
    import emcee

    proposal = _Mixture.fit(pilot, seed)

    def independence(coords: np.ndarray, random: np.random.RandomState) -> tuple[np.ndarray, np.ndarray]:
        new = proposal.sample(len(coords), random)
        return new, proposal.log_density(coords) - proposal.log_density(new)

    walk = WALK_SCALE * np.atleast_2d(np.cov(pilot, rowvar=False)) + 1e-12 * np.eye(pilot.shape[1])
    return [(emcee.moves.MHMove(independence), INDEPENDENCE_SHARE), (emcee.moves.GaussianMove(walk), 1.0 - INDEPENDENCE_SHARE)]


def _evaluate(venv: Any, x: np.ndarray, target_names: Sequence[str], bands: Sequence[Band]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One step of ``venv`` at the physical parameter rows ``x`` (at most its size; the rest of
    the batch repeats the last row). Returns the rows' observations of ``target_names`` (n, k),
    whether each heart is usable (status ok or not_converged, finite targets), the log of the
    prior's plausibility factor, −½ Σ_b (d_b / :data:`PLAUSIBILITY_SD`)² (module docstring), and
    each row's simulation status (:mod:`lvenv.status` names)."""
    padded = np.concatenate([x, np.repeat(x[-1:], venv.num_envs - len(x), axis=0)])
    _, _, _, _, info = venv.step(venv.unwrapped.config.actions.to_action(padded))
    obs = np.stack([np.asarray(info[k], float) for k in target_names], axis=1)[: len(x)]
    status = np.asarray(info["status"])[: len(x)]
    ok = np.isin(status, USABLE) & np.all(np.isfinite(obs), axis=1)
    log_factor = -0.5 * sum((np.asarray(distance(b, info[b.metric][: len(x)])) / PLAUSIBILITY_SD) ** 2 for b in bands)
    return obs, ok, np.broadcast_to(log_factor, (len(x),)), status


def _log_posterior(venv: Any, x: np.ndarray, patient: Patient, sigma: np.ndarray, bands: Sequence[Band]) -> tuple[np.ndarray, np.ndarray]:
    """The unnormalised log posterior at the physical rows ``x`` (one step of ``venv``, at most
    its size), −½ χ² plus the log plausibility factor, −inf for an unusable heart; and which
    hearts were usable."""
    obs, ok, log_factor, _ = _evaluate(venv, x, list(patient.targets), bands)
    value = -0.5 * np.sum(((obs - np.array(list(patient.targets.values()))) / sigma) ** 2, axis=1) + log_factor
    return np.where(ok, value, -np.inf), ok


def log_density(
    patient: Patient,
    x: np.ndarray,
    *,
    noise: Mapping[str, float | Relative] = NOISE,
    plausibility: bool | Sequence[Band] = True,
    batch: int = 32,
    steps_per_beat: int = 500,
    max_beats: int = 60,
) -> np.ndarray:
    """:func:`posterior`'s unnormalised log density at the physical rows ``x`` ((n, 6), columns
    :data:`DEFAULT_ACTION_PARAMS`), in the unit-cube coordinate where the prior is uniform: −½ χ²
    plus the log plausibility factor; −inf outside the bounds or for an unusable heart. One env
    of ``batch`` members at the posterior's settings. Comparing a point's density with that of
    the posterior's samples places it in the posterior's highest-density regions: for a truth
    drawn from the prior (:func:`prior_draws`), the fraction of samples below it is uniform."""
    from optim.fit import make_env

    x = np.atleast_2d(np.asarray(x, float))
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    inside = np.all((x >= space.lower) & (x <= space.upper), axis=1)
    sigma, bands, batch = measurement_sd(patient.targets, noise), resolve_bands(plausibility), integer("batch", batch, 1)
    venv = make_env(patient, batch, steps_per_beat, max_beats)
    venv.reset(seed=0)
    try:
        value = np.concatenate([_log_posterior(venv, x[i: i + batch], patient, sigma, bands)[0] for i in range(0, len(x), batch)])
    finally:
        venv.close()
    return np.where(inside, value, -np.inf)


#: :func:`prior_sample` gives up after this many uniform draws per requested one (it keeps about
#: 1 in 4 with the default bands).
PRIOR_TRIES = 1000


@dataclasses.dataclass(frozen=True)
class PriorSample:
    """Draws from :func:`posterior`'s prior with their noise-free observations (:func:`prior_sample`).

    ``parameters``: (n, 6), physical units, columns :data:`DEFAULT_ACTION_PARAMS`;
    ``observations``: (n, k) of ``names``, internal units; ``heart_rate``: (n,) 1/min, each draw's
    heart rate; ``base``: (n,) index of each draw's patient among those given; ``tried``: the
    uniform draws simulated; ``left_out``: how many of them were left out, by reason: a simulation
    status (:mod:`lvenv.status`) for an unusable heart, ``"nonfinite_targets"`` for a usable one
    whose targets are not finite, ``"implausible"`` for one the plausibility factor rejected.
    """

    parameters: np.ndarray
    observations: np.ndarray
    heart_rate: np.ndarray
    base: np.ndarray
    names: tuple[str, ...]
    tried: int
    left_out: dict[str, int]


def prior_sample(
    n: int,
    patients: Patient | Sequence[Patient],
    *,
    heart_rate: tuple[float, float] | None = None,
    seed: int = 0,
    batch: int = 32,
    steps_per_beat: int = 500,
    max_beats: int = 60,
    plausibility: bool | Sequence[Band] = True,
) -> PriorSample:
    """``n`` exact draws from :func:`posterior`'s prior, and the noise-free observations of the
    patients' targets at each (all ``patients`` must name the same targets).

    The prior is uniform in the unit cube of the identification bounds (log-uniform on log axes),
    times the plausibility factor exp(−½ Σ_b (d_b / :data:`PLAUSIBILITY_SD`)²), on hearts that
    simulate usably (module docstring). The factor is at most 1, so keeping a uniform draw with
    probability equal to it is exact rejection sampling. The hearts are simulated by the env that
    :func:`posterior` uses (a patient's heart with the six parameters replaced, ``batch``
    members, ``steps_per_beat``, ``max_beats``), so their observations are what its likelihood
    compares. Truths for simulation-based calibration must come from this prior: then, whatever
    the model, exact posteriors' 90 % intervals hold 90 % of them (Talts S et al.,
    arXiv:1804.06788, 2018).

    One patient without ``heart_rate``: every draw is of that patient's heart. Otherwise each
    draw's heart is one of ``patients``, uniformly at random, at a heart rate uniform in
    ``heart_rate`` = (low, high) 1/min (default: that patient's own); each batch then resets the
    env to its members' hearts first (a second simulation per member, from a cold start).
    """
    from optim.fit import make_env

    n, seed, batch = integer("n", n, 1), integer("seed", seed, 0), integer("batch", batch, 1)
    patients = [patients] if isinstance(patients, Patient) else list(patients)
    if not patients or not all(isinstance(p, Patient) for p in patients):
        raise InputError(f"patients = {patients!r} must be a Patient or a non-empty sequence of them")
    names = tuple(patients[0].targets)
    if any(tuple(p.targets) != names for p in patients):
        raise InputError(f"the patients name different targets {[tuple(p.targets) for p in patients]}; give them the same ones")
    if heart_rate is not None:
        lo, hi = (real("heart_rate", h, 20.0, 240.0) for h in heart_rate)
        if not lo < hi:
            raise InputError(f"heart_rate = ({lo:g}, {hi:g}) 1/min: the lower end must be below the upper")
    varied = heart_rate is not None or len(patients) > 1
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    bands = resolve_bands(plausibility)
    rng = np.random.default_rng(seed)
    venv = make_env(patients[0], batch, steps_per_beat, max_beats)
    venv.reset(seed=seed)
    kept: dict[str, list] = {"x": [], "obs": [], "hr": [], "base": []}
    left_out: dict[str, int] = {}
    tried = 0
    base = np.zeros(batch, int)
    rate = np.full(batch, float(patients[0].heart.get("HR")))
    try:
        while len(kept["x"]) < n:
            if tried >= PRIOR_TRIES * n:
                raise RuntimeError(f"prior_sample kept {len(kept['x'])} of {tried} uniform draws, fewer than 1 in {PRIOR_TRIES}: "
                                   f"the plausibility bands {[b.describe() for b in bands]} leave almost no usable heart inside the bounds")
            if varied:
                base = rng.integers(len(patients), size=batch)
                rate = (rng.uniform(lo, hi, batch) if heart_rate is not None
                        else np.array([float(patients[b].heart.get("HR")) for b in base]))
                members = [dataclasses.replace(patients[b], heart=patients[b].heart.replace(HR=float(h))) for b, h in zip(base, rate)]
                venv.reset(seed=seed, options={"patient": members})
            x = space.from_unit(rng.random((batch, space.dimension)))
            obs, ok, log_factor, status = _evaluate(venv, x, names, bands)
            plausible = rng.random(batch) < np.exp(log_factor)
            keep = ok & plausible
            reasons = np.where(ok, np.where(plausible, "", "implausible"), np.where(np.isin(status, USABLE), "nonfinite_targets", status))
            for reason, count in zip(*np.unique(reasons[~keep], return_counts=True)):
                left_out[str(reason)] = left_out.get(str(reason), 0) + int(count)
            for key, value in (("x", x), ("obs", obs), ("hr", rate), ("base", base)):
                kept[key].extend(value[keep])
            tried += batch
    finally:
        venv.close()
    return PriorSample(np.array(kept["x"][:n]), np.array(kept["obs"][:n]), np.array(kept["hr"][:n]), np.array(kept["base"][:n], int),
                       names, tried, left_out)


def prior_draws(
    n: int,
    patient: Patient,
    *,
    seed: int = 0,
    batch: int = 32,
    steps_per_beat: int = 500,
    max_beats: int = 60,
    plausibility: bool | Sequence[Band] = True,
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` exact draws from :func:`posterior`'s prior for ``patient``'s own heart
    (:func:`prior_sample`): (n, 6) parameters (physical units, columns
    :data:`DEFAULT_ACTION_PARAMS`) and (n, number of targets) noise-free observations (internal units)."""
    draws = prior_sample(n, patient, seed=seed, batch=batch, steps_per_beat=steps_per_beat, max_beats=max_beats, plausibility=plausibility)
    return draws.parameters, draws.observations


def posterior(
    patient: Patient,
    *,
    start: Mapping[str, float] | None = None,
    walkers: int = 64,
    steps: int = 200,
    burn: int | None = None,
    chains: int = 64,
    chain_steps: int = 1200,
    chain_burn: int | None = None,
    rounds: int = 2,
    spread: float = 0.02,
    seed: int = 0,
    noise: Mapping[str, float | Relative] = NOISE,
    steps_per_beat: int = 500,
    max_beats: int = 60,
    moves: Any = "de",
    plausibility: bool | Sequence[Band] = True,
    sampler: str = "ensemble",
    gradient_steps_per_beat: int = 500,
    max_doublings: int = 5,
) -> Posterior:
    """Sample the posterior of :data:`DEFAULT_ACTION_PARAMS` for ``patient`` (module docstring).

    Pilot: ``walkers`` × ``steps``, starting in a ball of radius ``spread`` (unit-cube units)
    around ``start`` (default: the patient's own values; a fit is better); ``burn``: its steps
    dropped (default ``steps // 2``). While the walkers' log-posterior still rises
    (:data:`CLIMB`), the pilot runs ``steps`` more, at most :data:`PILOT_EXTENSIONS` times, and
    drops the extra steps with the burn-in. ``moves``: the pilot's, ``"de"`` (default:
    differential-evolution moves, 80 % ``DEMove`` and 20 % ``DESnookerMove``, ter Braak & Vrugt
    2008) or any ``moves`` emcee takes (``None``: its stretch move). Then ``rounds`` rounds of
    ``chains`` independent chains × ``chain_steps``, ``chain_burn`` of each dropped (default
    ``chain_steps // 8``): round 1 starts at pilot draws with the proposal fitted to them, each
    later round continues the chains with the proposal refitted to the round before's draws
    (the second half of them), and the last round is the sample. Rounds before the last only
    improve the proposal and run ``chain_steps // 4`` steps. ``chains=0`` reports the pilot's walkers instead. The env has ``walkers // 2`` members
    (emcee proposes half the ensemble at a time); the chains go through it in blocks of that
    size. ``plausibility``: the filling-pressure bands in the prior factor (module docstring;
    :func:`lvenv.plausibility.resolve`).

    ``sampler="nuts"``: after the pilot, ``chains`` NUTS chains (:mod:`optim.nuts`, BlackJAX)
    start at pilot draws, in logit coordinates whitened by the pilot's mean and covariance, with
    gradients through the heart at ``gradient_steps_per_beat`` fixed steps per beat and trees of
    at most 2^``max_doublings`` leapfrog steps: ``chain_burn`` warmup iterations (default
    ``chain_steps // 2``) adapt each chain's step size and are dropped, ``chain_steps`` are kept;
    ``rounds`` does not apply. It costs far more per effective draw than the ensemble on a CPU
    (module docstring), so the ensemble is the default.
    """
    import emcee

    from optim.fit import make_env

    walkers, steps, seed = integer("walkers", walkers, 8), integer("steps", steps, 2), integer("seed", seed, 0)
    if walkers % 2:
        raise InputError(f"walkers = {walkers} must be even (emcee moves half the ensemble at a time)")
    burn = steps // 2 if burn is None else integer("burn", burn, 0, steps - 2)
    chains = integer("chains", chains, 0)
    if 0 < chains < 4:
        raise InputError(f"chains = {chains}: give 0 (the pilot's walkers are the sample) or at least 4 (split R-hat compares chains)")
    chain_steps = integer("chain_steps", chain_steps, 2)
    if sampler not in SAMPLERS:
        raise InputError(f"sampler = {sampler!r}; choose from {SAMPLERS}")
    if sampler == "nuts":
        chain_burn = chain_steps // 2 if chain_burn is None else integer("chain_burn", chain_burn, 0)
    else:
        chain_burn = chain_steps // 8 if chain_burn is None else integer("chain_burn", chain_burn, 0, chain_steps - 2)
    rounds = integer("rounds", rounds, 1)
    if sampler == "nuts" and not chains:
        raise InputError("sampler = 'nuts' needs chains >= 4 (the NUTS chains after the pilot)")
    gradient_steps_per_beat = integer("gradient_steps_per_beat", gradient_steps_per_beat, 50)
    max_doublings = integer("max_doublings", max_doublings, 1, 10)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    sigma = measurement_sd(patient.targets, noise)
    bands = resolve_bands(plausibility)
    block_size = walkers // 2
    venv = make_env(patient, block_size, steps_per_beat, max_beats)
    venv.reset(seed=seed)
    counts = {"evaluations": 0, "failed": 0}

    def log_prob(u: np.ndarray) -> np.ndarray:
        u = np.atleast_2d(u)
        inside = np.all((u >= 0.0) & (u <= 1.0), axis=1)
        x = space.from_unit(np.clip(u, 0.0, 1.0))
        out = np.full(len(u), -np.inf)
        for start_row in range(0, len(u), block_size):
            block = slice(start_row, start_row + block_size)
            value, ok = _log_posterior(venv, x[block], patient, sigma, bands)
            out[block] = np.where(inside[block], value, -np.inf)
            counts["evaluations"] += len(ok)
            counts["failed"] += int(np.sum(~ok))
        return out

    rng = np.random.default_rng(seed)
    centre = space.to_unit(space.clip(np.array([float((start or {}).get(n, patient.heart.get(n))) for n in space.names])))
    u0 = np.clip(centre + spread * rng.standard_normal((walkers, space.dimension)), 1e-6, 1 - 1e-6)
    if moves == "de":
        moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    ensemble = emcee.EnsembleSampler(walkers, space.dimension, log_prob, vectorize=True, moves=moves)
    ensemble.random_state = np.random.RandomState(seed).get_state()  # emcee's own generator, seeded
    ensemble.run_mcmc(u0, steps, progress=False)
    for _ in range(PILOT_EXTENSIONS):
        if not _climbing(ensemble.get_log_prob()):
            break
        ensemble.run_mcmc(None, steps, progress=False)
    pilot_steps = ensemble.iteration
    burn += pilot_steps - steps  # an extended pilot keeps as many steps as one of `steps`
    divergent = 0
    if chains:
        draws = ensemble.get_chain(discard=burn, flat=True)[np.isfinite(ensemble.get_log_prob(discard=burn, flat=True))]
        if len(draws) < 2 * space.dimension:
            raise RuntimeError(f"only {len(draws)} of the pilot's draws had a usable simulation; start nearer a fit (start=) or run a longer pilot")
        position = draws[rng.choice(len(draws), size=chains, replace=len(draws) < chains)]
    if sampler == "nuts":
        venv.close()
        from optim.nuts import LogDensity, run_nuts

        z = to_logit(draws)
        mean, chol = z.mean(axis=0), np.linalg.cholesky(np.cov(z, rowvar=False) + 1e-9 * np.eye(space.dimension))
        density = LogDensity(patient, space, sigma, bands, PLAUSIBILITY_SD, mean, chol, gradient_steps_per_beat, max_beats)
        run = run_nuts(density, np.linalg.solve(chol, (to_logit(position) - mean).T).T, warmup=chain_burn, draws=chain_steps, seed=seed,
                       max_doublings=max_doublings)
        chain = density.unit(run["positions"])
        tau = emcee.autocorr.integrated_time(chain, quiet=True)
        acceptance = float(np.mean(run["acceptance"][chain_burn:]))
        counts["evaluations"] += density.evaluations
        counts["failed"] += density.failed
        divergent = int(np.sum(run["divergent"]))
    else:
        if chains:
            for r in range(rounds):
                last = r == rounds - 1
                ensemble = emcee.EnsembleSampler(chains, space.dimension, log_prob, vectorize=True, moves=_chain_moves(draws, seed + r))
                ensemble.random_state = np.random.RandomState(seed + 1 + r).get_state()
                n = chain_steps if last else max(2, chain_steps // 4)
                ensemble.run_mcmc(position, n, progress=False, skip_initial_state_check=True)  # chains need no spread
                draws, position = ensemble.get_chain(discard=n // 2, flat=True), ensemble.get_last_sample().coords
            burn = chain_burn
        venv.close()
        chain = ensemble.get_chain(discard=burn)  # (kept steps, walkers or chains, k), unit cube
        tau = ensemble.get_autocorr_time(discard=burn, quiet=True)
        acceptance = float(np.mean(ensemble.acceptance_fraction))
    physical = space.from_unit(chain)
    kept = chain.shape[0] * chain.shape[1]
    samples = {n: physical[..., j].T.reshape(-1) for j, n in enumerate(space.names)}
    return Posterior(
        samples=samples,
        median={n: float(np.median(v)) for n, v in samples.items()},
        interval_90={n: (float(np.percentile(v, 5)), float(np.percentile(v, 95))) for n, v in samples.items()},
        acceptance=acceptance,
        autocorr_time={n: float(t) for n, t in zip(space.names, tau)},
        ess={n: float(kept / t) for n, t in zip(space.names, tau)},
        rhat={n: _split_rhat(chain[..., j].T) for j, n in enumerate(space.names)},
        evaluations=counts["evaluations"],
        failed=counts["failed"],
        pilot_steps=pilot_steps,
        sampler=sampler,
        divergent=divergent,
    )


def amortised(
    patients: Patient | Sequence[Patient],
    n_samples: int = 1000,
    *,
    seed: int = 0,
    estimator: Any = None,
) -> list[Posterior]:
    """The amortised posterior of each patient (:mod:`optim.amortised`): ``n_samples`` draws of
    the trained flow given its targets (any subset of :data:`optim.amortised.OBSERVED`, internal
    units) and its heart's rate, in one batched pass for all patients. One :class:`Posterior` per
    patient (``sampler="amortised"``), in order; ``out_of_distribution`` says why a patient's
    observation lies outside the training set (:meth:`optim.amortised.Estimator.out_of_distribution`),
    and its samples are then not to be trusted. ``estimator``: an
    :class:`optim.amortised.Estimator` or an artefact path (default: the shipped artefact).
    :class:`InputError` for a target the estimator does not take or a heart that is none of its
    base presets (up to the six parameters and the heart rate)."""
    from optim import amortised as amortised_module

    patients = [patients] if isinstance(patients, Patient) else list(patients)
    if not patients or not all(isinstance(p, Patient) for p in patients):
        raise InputError(f"patients must be a Patient or a non-empty list of them, got {patients!r}")
    n_samples, seed = integer("n_samples", n_samples, 8), integer("seed", seed, 0)
    if not isinstance(estimator, amortised_module.Estimator):
        estimator = amortised_module.load(amortised_module.DEFAULT_ARTEFACT if estimator is None else estimator)
    obs = np.stack([amortised_module.observations(p) for p in patients])
    heart_rate = np.array([float(p.heart.get("HR")) for p in patients])
    base = np.array([amortised_module.base_index(p.heart, estimator.bases) for p in patients])
    reasons = estimator.out_of_distribution(obs, heart_rate)
    draws = estimator.sample(obs, heart_rate, base, n_samples, seed)
    names = DEFAULT_ACTION_PARAMS
    out = []
    for x, reason in zip(draws, reasons):
        samples = {n: x[:, j] for j, n in enumerate(names)}
        blocks = x[: n_samples // 4 * 4].reshape(4, -1, len(names))
        out.append(Posterior(
            samples=samples,
            median={n: float(np.median(v)) for n, v in samples.items()},
            interval_90={n: (float(np.percentile(v, 5)), float(np.percentile(v, 95))) for n, v in samples.items()},
            acceptance=float("nan"),
            autocorr_time=dict.fromkeys(names, 1.0),
            ess=dict.fromkeys(names, float(n_samples)),
            rhat={n: _split_rhat(blocks[..., j]) for j, n in enumerate(names)},
            evaluations=0,
            failed=0,
            pilot_steps=0,
            sampler="amortised",
            out_of_distribution=reason,
        ))
    return out


#: The sampler's size settings that scripts expose as options (``--chain-steps`` for
#: ``chain_steps``), with their help; the defaults are :func:`posterior`'s own.
SAMPLER_SETTINGS = {
    "walkers": "the pilot ensemble's walkers",
    "steps": "the pilot's steps",
    "chains": "independent chains after the pilot (0: the pilot's walkers are the sample)",
    "chain_steps": "steps of each chain in the last round (NUTS: kept iterations of each chain)",
}


def add_sampler_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--sampler`` (:data:`SAMPLERS`) and :data:`SAMPLER_SETTINGS` to ``parser``, the
    latter as integer options, all with :func:`posterior`'s defaults."""
    defaults = inspect.signature(posterior).parameters
    parser.add_argument("--sampler", choices=SAMPLERS, default=defaults["sampler"].default,
                        help="what samples after the pilot: independent MH chains or NUTS through the heart (default %(default)s)")
    for name, text in SAMPLER_SETTINGS.items():
        parser.add_argument("--" + name.replace("_", "-"), type=int, default=defaults[name].default, help=f"{text} (default %(default)s)")


def sampler_options(args: argparse.Namespace) -> dict[str, Any]:
    """``sampler`` and the :data:`SAMPLER_SETTINGS` of parsed ``args``, as keywords of :func:`posterior`."""
    return {"sampler": args.sampler, **{name: getattr(args, name) for name in SAMPLER_SETTINGS}}


def probability_lower(a: Posterior, b: Posterior, name: str) -> float:
    """P(θ_a < θ_b) for parameter ``name`` of two patients with independent posteriors, over all
    pairs of one sample of each (exact for the two sample sets)."""
    other = np.sort(b.samples[name])
    above = len(other) - np.searchsorted(other, a.samples[name], side="right")  # b-samples above each a-sample
    return float(np.sum(above) / (len(a.samples[name]) * len(other)))


def _bound_text(value: float | None, side: str) -> str:
    return f"{value:.4g}" if value is not None else f"({side} bound)"


def write_report(
    patient: Patient,
    fit: Mapping[str, float],
    observation: Mapping[str, float],
    out_dir: str | pathlib.Path,
    *,
    grid: int = 7,
    options: CohortOptions | None = None,
    posterior_options: Mapping[str, Any] | None = None,
    noise: Mapping[str, float | Relative] = NOISE,
) -> pathlib.Path:
    """Per-patient identifiability report at the fit ``fit`` (parameters by name, physical units),
    whose steady-state metrics are ``observation`` (by name, internal units: a fit result's
    ``observation``; the report gives χ² at the fit from it).

    Writes to ``out_dir``: ``identifiability.md`` (targets and their σ, the fit, the sensitivity's
    singular values and null directions, each parameter's profile class and 95 % interval, the
    posterior's medians, 90 % intervals and diagnostics), ``profiles.png``
    (:func:`lvenv.plots.profile_figure`), ``posterior_pairs.png`` (:func:`lvenv.plots.pairs_figure`)
    and ``identifiability.json`` (every number, internal units). ``grid`` and ``options``: of
    :func:`profile`; ``posterior_options``: keywords of :func:`posterior`. Returns the markdown's
    path. Takes a few minutes on 2 cores with the defaults (mostly the posterior).
    """
    from lvenv.plots import pairs_figure, profile_figure

    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    fit = {n: float(fit[n]) for n in space.names}
    log = dict(zip(space.names, space.log))
    prof = profile(patient, grid=grid, fit=fit, noise=noise, options=options)
    post = posterior(patient, start=fit, noise=noise, **dict(posterior_options or {}))
    profile_figure(prof.grid, prof.chi2, prof.chi2_min, out / "profiles.png", DELTA_95, log=log, best=fit)
    pairs_figure({patient.name: post.samples}, out / "posterior_pairs.png", log=log)
    sigma = dict(zip(patient.targets, measurement_sd(patient.targets, noise)))
    lines = [f"# Identifiability of {patient.name}", "",
             "Internal units (s, ml, kPa). Measurement model, priors and methods: `optim.identify`.", "",
             "| target | value | σ |", "|---|---|---|",
             *(f"| {k} | {v:.4g} | {sigma[k]:.3g} |" for k, v in patient.targets.items()), "",
             "## Fit", "", "| parameter | value | units |", "|---|---|---|",
             *(f"| {n} | {fit[n]:.4g} | {ACTION_BOUNDS[n].units} |" for n in space.names), "",
             f"χ² at the fit: {chi2(patient, observation, noise):.3g}", "",
             "## Sensitivity at the fit", ""]
    sens = prof.sensitivity
    if sens is None:
        lines += ["No usable steady state at the fit: no sensitivity.", ""]
    else:
        lines += ["Singular values of diag(1/σ) dM/du (χ per unit-cube step): " + ", ".join(f"{v:.3g}" for v in sens.singular_values), ""]
        lines += [f"* null direction {j + 1}: " + ", ".join(f"{n} {v:+.2f}" for n, v in d.items()) for j, d in enumerate(sens.null_directions)]
        lines += [""]
    lines += ["## Profile likelihoods", "",
              f"{grid} constrained fits per parameter over its bound; Δχ² = {DELTA_95} marks the 95 % interval. ![profiles](profiles.png)", "",
              "| parameter | class | 95 % interval (outer grid points) | profile range (Δχ²) |", "|---|---|---|---|"]
    for n in space.names:
        lo, hi = prof.interval[n]
        values = prof.chi2[n]
        spread = f"{np.nanmax(values) - np.nanmin(values):.3g}" if np.isfinite(values).any() else "—"
        lines.append(f"| {n} | {prof.classification[n]} | [{_bound_text(lo, 'lower')}, {_bound_text(hi, 'upper')}] | {spread} |")
    lines += ["", "## Posterior", "",
              f"{post.evaluations} evaluations ({post.failed} failed), acceptance {post.acceptance:.2f}. ![posterior pairs](posterior_pairs.png)", "",
              "| parameter | median | 90 % interval | split R-hat | ESS |", "|---|---|---|---|---|"]
    for n in space.names:
        lo, hi = post.interval_90[n]
        lines.append(f"| {n} | {post.median[n]:.4g} | [{lo:.4g}, {hi:.4g}] | {post.rhat[n]:.3f} | {post.ess[n]:.0f} |")
    if max(post.rhat.values()) >= 1.01:
        lines += ["", f"**Not converged**: split R-hat up to {max(post.rhat.values()):.3f} (≥ 1.01); run longer chains (`chain_steps`)."]
    path = out / "identifiability.md"
    path.write_text("\n".join(lines) + "\n")
    sens_dict = None if sens is None else {"singular_values": sens.singular_values.tolist(), "null_directions": sens.null_directions}
    (out / "identifiability.json").write_text(json.dumps({"patient": patient.name, "targets": patient.targets, "noise": sigma, "fit": fit,
                                                          "sensitivity": sens_dict, "profiles": prof.to_dict(), "posterior": post.to_dict()},
                                                         indent=2, default=float))
    return path

