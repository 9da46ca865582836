"""`optim.identify`: the sensitivity's null directions and profile likelihoods whose every point
is a real constrained fit, checked by an independent simulation."""

import dataclasses

import numpy as np
import pytest

import lvenv
from lvenv.identification import ACTION_BOUNDS
from lvenv.patients import builtin
from optim.cohort import CohortOptions
from optim.identify import DELTA_95, chi2, profile, sensitivity

STEPS = 250


def test_null_directions_change_no_target_and_four_targets_leave_two_of_them():
    patient = builtin("normal")
    sens = sensitivity(patient, steps_per_beat=STEPS)
    assert sens.matrix.shape == (4, 6) and len(sens.null_directions) == 2
    for direction in sens.null_directions:
        v = np.array([direction[n] for n in sens.names])
        assert np.linalg.norm(v) == pytest.approx(1.0)
        assert np.linalg.norm(sens.matrix @ v) <= 1e-3 * sens.singular_values[0]
    assert all(0.0 <= sens.null_component(n) <= 1.0 + 1e-12 for n in sens.names)


def test_profile_interval_spans_every_point_below_the_threshold():
    """A constrained fit can only stall above the true profile, so a high point between two low
    ones does not end the interval; NaN (failed) points are skipped."""
    from optim.identify.profiles import _interval

    grid = np.arange(7.0)
    assert _interval(grid, np.array([110, 72, 19, 0, 37, 6, 3.0]), 3.84) == (2.0, None)
    assert _interval(grid, np.array([9, 1, 0, 2, 9, 9, 9.0]), 3.84) == (0.0, 4.0)
    assert _interval(grid, np.array([9, np.nan, 0, 2, np.nan, 9, 1.0]), 3.84) == (0.0, None)
    assert _interval(grid, np.array([np.nan, 1, 0, 2, np.nan, 9, 9.0]), 3.84) == (None, 5.0)
    assert _interval(grid, np.array([9, 8, 5, 6, 9, 9, 9.0]), 3.84) == (1.0, 3.0), "all above: around its own minimum"


def test_each_profile_point_is_a_constrained_fit_with_the_chi2_it_reports():
    patient = builtin("heart_failure")
    options = CohortOptions(budget=48, stop_mismatch=0.0, steps_per_beat=STEPS, confirm_steps=4)
    prof = profile(patient, names=("Sa", "R3"), grid=3, options=options)
    compared = {}
    for name in ("Sa", "R3"):
        bound = ACTION_BOUNDS[name]
        assert prof.grid[name][0] == pytest.approx(bound.lo) and prof.grid[name][-1] == pytest.approx(bound.hi)
        hearts = [patient.heart.replace(**fit) for fit in prof.fits[name]]
        for fit, value in zip(prof.fits[name], prof.grid[name]):
            assert fit[name] == value, "the profiled parameter is held at its grid value"
        sim = lvenv.simulate(hearts, scheme=options.scheme, acceleration="anderson", traces=False)
        # where P_lv only grazes P_at before mitral opening (Sa at its upper bound), IVRT jumps by
        # tens of ms between integrations of the same steady state; compare where two schemes agree
        fine = lvenv.simulate(hearts, traces=False)
        conditioned = np.abs(sim.metrics["IVRT"] - fine.metrics["IVRT"]) < 0.002
        compared[name] = int(conditioned.sum())
        for g, heart_chi2 in enumerate(prof.chi2[name]):
            independent = chi2(patient, {k: float(v[g]) for k, v in sim.metrics.items()})
            if conditioned[g]:
                assert heart_chi2 == pytest.approx(independent, rel=2e-2, abs=1e-2)
        lo, hi = prof.interval[name]
        assert (prof.classification[name] == "identified") == (lo is not None and hi is not None)
    assert sum(compared.values()) >= 4, compared
    assert prof.chi2_min == pytest.approx(min(np.nanmin(v) for v in prof.chi2.values()))
    assert DELTA_95 == pytest.approx(3.84)
    assert prof.evaluations <= 6 * options.budget


