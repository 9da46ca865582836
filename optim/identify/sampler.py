"""Sampling a patient's posterior (:mod:`optim.identify.density`): MCMC through the batched heart,
or the amortised flow of :mod:`optim.amortised`.

:func:`posterior` samples, in two stages:

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
below 1.01 in the README's runs of the built-in patients. :func:`probability_lower` compares two
patients' posteriors.

:func:`amortised`: the posterior of any number of patients from the trained flow of
:mod:`optim.amortised` (same prior, noise and observation model), one batched pass, with an
out-of-distribution flag; :func:`~optim.identify.prior_sample` draws its training pairs. With
``importance`` the flow's draws are a proposal, reweighted by this module's exact posterior
density (one simulation each, Pareto-smoothed importance sampling) and resampled, with the
weights' Pareto k̂ as the flag.
:func:`identify_patients` (the CLI's and the cohort's ``--posterior amortised``) does that for
a list of patients and runs :func:`posterior` for those flagged, with ``refine``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace, from_logit, to_logit
from lvenv.patients import Patient
from lvenv.plausibility import Band
from lvenv.plausibility import resolve as resolve_bands
from lvenv.validation import InputError, integer, real
from optim.fit import make_env
from optim.identify.density import PLAUSIBILITY_SD, _log_posterior, log_density
from optim.identify.noise import NOISE, Relative, measurement_sd
from optim.nuts import LogDensity, run_nuts

__all__ = ["Posterior", "SAMPLERS", "CLIMB", "PILOT_EXTENSIONS", "PARETO_K", "IMPORTANCE_BATCH", "posterior", "amortised", "probability_lower", "Identified", "identify_patients"]


@dataclasses.dataclass(frozen=True)
class Posterior:
    """Posterior samples by parameter name (physical units, burn-in removed, walkers × steps
    flattened), their medians and 90 % credible intervals, and the diagnostics (module docstring).
    ``pilot_steps``: the pilot's steps, more than ``steps`` where it was extended (:data:`CLIMB`).
    From :func:`amortised` (``sampler="amortised"``) the samples are independent draws of the
    flow: no acceptance (NaN), autocorrelation time 1, ESS the number of samples, and the split
    R-hat of four consecutive blocks of them; importance-weighted (``sampler="importance"``), ESS
    is the weights' effective sample size and ``pareto_k`` their Pareto k̂."""

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
    pareto_k: float = float("nan")  # importance-weighted amortised posteriors: the weights' Pareto k̂ (NaN otherwise)

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if k != "samples"}

    @property
    def weights_ess(self) -> float:
        """An importance-weighted posterior's effective sample size of its weights (one number,
        :attr:`ess` of every parameter); NaN for the other samplers."""
        return next(iter(self.ess.values())) if self.sampler == "importance" else float("nan")

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


#: Largest Pareto k̂ of trustworthy importance weights (Vehtari A et al., JMLR 25:72, 2024: the
#: smoothed estimate is reliable for k̂ < min(1 − 1/log10 S, 0.7) with S draws).
PARETO_K = 0.7
#: Members of the env that simulates the importance proposals (:func:`amortised`).
IMPORTANCE_BATCH = 500


