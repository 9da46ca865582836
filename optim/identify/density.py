"""The posterior's density and its prior, evaluated through the batched vector env.

p(θ | targets) ∝ exp(−χ²(θ)/2) · prior(θ), with χ² of :mod:`optim.identify.noise` and the prior
uniform in the unit cube of the identification bounds (log-uniform on log axes: weak, inside the
physical bounds), times the factor exp(−½ Σ_b (d_b / 5 mmHg)²) over the bands b of every other
method's objective (:mod:`lvenv.plausibility`: d_b is how far the mean aortic pressure lies
outside 80–120 mmHg and, with ``plausibility`` (default), the mean atrial pressure or EDP outside
4–25 mmHg; 5 mmHg is the pressure σ of :data:`~optim.identify.NOISE`, :data:`PLAUSIBILITY_SD`).
Without the aortic band the posterior spread along the τ2–Sa ridge into hearts no other method
would accept, and the 90 % intervals of synthetic truths drawn inside it missed the truth too
often (``scripts/calibration.py``). Each evaluation is one step of a vector env
(:func:`optim.fit.make_env`), so a batch of parameter sets runs through the batched heart.

Calibration: :func:`prior_draws` (and :func:`prior_sample`, which also varies the heart and its
rate, for :mod:`optim.amortised`) draws truths from this prior exactly (rejection sampling), with
their observations from the posterior's env; :func:`log_density` evaluates the unnormalised
posterior density at any parameters, to rank a truth among the samples
(``scripts/calibration.py``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.patients import Patient
from lvenv.plausibility import Band, distance
from lvenv.plausibility import resolve as resolve_bands
from lvenv.status import USABLE
from lvenv.units import mmhg_to_kpa
from lvenv.validation import InputError, integer, real
from optim.fit import make_env
from optim.identify.noise import NOISE, Relative, measurement_sd

__all__ = ["PLAUSIBILITY_SD", "PRIOR_TRIES", "ARRAYS", "PriorSample", "prior_sample", "prior_draws", "log_density"]


#: Standard deviation (kPa) of the posterior's plausibility factor: 5 mmHg outside a filling band
#: costs as much as a pressure measured 1 σ off.
PLAUSIBILITY_SD = float(mmhg_to_kpa(5.0))


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
    """:func:`~optim.identify.posterior`'s unnormalised log density at the physical rows ``x`` ((n, 6), columns
    :data:`DEFAULT_ACTION_PARAMS`), in the unit-cube coordinate where the prior is uniform: −½ χ²
    plus the log plausibility factor; −inf outside the bounds or for an unusable heart. One env
    of ``batch`` members at the posterior's settings. Comparing a point's density with that of
    the posterior's samples places it in the posterior's highest-density regions: for a truth
    drawn from the prior (:func:`prior_draws`), the fraction of samples below it is uniform."""
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


#: The per-draw arrays of a :class:`PriorSample`, in field order.
ARRAYS = ("parameters", "observations", "heart_rate", "base", "geometry")


@dataclasses.dataclass(frozen=True)
class PriorSample:
    """Draws from :func:`~optim.identify.posterior`'s prior with their noise-free observations (:func:`prior_sample`).

    ``parameters``: (n, 6), physical units, columns :data:`DEFAULT_ACTION_PARAMS`;
    ``observations``: (n, k) of ``names``, internal units; ``heart_rate``: (n,) 1/min, each draw's
    heart rate; ``base``: (n,) index of each draw's patient among those given; ``geometry``: (n, 6)
    the unloaded geometry of each draw's heart (:class:`lvenv.geometry.Geometry` fields, mm and
    degrees); ``tried``: the
    uniform draws simulated; ``left_out``: how many of them were left out, by reason: a simulation
    status (:mod:`lvenv.status`) for an unusable heart, ``"nonfinite_targets"`` for a usable one
    whose targets are not finite, ``"implausible"`` for one the plausibility factor rejected.
    """

    parameters: np.ndarray
    observations: np.ndarray
    heart_rate: np.ndarray
    base: np.ndarray
    geometry: np.ndarray
    names: tuple[str, ...]
    tried: int
    left_out: dict[str, int]

    @classmethod
    def concatenate(cls, parts: Sequence[PriorSample]) -> PriorSample:
        """One sample of all ``parts`` (draws of the same targets over the same patients), in order;
        ``tried`` and ``left_out`` are summed."""
        if not parts or any(p.names != parts[0].names for p in parts):
            raise InputError(f"cannot concatenate prior samples of different targets {[p.names for p in parts]}")
        left_out: dict[str, int] = {}
        for part in parts:
            for reason, count in part.left_out.items():
                left_out[reason] = left_out.get(reason, 0) + count
        arrays = (np.concatenate([getattr(p, f) for p in parts]) for f in ARRAYS)
        return cls(*arrays, parts[0].names, sum(p.tried for p in parts), left_out)


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
    """``n`` exact draws from :func:`~optim.identify.posterior`'s prior, and the noise-free observations of the
    patients' targets at each (all ``patients`` must name the same targets).

    The prior is uniform in the unit cube of the identification bounds (log-uniform on log axes),
    times the plausibility factor exp(−½ Σ_b (d_b / :data:`PLAUSIBILITY_SD`)²), on hearts that
    simulate usably (module docstring). The factor is at most 1, so keeping a uniform draw with
    probability equal to it is exact rejection sampling. The hearts are simulated by the env that
    :func:`~optim.identify.posterior` uses (a patient's heart with the six parameters replaced, ``batch``
    members, ``steps_per_beat``, ``max_beats``), so their observations are what its likelihood
    compares. Truths for simulation-based calibration must come from this prior: then, whatever
    the model, exact posteriors' 90 % intervals hold 90 % of them (Talts S et al.,
    arXiv:1804.06788, 2018).

    One patient without ``heart_rate``: every draw is of that patient's heart. Otherwise each
    draw's heart is one of ``patients``, uniformly at random, at a heart rate uniform in
    ``heart_rate`` = (low, high) 1/min (default: that patient's own); each batch then resets the
    env to its members' hearts first (a second simulation per member, from a cold start).
    """
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
    base = np.array(kept["base"][:n], int)
    shapes = np.array([p.heart.geometry.as_tuple() for p in patients], float)
    return PriorSample(np.array(kept["x"][:n]), np.array(kept["obs"][:n]), np.array(kept["hr"][:n]), base, shapes[base].reshape(len(base), -1),
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
    """``n`` exact draws from :func:`~optim.identify.posterior`'s prior for ``patient``'s own heart
    (:func:`prior_sample`): (n, 6) parameters (physical units, columns
    :data:`DEFAULT_ACTION_PARAMS`) and (n, number of targets) noise-free observations (internal units)."""
    draws = prior_sample(n, patient, seed=seed, batch=batch, steps_per_beat=steps_per_beat, max_beats=max_beats, plausibility=plausibility)
    return draws.parameters, draws.observations