def test_volume_errors_are_a_fraction_of_the_measured_volume_and_plain_numbers_stay_absolute():
    from lvenv.metrics import FRAME_NAMES
    from lvenv.validation import InputError
    from optim.identify import NOISE, VOLUME_NAMES, Relative, measurement_sd

    base = builtin("normal")
    patient = dataclasses.replace(base, targets={**base.targets, "EDV": 60.0, "ESV": 24.0, FRAME_NAMES[5]: 40.0})
    sigma = dict(zip(patient.targets, measurement_sd(patient.targets)))
    assert (sigma["EDV"], sigma["ESV"], sigma[FRAME_NAMES[5]]) == pytest.approx((3.0, 1.2, 2.0))
    assert all(sigma[k] == NOISE[k] for k in base.targets)
    # each volume read 5 % off its target costs one χ² unit, whatever its size
    observation = {**patient.targets, "EDV": 63.0, "ESV": 22.8, FRAME_NAMES[5]: 42.0}
    assert chi2(patient, observation) == pytest.approx(3.0)
    absolute = {**NOISE, **dict.fromkeys(VOLUME_NAMES, 5.0)}
    assert chi2(patient, observation, absolute) == pytest.approx((3.0**2 + 1.2**2 + 2.0**2) / 25.0)
    assert measurement_sd({"EDV": 60.0}, {"EDV": 3 * Relative(0.05)}) == pytest.approx([9.0])
    assert measurement_sd({"EDV": 60.0}, {"EDV": Relative(0.05) / 5}) == pytest.approx([0.6])
    with pytest.raises(InputError, match="EDV = 0.0"):
        measurement_sd({"EDV": 0.0})
    with pytest.raises(InputError, match="Relative.fraction = -0.05"):
        Relative(-0.05)
    with pytest.raises(InputError, match="no measurement error for the target"):
        measurement_sd({"EDV": 60.0}, {"ESV": 1.0})


def test_posterior_samples_stay_in_bounds_count_their_evaluations_and_follow_the_likelihood():
    from optim.identify import NOISE, posterior, probability_lower

    patient = builtin("normal")
    wide = {k: 100 * v for k, v in NOISE.items()}
    narrow = {k: v / 100 for k, v in NOISE.items()}
    kwargs = dict(walkers=16, steps=30, burn=10, chains=8, chain_steps=40, chain_burn=8, steps_per_beat=STEPS, max_beats=30, seed=3)
    flat, sharp = posterior(patient, noise=wide, **kwargs), posterior(patient, noise=narrow, **kwargs)
    pilot = posterior(patient, noise=narrow, **{**kwargs, "chains": 0})
    for post, chained, draws in ((flat, True, 32 * 8), (sharp, True, 32 * 8), (pilot, False, 20 * 16)):
        # each sampler evaluates its starting points once, then one proposal per walker (chain) and step;
        # the chains' first round runs chain_steps // 4 steps; an extended pilot runs steps more each time
        assert post.pilot_steps in (30, 60, 90, 120)
        assert post.evaluations == 16 * (1 + post.pilot_steps) + chained * 8 * (11 + 41)
        assert 0.0 <= post.acceptance <= 1.0 and 0 <= post.failed <= post.evaluations
        for name, values in post.samples.items():
            bound = ACTION_BOUNDS[name]
            assert values.shape == (draws,) and np.all((values >= bound.lo) & (values <= bound.hi))
            lo, hi = post.interval_90[name]
            assert lo <= post.median[name] <= hi
    spread = lambda post, name: np.std(np.log(post.samples[name]))
    assert spread(flat, "tau2") > 2 * spread(sharp, "tau2"), "a likelihood 10^4 times sharper keeps the walkers together"
    assert probability_lower(flat, flat, "Sa") == pytest.approx(0.5, abs=0.1)
    assert probability_lower(flat, sharp, "Sa") + probability_lower(sharp, flat, "Sa") == pytest.approx(1.0)
    for name, width in sharp.widths().items():  # fraction of the bound, on the log scale for log axes
        bound, (lo, hi) = ACTION_BOUNDS[name], sharp.interval_90[name]
        expected = np.log(hi / lo) / np.log(bound.hi / bound.lo) if bound.log else (hi - lo) / (bound.hi - bound.lo)
        assert width == pytest.approx(expected, rel=1e-9) and 0.0 <= width <= 1.0, name
    assert flat.widths()["tau2"] > sharp.widths()["tau2"]