def amortised(
    patients: Patient | Sequence[Patient],
    n_samples: int = 1000,
    *,
    seed: int = 0,
    estimator: Any = None,
    importance: int = 0,
) -> list[Posterior]:
    """The amortised posterior of each patient (:mod:`optim.amortised`): ``n_samples`` draws of
    the trained flow given its targets (any subset of :data:`optim.amortised.OBSERVED`, internal
    units) and its heart's rate, in one batched pass for all patients. One :class:`Posterior` per
    patient (``sampler="amortised"``), in order; ``out_of_distribution`` says why a patient's
    observation lies outside the training set (:meth:`optim.amortised.Estimator.out_of_distribution`),
    and its samples are then not to be trusted. ``estimator``: an
    :class:`optim.amortised.Estimator` or an artefact path (default: the shipped artefact).
    :class:`InputError` for a target the estimator does not take or a heart it does not cover
    (:func:`optim.amortised.covered_geometry`: its base presets, and with the anatomy kind any
    geometry in the anatomy box with the regression's maps, up to the six parameters and the
    heart rate).

    ``importance`` > 0: the flow is a proposal, not the answer (``sampler="importance"``). It
    draws ``importance`` parameter sets per patient, each heart is simulated once
    (:func:`optim.identify.log_density`, :data:`IMPORTANCE_BATCH` at a time: about 1–2 s per
    patient for 2,000), and each draw is weighted by the posterior's density over the flow's
    (:meth:`optim.amortised.Estimator.log_density`), Pareto-smoothed (PSIS, Vehtari et al. 2024,
    ``arviz_stats``); ``n_samples`` are resampled from them (systematic resampling). So the
    samples follow the same posterior as :func:`posterior`'s MCMC, up to the weights' Monte-Carlo
    error, whatever the flow's own error. ``ess`` is the weights' effective sample size,
    ``evaluations`` and ``failed`` count the simulations, and ``pareto_k`` is k̂: above
    :data:`PARETO_K` the weights are unreliable (the flow misses part of the posterior), and the
    patient is flagged through ``out_of_distribution``."""
    from optim import amortised as amortised_module

    patients = [patients] if isinstance(patients, Patient) else list(patients)
    if not patients or not all(isinstance(p, Patient) for p in patients):
        raise InputError(f"patients must be a Patient or a non-empty list of them, got {patients!r}")
    n_samples, seed = integer("n_samples", n_samples, 8), integer("seed", seed, 0)
    importance = integer("importance", importance, 0)
    if 0 < importance < n_samples:
        raise InputError(f"importance = {importance}: give 0 (no reweighting) or at least n_samples = {n_samples} proposals per patient")
    if not isinstance(estimator, amortised_module.Estimator):
        estimator = amortised_module.load(amortised_module.DEFAULT_ARTEFACT if estimator is None else estimator)
    obs = np.stack([amortised_module.observations(p) for p in patients])
    heart_rate = np.array([float(p.heart.get("HR")) for p in patients])
    geometry = np.stack([amortised_module.covered_geometry(p.heart, estimator.bases) for p in patients])
    reasons = estimator.out_of_distribution(obs, heart_rate)
    draws = estimator.sample(obs, heart_rate, geometry, importance or n_samples, seed)
    names = DEFAULT_ACTION_PARAMS
    out = []
    for j, (x, reason) in enumerate(zip(draws, reasons)):
        ess, evaluations, failed, pareto_k = float(n_samples), 0, 0, float("nan")
        if importance:
            log_q = estimator.log_density(x, np.repeat(obs[j: j + 1], len(x), axis=0), np.full(len(x), heart_rate[j]),
                                          np.repeat(geometry[j: j + 1], len(x), axis=0))
            log_p = log_density(patients[j], x, batch=min(importance, IMPORTANCE_BATCH))
            x, ess, pareto_k = _importance_resample(x, log_p - log_q, n_samples, np.random.default_rng([seed, j]))
            evaluations, failed = len(log_p), int(np.sum(~np.isfinite(log_p)))
            limit = min(1.0 - 1.0 / np.log10(importance), PARETO_K)
            if not pareto_k < limit:
                text = f"importance weights unreliable (Pareto k {pareto_k:.2f}, above {limit:.2f}): the flow misses part of this posterior"
                reason = "; ".join(filter(None, [reason, text]))
        samples = {n: x[:, k] for k, n in enumerate(names)}
        blocks = x[: n_samples // 4 * 4].reshape(4, -1, len(names))
        out.append(Posterior(
            samples=samples,
            median={n: float(np.median(v)) for n, v in samples.items()},
            interval_90={n: (float(np.percentile(v, 5)), float(np.percentile(v, 95))) for n, v in samples.items()},
            acceptance=float("nan"),
            autocorr_time=dict.fromkeys(names, 1.0),
            ess=dict.fromkeys(names, ess),
            rhat={n: _split_rhat(blocks[..., k]) for k, n in enumerate(names)},
            evaluations=evaluations,
            failed=failed,
            pilot_steps=0,
            sampler="importance" if importance else "amortised",
            out_of_distribution=reason,
            pareto_k=pareto_k,
        ))
    return out


def _importance_resample(x: np.ndarray, log_w: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, float, float]:
    """``n`` rows of ``x`` resampled by their log importance weights ``log_w`` (−inf: weight 0),
    Pareto-smoothed (``arviz_stats``' PSIS, which takes the negated log weights), systematically
    and in random order; with the weights' effective sample size and Pareto k̂. No usable row:
    ``x``'s first ``n`` rows as they are, ESS 0 and k̂ inf."""
    from arviz_stats.base import array_stats

    usable = np.flatnonzero(np.isfinite(log_w))
    if len(usable) < 2:
        return x[:n], 0.0, float("inf")
    smoothed, pareto_k = array_stats.psislw(-log_w[usable])
    w = np.exp(smoothed - np.max(smoothed))
    w /= w.sum()
    picks = np.searchsorted(np.cumsum(w), (rng.random() + np.arange(n)) / n, side="right").clip(max=len(w) - 1)
    return x[usable[rng.permutation(picks)]], float(1.0 / np.sum(w ** 2)), float(pareto_k)


def probability_lower(a: Posterior, b: Posterior, name: str) -> float:
    """P(θ_a < θ_b) for parameter ``name`` of two patients with independent posteriors, over all
    pairs of one sample of each (exact for the two sample sets)."""
    other = np.sort(b.samples[name])
    above = len(other) - np.searchsorted(other, a.samples[name], side="right")  # b-samples above each a-sample
    return float(np.sum(above) / (len(a.samples[name]) * len(other)))


@dataclasses.dataclass(frozen=True)
class Identified:
    """One patient's posterior as :func:`identify_patients` reports it.

    ``posterior``: the amortised one (``sampler="amortised"``), the MCMC one where ``refined``,
    or None for a patient the estimator does not cover and that was not refined. ``flag``: why
    the amortised answer is not to be trusted (outside the training distribution, or not covered
    by the estimator at all); ``""`` when it is. A refined patient keeps its flag."""

    patient: str
    posterior: Any  # optim.identify.Posterior | None
    flag: str
    refined: bool


def identify_patients(
    patients: Sequence[Patient],
    n_samples: int = 1000,
    *,
    seed: int = 0,
    estimator: Any = None,
    refine: bool = False,
    mcmc_options: Mapping[str, Any] | None = None,
    progress: Any = None,
    importance: int = 0,
) -> list[Identified]:
    """The amortised posterior of every patient (:func:`amortised`, one batched
    pass; ``importance`` proposals per patient reweighted by the exact posterior where > 0), and with ``refine`` the MCMC posterior (:func:`optim.identify.posterior`, keywords
    ``mcmc_options``) of each flagged one instead. ``estimator``: as :func:`amortised` takes it.

    A patient the estimator does not cover (a target it does not condition on, such as EDV, or a
    heart that is none of its base presets) is flagged with the reason rather than refused, so
    one such patient never stops a cohort. MCMC starts from the amortised median where there is
    one (:func:`optim.identify.posterior` takes one start point, its walkers start in a small
    ball around it), else from the patient's own values. ``progress(done, total, name)`` is
    called before each MCMC run (about 100 s each on 2 cores). One :class:`Identified` per
    patient, in order."""
    from optim.amortised import DEFAULT_ARTEFACT, Estimator, covered_geometry, load, observations

    patients = list(patients)
    if not isinstance(estimator, Estimator):
        estimator = load(DEFAULT_ARTEFACT if estimator is None else estimator)
    covered, flags = [], [""] * len(patients)
    for j, p in enumerate(patients):
        try:
            observations(p)
            covered_geometry(p.heart, estimator.bases)
            covered.append(j)
        except InputError as err:
            flags[j] = f"not covered by the amortised estimator: {err}"
    posteriors: list[Any] = [None] * len(patients)
    if covered:
        for j, post in zip(covered, amortised([patients[j] for j in covered], n_samples, seed=seed, estimator=estimator, importance=importance)):
            posteriors[j], flags[j] = post, post.out_of_distribution
    refined = [False] * len(patients)
    if refine:
        todo = [j for j, f in enumerate(flags) if f]
        for done, j in enumerate(todo):
            if progress is not None:
                progress(done, len(todo), patients[j].name)
            start = None if posteriors[j] is None else posteriors[j].median
            posteriors[j] = dataclasses.replace(posterior(patients[j], start=start, seed=seed, **dict(mcmc_options or {})),
                                                out_of_distribution=flags[j])
            refined[j] = True
    return [Identified(p.name, post, flag, r) for p, post, flag, r in zip(patients, posteriors, flags, refined)]
