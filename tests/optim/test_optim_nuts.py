"""NUTS through the heart (optim.nuts): the sampler on a known density, the log-density's gradient
against central differences of its own value, and a small posterior run end to end."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.patients import builtin
from lvenv.plausibility import resolve
from lvenv.validation import InputError
from optim.identify import NOISE, PLAUSIBILITY_SD, measurement_sd, posterior
from optim.nuts import LogDensity, as_jax, run_nuts


def test_nuts_chains_sample_a_known_gaussian_through_the_host_callback():
    """log p(w) = −½ (w − μ)ᵀ P (w − μ) on the host: the kept draws of 8 chains have its mean and
    covariance, so the callback's value, its gradient (custom VJP) and the step-size adaptation fit."""
    mu = np.array([1.0, -2.0, 0.5])
    cov = np.array([[1.0, 0.6, 0.0], [0.6, 2.0, -0.3], [0.0, -0.3, 0.5]])
    precision = np.linalg.inv(cov)
    calls = []

    def host(w):
        calls.append(len(w))
        r = w - mu
        return -0.5 * np.einsum("ni,ij,nj->n", r, precision, r), -r @ precision

    run = run_nuts(host, np.zeros((8, 3)), warmup=150, draws=400, seed=0)
    draws = run["positions"].reshape(-1, 3)
    assert run["positions"].shape == (400, 8, 3)
    assert set(calls) == {8}, "each leapfrog step of all chains is one batched host call"
    assert 0.6 < np.mean(run["acceptance"][150:]) <= 1.0
    se = np.sqrt(np.diag(cov) / len(draws) * 10)  # draws are correlated: ESS >= n / 10 here
    assert np.all(np.abs(draws.mean(axis=0) - mu) < 4 * se)
    assert np.allclose(np.cov(draws, rowvar=False), cov, atol=0.25)
    assert not run["divergent"].any()


def test_log_density_gradient_matches_central_differences_of_its_value():
    """The chain rule behind the NUTS gradient: whitening, the logit, the unit-cube map and a band
    that is active (mean atrial pressure above a deliberately low limit)."""
    patient = builtin("normal")
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    x = np.array([float(patient.heart.get(n)) for n in space.names])
    u = space.to_unit(space.clip(x))
    rng = np.random.default_rng(4)
    chol = np.tril(0.05 * rng.standard_normal((6, 6))) + 0.2 * np.eye(6)
    # the posterior's bands (so the compiled tangents are the next test's), the atrial one
    # narrowed below the preset's filling pressure so that it is active
    bands = tuple(dataclasses.replace(b, low=0.1, high=0.5) if b.metric == "P_at_mean" else b for b in resolve(True))
    density = LogDensity(patient, space, measurement_sd(patient.targets, NOISE), bands, PLAUSIBILITY_SD, np.log(u) - np.log1p(-u), chol, 1000, 60)
    directions = rng.standard_normal((3, 6))
    h = 1e-3
    points = np.vstack([np.zeros(6), h * directions, -h * directions])
    log_density = as_jax(density)  # as NUTS calls it: through the host callback and the custom VJP
    logp = np.asarray(jax.vmap(log_density)(jnp.asarray(points)))
    grad = np.asarray(jax.grad(log_density)(jnp.zeros(6)))
    assert np.all(np.isfinite(logp)) and density.evaluations == 8 and density.calls == 2 and density.failed == 0
    numeric = (logp[1:4] - logp[4:7]) / (2 * h)
    assert grad @ directions.T == pytest.approx(numeric, rel=0.05, abs=0.05)
    assert np.max(np.abs(grad)) > 1.0, "the band and the targets give a gradient well above the tolerance"


def test_nuts_posterior_runs_chains_through_the_heart_and_reports_them():
    patient = builtin("normal")
    post = posterior(patient, walkers=16, steps=4, chains=4, chain_steps=4, chain_burn=2, sampler="nuts", max_doublings=1,
                     steps_per_beat=250, gradient_steps_per_beat=1000, max_beats=60, seed=1)
    assert post.sampler == "nuts" and post.pilot_steps in (4, 8, 12, 16)
    # the pilot's evaluations, then at least one batched gradient per chain and iteration (init + 6 iterations)
    assert post.evaluations >= 16 * (1 + post.pilot_steps) + 4 * 7
    assert 0 <= post.divergent <= 4 * 4 and 0.0 <= post.acceptance <= 1.0
    for name, values in post.samples.items():
        bound = ACTION_BOUNDS[name]
        assert values.shape == (4 * 4,) and np.all((values >= bound.lo) & (values <= bound.hi))
    assert set(post.rhat) == set(post.ess) == set(DEFAULT_ACTION_PARAMS)
    with pytest.raises(InputError, match="sampler = 'hmc'"):
        posterior(patient, sampler="hmc")
    with pytest.raises(InputError, match="needs chains"):
        posterior(patient, sampler="nuts", chains=0)