def test_pilot_is_extended_while_its_walkers_still_climb():
    from optim.identify.sampler import CLIMB, _climbing

    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 3.0, (200, 64))  # an equilibrium's spread of log-posteriors, far wider than CLIMB
    assert not _climbing(noise - 50.0)
    assert _climbing(noise - 50.0 + np.linspace(0.0, 8 * CLIMB, 200)[:, None]), "a rise of 2 CLIMB per quarter"
    assert not _climbing(noise - 50.0 + np.linspace(0.0, 2 * CLIMB, 200)[:, None]), "half a CLIMB per quarter: settled enough"
    stuck = np.full((200, 64), -np.inf)
    stuck[150:, :8] = -40.0
    assert _climbing(stuck), "walkers only now finding usable hearts"
    assert not _climbing(np.full((200, 64), -np.inf))


def _ridge_log_density(u: np.ndarray) -> np.ndarray:
    """A curved ridge in the 6-D unit cube (x = u − 1/2): x1 ≈ 2 x0² − 0.1 within 0.03, x0 ~ N(0, 0.2²),
    the rest N(0, 0.1²), truncated to the cube."""
    u = np.atleast_2d(u)
    x = u - 0.5
    value = -0.5 * (((x[:, 1] - 2.0 * x[:, 0] ** 2 + 0.1) / 0.03) ** 2 + (x[:, 0] / 0.2) ** 2 + np.sum((x[:, 2:] / 0.1) ** 2, axis=1))
    return np.where(np.all((u >= 0.0) & (u <= 1.0), axis=1), value, -np.inf)


def _ridge_draws(n: int, rng: np.random.Generator) -> np.ndarray:
    x0 = rng.normal(0.0, 0.2, n)
    x = np.column_stack([x0, 2.0 * x0**2 - 0.1 + 0.03 * rng.standard_normal(n), rng.normal(0.0, 0.1, (n, 4))]) + 0.5
    return x[np.all((x >= 0.0) & (x <= 1.0), axis=1)]


def test_independent_chains_sample_a_known_ridge_even_from_a_wrong_pilot():
    """The chains' moves are Metropolis–Hastings with the proposal's density in the acceptance
    ratio, so they sample the target whatever the pilot draws were: here a straight, shifted and
    too narrow Gaussian instead of the curved ridge. Quantiles against direct draws of the ridge."""
    import emcee

    from optim.identify.sampler import _chain_moves, _split_rhat

    rng = np.random.default_rng(0)
    truth = _ridge_draws(200_000, rng)
    pilot = np.clip(rng.normal(0.55, 0.05, (2000, 6)), 0.01, 0.99)

    def run(rounds: tuple[int, ...]) -> emcee.EnsembleSampler:
        draws, position = pilot, pilot[:64]
        for r, steps in enumerate(rounds):
            sampler = emcee.EnsembleSampler(64, 6, _ridge_log_density, vectorize=True, moves=_chain_moves(draws, r))
            sampler.random_state = np.random.RandomState(r).get_state()
            sampler.run_mcmc(position, steps, progress=False)
            draws, position = sampler.get_chain(discard=steps // 2, flat=True), sampler.get_last_sample().coords
        return sampler

    def worst_rhat(sampler: emcee.EnsembleSampler) -> float:
        chain = sampler.get_chain(discard=100)
        return max(_split_rhat(chain[..., j].T) for j in range(6))

    assert worst_rhat(run((150, 600))) > 1.1, "two rounds from this pilot have not mixed, and the chains' R-hat says so"
    sampler = run((150, 150, 150, 600))  # each refit moves the proposal closer to the ridge
    got = sampler.get_chain(discard=100, flat=True)
    for q in (5, 50, 95):
        np.testing.assert_allclose(np.percentile(got, q, axis=0), np.percentile(truth, q, axis=0), atol=0.015, err_msg=f"{q} % quantile")
    assert worst_rhat(sampler) < 1.1
    assert 0.3 < np.mean(sampler.acceptance_fraction) < 0.95


def test_mixture_proposal_density_matches_its_draws():
    """The proposal's density on the unit cube (logit change of variables included) against a
    histogram of its own draws, in 1-D, where a missing Jacobian would be off by a factor u (1 − u)."""
    from optim.identify.sampler import _Mixture

    rng = np.random.default_rng(1)
    mix = _Mixture.fit(np.clip(rng.beta(2.0, 5.0, (4000, 1)), 1e-6, 1 - 1e-6), seed=0)
    draws = mix.sample(1_000_000, np.random.RandomState(2))[:, 0]
    counts, edges = np.histogram(draws, bins=25, range=(0.0, 1.0))
    fine = np.linspace(0.0, 1.0, 25 * 40 + 1)[1:-1]  # the density averaged over each bin, on 40 points a bin
    density = np.exp(mix.log_density(fine[:, None]))
    per_bin = np.array([np.mean(density[(fine >= a) & (fine < b)]) for a, b in zip(edges[:-1], edges[1:])])
    expected = counts / (len(draws) * np.diff(edges))
    busy = counts > 5000  # Poisson error below 1.4 %
    np.testing.assert_allclose(per_bin[busy], expected[busy], rtol=0.05)
    assert np.sum(per_bin * np.diff(edges)) == pytest.approx(1.0, abs=0.01)


def test_highest_density_interval_reaches_the_bound_the_samples_pile_against():
    """R2 drawn with density rising linearly to its upper bound: the equal-tailed interval leaves
    out the top 5 %, the most probable values; the highest-density one ends at the largest sample
    and still holds 90 %. A symmetric posterior inside the bounds gets the equal-tailed interval."""
    from optim.identify import Posterior

    rng = np.random.default_rng(3)
    lo, hi = ACTION_BOUNDS["R2"].lo, ACTION_BOUNDS["R2"].hi
    r2 = lo + (hi - lo) * np.sqrt(rng.random(40_000))  # density ∝ R2 − lo
    sa = rng.normal(1.0, 0.05, 40_000)
    samples = {"R2": r2, "Sa": sa}
    post = Posterior(samples, {}, {n: (float(np.percentile(v, 5)), float(np.percentile(v, 95))) for n, v in samples.items()},
                     0.5, {}, {}, {}, 0, 0, 0)
    hdi = post.highest_density(0.9)
    assert hdi["R2"][1] == r2.max() and post.interval_90["R2"][1] < hi - 0.02 * (hi - lo)
    assert np.mean((r2 >= hdi["R2"][0]) & (r2 <= hdi["R2"][1])) == pytest.approx(0.9, abs=1e-3)
    assert hdi["R2"][1] - hdi["R2"][0] < post.interval_90["R2"][1] - post.interval_90["R2"][0]
    np.testing.assert_allclose(hdi["Sa"], post.interval_90["Sa"], atol=0.005)
    with pytest.raises(ValueError, match="level"):
        post.highest_density(0.0)


def test_identifiability_report_holds_every_parameter_its_figures_and_the_numbers_behind_them(tmp_path):
    import json

    from optim.identify import write_report

    patient = builtin("normal")
    fit = {n: float(patient.heart.get(n)) for n in ACTION_BOUNDS}
    options = CohortOptions(candidates=8, budget=16, stop_mismatch=0.0, slots=32, steps_per_beat=STEPS)  # the sensitivity's programs of the first test
    small = dict(walkers=16, steps=10, burn=4, chains=8, chain_steps=16, chain_burn=4, steps_per_beat=STEPS, max_beats=30)
    off = {k: 1.1 * v for k, v in patient.targets.items()}  # each target 10 % off: χ² at the fit is known
    path = write_report(patient, fit, off, tmp_path, grid=3, options=options, posterior_options=small)
    text = path.read_text()
    record = json.loads((tmp_path / "identifiability.json").read_text())
    for image in ("profiles.png", "posterior_pairs.png"):
        assert (tmp_path / image).read_bytes()[:4] == b"\x89PNG" and f"({image})" in text
    classes = {"identified", "practically non-identifiable", "structurally non-identifiable", "no usable fit"}
    for name in ACTION_BOUNDS:
        assert record["profiles"]["classification"][name] in classes
        row = next(line for line in text.splitlines() if line.startswith(f"| {name} | {record['profiles']['classification'][name]} |"))
        assert "[" in row
        median = record["posterior"]["median"][name]
        assert f"| {name} | {median:.4g} |" in text, "the posterior table shows the JSON's median"
    assert record["fit"] == fit and set(record["targets"]) == set(patient.targets)
    assert f"χ² at the fit: {chi2(patient, off):.3g}" in text, "χ² is of the observation passed in"
    assert len(record["sensitivity"]["null_directions"]) == 2, "four targets, six parameters"


def test_prior_draws_are_the_posteriors_prior_and_carry_their_own_observations():
    """Rejection sampling keeps a uniform draw with probability exp(log factor): no kept heart lies
    4 σ or more outside the plausibility bands (a uniform draw does so about half the time), each
    is usable, inside the bounds, and its observations are what the posterior's env computes; the
    posterior's density peaks at the draw whose observations are the targets."""
    from lvenv.identification import DEFAULT_ACTION_PARAMS
    from lvenv.plausibility import resolve
    from optim.fit import make_env
    from optim.identify import log_density, measurement_sd, prior_draws
    from optim.identify.density import _evaluate

    patient = builtin("normal")
    x, obs = prior_draws(12, patient, seed=4, batch=16, steps_per_beat=STEPS, max_beats=30)
    assert x.shape == (12, 6) and obs.shape == (12, len(patient.targets))
    for j, name in enumerate(DEFAULT_ACTION_PARAMS):
        assert np.all((x[:, j] >= ACTION_BOUNDS[name].lo) & (x[:, j] <= ACTION_BOUNDS[name].hi)), name
    venv = make_env(patient, 16, STEPS, 30)
    venv.reset(seed=0)
    again, ok, log_factor, _ = _evaluate(venv, x, list(patient.targets), resolve(True))
    venv.close()
    assert np.all(ok)
    # each env member starts from its previous heart's steady state, so the event times move a little with the history
    # (up to 0.15 σ measured); another heart's observations would be many σ away
    sigma = measurement_sd(patient.targets)
    assert np.all(np.abs(again - obs) < 0.5 * sigma), (again - obs) / sigma
    assert np.all(log_factor > -8.0), log_factor
    # the posterior's density for a patient whose targets are the first draw's observations: χ² ≈ 0 there
    observed = dataclasses.replace(patient, targets=dict(zip(patient.targets, map(float, obs[0]))))
    outside = np.concatenate([[2.0 * ACTION_BOUNDS["tau2"].hi], x[1, 1:]])
    density = log_density(observed, np.vstack([x[:2], outside]), steps_per_beat=STEPS, max_beats=30, batch=16)
    assert density[0] == pytest.approx(log_factor[0], abs=0.5) and density[1] < density[0] - 1.0  # ½ · 4 · 0.5² = 0.5
    assert density[2] == -np.inf


def test_prior_draws_give_up_with_the_bands_named_when_no_heart_is_plausible(monkeypatch):
    import optim.identify.density
    from lvenv.plausibility import Band

    monkeypatch.setattr(optim.identify.density, "PRIOR_TRIES", 1)
    impossible = (Band.mmhg("P_ao_mean", 400.0, 410.0, 80.0),)
    with pytest.raises(RuntimeError, match="P_ao_mean 400–410 mmHg"):
        optim.identify.prior_draws(1, builtin("normal"), batch=16, steps_per_beat=STEPS, max_beats=30, plausibility=impossible)
