"""Amortised identification (optim.amortised, optim.identify.amortised): a tiny estimator trained
on a small real simulated set, its loose calibration on held-out truths, the artefact's round
trip and errors, and the out-of-distribution flag."""

import dataclasses
import pathlib
import tempfile

import numpy as np
import pytest

import lvenv
from lvenv import archive
from lvenv.archive import ArchiveError
from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS
from lvenv.patients import Patient, builtin
from lvenv.status import STATUS
from lvenv.validation import InputError
from optim import amortised, cohort
from optim.identify import NOISE, Posterior, PriorSample, amortised as amortised_posteriors, identify_patients, measurement_sd
from optim.identify.density import ARRAYS

TRAIN, HELD_OUT = 240, 100
TINY = amortised.Architecture(flow_layers=3, knots=6, nn_width=32, nn_depth=1)


@pytest.fixture(scope="module")
def data():
    draws = amortised.simulate(TRAIN + HELD_OUT, seed=11, batch=128)
    split = lambda s: PriorSample(*(getattr(draws, f)[s] for f in ARRAYS), draws.names,
                                  draws.tried, draws.left_out)
    estimator = amortised.train(split(slice(0, TRAIN)), architecture=TINY, copies=4, batch_size=128, max_epochs=150, patience=10, seed=0)
    return draws, split(slice(TRAIN, None)), estimator


def test_validation_pairs_have_no_copy_in_training():
    """With copies, a validation pair's every copy is a validation row, so early stopping never sees
    a training pair with only its noise changed; with one copy the split is the plain shuffle's."""
    n, copies = 50, 3
    order, n_val = amortised._validation_first(n, copies, 0.2, np.random.default_rng(0))
    assert sorted(order) == list(range(copies * n))
    val, train = set(order[:n_val] % n), set(order[n_val:] % n)
    assert not val & train and len(val) == 10 and n_val == copies * 10 and len(train) == n - 10
    plain, n_plain = amortised._validation_first(n, 1, 0.2, np.random.default_rng(0))
    assert n_plain == 10 and np.array_equal(plain, np.random.default_rng(0).permutation(n))


def test_a_share_of_training_masks_are_the_target_sets_patients_carry():
    """Each of COMMON_MASKS is the mask of share/3 of the rows plus its chance under independent
    drops (binomial bounds at 5 sd); the others drop each target with MISSING. The sets are the
    built-in patients' and a cohort report's own targets, and all six."""
    n, share = 60_000, 0.5
    observed = np.isfinite(amortised._noisy_masked(np.ones((n, 6)), np.zeros(6), np.random.default_rng(0), share))
    drop = amortised.MISSING
    for targets in amortised.COMMON_MASKS:
        k = len(targets)
        expected = share / len(amortised.COMMON_MASKS) + (1 - share) * (1 - drop) ** k * drop ** (6 - k)
        frequency = np.mean((observed == np.isin(amortised.OBSERVED, targets)).all(axis=1))
        assert abs(frequency - expected) < 5 * np.sqrt(expected * (1 - expected) / n), (targets, frequency, expected)
    alone = np.isfinite(amortised._noisy_masked(np.ones((n, 6)), np.zeros(6), np.random.default_rng(0), 0.0))
    assert abs(alone.mean() - (1 - drop)) < 0.01 and alone.any(axis=1).all()
    assert set(amortised.COMMON_MASKS[0]) == set(builtin("normal").targets) == set(amortised.HELD_OUT_TARGETS)
    row = {"id": "r", "EF_pct": "55", "ET_ms": "290", "IVRT_ms": "80", "SBP_mmHg": "120", "DBP_mmHg": "80", "HR_bpm": "60"}
    assert set(amortised.COMMON_MASKS[1]) == set(cohort._patient(row, builtin("normal").heart).targets)
    assert set(amortised.COMMON_MASKS[2]) == set(amortised.OBSERVED)


def test_training_pairs_come_from_the_prior_with_failures_counted_by_status(data):
    draws, _, estimator = data
    assert draws.parameters.shape == (TRAIN + HELD_OUT, 6) and draws.observations.shape == (TRAIN + HELD_OUT, len(amortised.OBSERVED))
    assert np.all(np.isfinite(draws.observations))
    lo, hi = np.array([ACTION_BOUNDS[n].lo for n in DEFAULT_ACTION_PARAMS]), np.array([ACTION_BOUNDS[n].hi for n in DEFAULT_ACTION_PARAMS])
    assert np.all((draws.parameters >= lo) & (draws.parameters <= hi))
    assert np.all((draws.heart_rate >= 40.0) & (draws.heart_rate <= 120.0)) and set(np.unique(draws.base)) == {0, 1}
    assert set(draws.left_out) <= {*STATUS, "nonfinite_targets", "implausible"} and draws.left_out.get("implausible", 0) > 0
    assert sum(draws.left_out.values()) + len(draws.parameters) <= draws.tried < sum(draws.left_out.values()) + len(draws.parameters) + 128
    training = estimator.meta["training"]
    assert training["pairs"] == TRAIN and np.isfinite(training["best_validation_loss"])
    assert training["masks"] == {"missing": amortised.MISSING, "common": [list(t) for t in amortised.COMMON_MASKS], "common_share": amortised.COMMON_SHARE}
    assert training["best_validation_loss"] == min(training["validation_loss"]) < training["validation_loss"][0]


def test_learning_rate_decays_after_each_plateau_without_improvement(data):
    """The rate starts at the given one and halves exactly when the validation loss has not improved
    for a multiple of ``plateau`` epochs; training stopped at ``patience`` stale epochs, so after
    three decays (plateau 3, patience 10)."""
    training = data[2].meta["training"]
    rates, val = np.array(training["learning_rates"]), np.array(training["validation_loss"])
    assert rates[0] == training["learning_rate"] and training["plateau"] == 3 and training["decay"] == 0.5
    for i in range(len(rates) - 1):
        stale = i - int(np.argmin(val[: i + 1]))
        expected = rates[i] * 0.5 if stale > 0 and stale % 3 == 0 else rates[i]
        assert rates[i + 1] == expected, (i, stale, rates[i], rates[i + 1])
    assert len(rates) < 150 and np.count_nonzero(np.diff(rates)) >= 3


def test_tiny_estimator_is_loosely_calibrated_on_held_out_truths(data):
    """90 % intervals of held-out prior truths (noisy observations, random masks) hold about 90 %
    of them: each parameter between 0.7 and 1, and all together between 0.8 and 0.98 (the tiny
    flow is near its prior where it has learnt little, which covers)."""
    _, held, estimator = data
    rng = np.random.default_rng(3)
    sigma = measurement_sd(dict.fromkeys(amortised.OBSERVED, 1.0), NOISE)
    obs = held.observations + sigma * rng.standard_normal(held.observations.shape)
    obs[rng.random(obs.shape) < 0.3] = np.nan
    obs[np.all(np.isnan(obs), axis=1), 0] = held.observations[np.all(np.isnan(obs), axis=1), 0]
    x = estimator.sample(obs, held.heart_rate, held.geometry, 400, seed=1)
    lo, hi = np.percentile(x, 5, axis=1), np.percentile(x, 95, axis=1)
    coverage = np.mean((held.parameters >= lo) & (held.parameters <= hi), axis=0)
    assert np.all(coverage >= 0.7) and 0.8 <= coverage.mean() <= 0.98, coverage
    # the intervals are informative: EF, ET and the pressures narrow at least one parameter well inside its bound
    unit = lvenv.identification.ParameterSpace.for_names().to_unit
    assert np.min(np.median(unit(hi) - unit(lo), axis=0)) < 0.7


def test_artefact_round_trips_and_bad_artefacts_say_what_is_wrong(data, tmp_path):
    _, held, estimator = data
    path = amortised.save(estimator, tmp_path / "est.npz")
    loaded = amortised.load(path)
    args = (held.observations[:5], held.heart_rate[:5], held.geometry[:5], 50)
    np.testing.assert_allclose(loaded.sample(*args, seed=2), estimator.sample(*args, seed=2), rtol=1e-12)
    assert loaded.meta == {**estimator.meta}

    with pytest.raises(ArchiveError, match="no trained amortised estimator"):
        amortised.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not an archive")
    with pytest.raises(ArchiveError, match="damaged or not an lvenv archive"):
        amortised.load(tmp_path / "junk.npz")
    arrays, meta = archive.load(path)
    cases = {
        "format": ({**meta, "version": 99}, arrays),
        "noise": ({**meta, "noise": {**meta["noise"], "EF": 0.1}}, arrays),
        "prior": ({**meta, "prior": {**meta["prior"], "bounds": {**meta["prior"]["bounds"], "tau2": [0.01, 0.6, True]}}}, arrays),
        "shape": (meta, {**arrays, "flow_000": np.zeros(3)}),
        "lacks": (meta, {k: v for k, v in arrays.items() if k != "ood_means"}),
        "finite": (meta, {**arrays, "theta_sd": np.full(6, np.nan)}),
    }
    messages = {"format": "version 99", "noise": "noise", "prior": "prior", "shape": "shape", "lacks": "lacks", "finite": "not finite"}
    for name, (m, a) in cases.items():
        archive.save(tmp_path / f"{name}.npz", a, m)
        with pytest.raises(ArchiveError, match=messages[name]):
            amortised.load(tmp_path / f"{name}.npz")


def test_training_pairs_file_round_trips_concatenates_and_refuses_other_priors(data, tmp_path):
    """A long simulation's pairs survive on disk (scripts/train_amortised.py --draws): chunks
    concatenate in order with their counts summed, read back bit for bit, and a file of another
    prior or of other shapes is refused with what differs."""
    draws, held, _ = data
    first = PriorSample(*(getattr(draws, f)[:50] for f in ARRAYS), draws.names, 300, {"implausible": 200})
    both = PriorSample.concatenate([first, held])
    assert len(both.parameters) == 50 + HELD_OUT and both.tried == 300 + held.tried
    assert both.left_out["implausible"] == 200 + held.left_out["implausible"]
    np.testing.assert_array_equal(both.parameters[50:], held.parameters)
    path = amortised.save_draws(both, tmp_path / "draws.npz", seeds=[1, 2])
    back, seeds, code_version, kinds = amortised.load_draws(path)
    assert seeds == [1, 2] and code_version and back.names == both.names and (back.tried, back.left_out) == (both.tried, both.left_out)
    assert kinds == amortised.BASES
    for f in ARRAYS:
        np.testing.assert_array_equal(getattr(back, f), getattr(both, f))
    arrays, meta = archive.load(path)
    archive.save(tmp_path / "old.npz", {k: v for k, v in arrays.items() if k != "geometry"}, meta)
    np.testing.assert_array_equal(amortised.load_draws(tmp_path / "old.npz")[0].geometry, both.geometry), "a file from before geometry: from its presets"
    with pytest.raises(ArchiveError, match="prior"):
        amortised.load_draws(path, bases=("normal", "heart_failure", "anatomy"))
    with pytest.raises(ArchiveError, match="prior"):
        amortised.load_draws(path, heart_rate=(50.0, 100.0))
    arrays, meta = archive.load(path)
    archive.save(tmp_path / "short.npz", {**arrays, "base": arrays["base"][:3]}, meta)
    with pytest.raises(ArchiveError, match="shapes"):
        amortised.load_draws(tmp_path / "short.npz")
    path = amortised.save(data[2], tmp_path / "est.npz")
    with pytest.raises(ArchiveError, match="not 'lvenv-amortised-draws' pairs"):
        amortised.load_draws(path)
    with pytest.raises(InputError, match="different targets"):
        PriorSample.concatenate([first, dataclasses.replace(held, names=("EF",))])


def test_observations_outside_the_training_set_are_flagged(data):
    _, held, estimator = data
    rng = np.random.default_rng(4)
    sigma = measurement_sd(dict.fromkeys(amortised.OBSERVED, 1.0), NOISE)
    obs = held.observations + sigma * rng.standard_normal(held.observations.shape)
    # thresholds from the tiny set's 24 held-out rows are rough: a few false alarms (the shipped artefact's are 1 in 1000)
    assert np.mean([r != "" for r in estimator.out_of_distribution(obs, held.heart_rate)]) <= 0.15
    far = obs[:3].copy()
    far[:, 0], far[:, 4] = 0.05, 40.0  # EF 5 % with a mean pressure of 300 mmHg
    assert all("log density" in r for r in estimator.out_of_distribution(far, held.heart_rate[:3]))
    partial = np.full((1, 6), np.nan)
    partial[0, 1] = 1.5  # an ejection time of 1.5 s, alone
    assert estimator.out_of_distribution(partial, np.array([60.0]))[0]
    assert "heart rate" in estimator.out_of_distribution(obs[:1], np.array([150.0]))[0]


def test_identify_amortised_returns_one_posterior_per_patient(data):
    _, _, estimator = data
    normal = builtin("normal")
    one = amortised_posteriors(normal, n_samples=200, estimator=estimator)
    assert len(one) == 1 and isinstance(one[0], Posterior) and one[0].sampler == "amortised"
    assert set(one[0].samples) == set(DEFAULT_ACTION_PARAMS) and all(len(v) == 200 for v in one[0].samples.values())
    assert one[0].out_of_distribution == "" and one[0].ess["tau2"] == 200
    lo, hi = one[0].interval_90["Sa"]
    assert ACTION_BOUNDS["Sa"].lo <= lo < one[0].median["Sa"] < hi <= ACTION_BOUNDS["Sa"].hi
    fast = dataclasses.replace(normal, name="fast", heart=normal.heart.replace(HR=200.0),
                               targets={"EF": 0.6, "P_ao_dia": 10.0, "P_ao_mean": 12.0})
    both = amortised_posteriors([normal, fast], n_samples=100, estimator=estimator)
    assert [p.out_of_distribution == "" for p in both] == [True, False] and "heart rate" in both[1].out_of_distribution
    with pytest.raises(InputError, match="does not condition on"):
        amortised_posteriors(dataclasses.replace(normal, targets={"EF": 0.6, "EDV": 120.0}), estimator=estimator)
    with pytest.raises(InputError, match="none of the estimator's hearts"):
        amortised_posteriors(Patient("other", normal.heart.replace(Pat=1.2), {"EF": 0.6}), estimator=estimator)


@pytest.mark.parametrize("which", ["tiny", "shipped"])
def test_batched_draw_is_the_flows_own_inverse_and_compiles_once(data, which):
    """optim.amortised's batched inverse (the sampler's hot path) equals flowjax's own
    flow.bijection.transform draw by draw, also for base draws beyond the spline's interval
    (identity there); float32 to 1e-4. Repeated draws of one shape reuse one compilation."""
    import jax
    import jax.numpy as jnp
    import paramax

    estimator = data[2] if which == "tiny" else amortised.load()
    flow = paramax.unwrap(estimator.flow)
    rng = np.random.default_rng(5)
    cond, eps = rng.standard_normal((6, len(amortised.CONDITION))), 3.0 * rng.standard_normal((6, 7, 6))
    assert np.any(np.abs(eps) > estimator.architecture.interval)
    reference = np.asarray(jax.vmap(lambda e, c: jax.vmap(lambda x: flow.bijection.transform(x, c))(e))(eps, cond))
    for dtype, tolerance in ((jnp.float64, 1e-10), (jnp.float32, 1e-4)):
        np.testing.assert_allclose(np.asarray(amortised._coupling_inverse(estimator.flow, dtype)(eps, cond)), reference, atol=tolerance)
    obs, hr, shape = np.tile([[0.6, 0.3, 0.08, 10.0, 12.5, 6.0]], (3, 1)), np.full(3, 60.0), np.tile(amortised.covered_geometry(builtin("normal").heart, amortised.BASES), (3, 1))
    first = estimator.sample(obs, hr, shape, 64, seed=1)
    compiled = estimator._sampler._cache_size()
    second = estimator.sample(obs[:2], hr[:2], shape[:2], 64, seed=2)  # padded to the same block: no new compilation
    assert first.shape == (3, 64, 6) and second.shape == (2, 64, 6) and first.dtype == np.float64 and not np.array_equal(first[:2], second)
    assert estimator._sampler._cache_size() == compiled


def test_refine_replaces_flagged_posteriors_by_mcmc_and_keeps_the_flag():
    """identify_patients(refine=True): the flagged patient (far from every simulated heart) gets
    the MCMC posterior, marked refined with its reason kept; the one in distribution keeps the
    amortised answer; one the estimator does not cover is flagged with the reason."""
    normal = builtin("normal")
    far = dataclasses.replace(normal, name="far", targets={"EF": 0.1, "ET": 0.08, "IVRT": 0.3, "P_ao_pulse": 25.0})
    volume = dataclasses.replace(normal, name="volume", targets={"EF": 0.6, "EDV": 120.0})
    mcmc = {"walkers": 12, "steps": 4, "chains": 0, "steps_per_beat": 200, "max_beats": 20}
    answers = identify_patients([normal, far, volume], 200, refine=False)
    assert [bool(a.flag) for a in answers] == [False, True, True] and "['EDV']" in answers[2].flag and answers[2].posterior is None
    calls = []
    ok, refined = identify_patients([normal, far], 200, refine=True, mcmc_options=mcmc, progress=lambda *a: calls.append(a))
    assert calls == [(0, 1, "far")]
    assert (ok.refined, ok.posterior.sampler, ok.flag) == (False, "amortised", "")
    assert refined.refined and refined.posterior.sampler == "ensemble" and refined.flag == answers[1].flag != ""
    assert refined.posterior.out_of_distribution == refined.flag and refined.posterior.evaluations > 0


def test_shipped_artefact_answers_the_built_in_patients():
    """The shipped artefact loads (its metadata matches this code: the anatomy regression too),
    covers every heart kind and places the built-in patients in distribution, with HF's
    contraction efficiency below N's more likely than not."""
    estimator = amortised.load()
    assert estimator.meta["training"]["pairs"] >= 10_000 and estimator.bases == amortised.KINDS
    normal, failure = amortised_posteriors([builtin("normal"), builtin("heart_failure")], n_samples=2000, estimator=estimator)
    assert normal.out_of_distribution == failure.out_of_distribution == ""
    assert np.median(failure.samples["Sa"]) < np.median(normal.samples["Sa"]) * 1.5


def test_importance_resampling_recovers_a_known_target_and_flags_heavy_tails():
    """_importance_resample: draws of N(0, 1) weighted towards N(0.5, 0.7²) resample to that
    target (mean and sd within Monte-Carlo tolerance), never pick an unusable (−inf) row, and have
    Pareto k̂ below 0.7; weighted towards a target wider than the proposal (N(0, 3²): weights of
    infinite variance) k̂ exceeds 0.7, which is what flags an unreliable importance posterior."""
    from optim.identify.sampler import PARETO_K, _importance_resample

    rng = np.random.default_rng(3)
    x = rng.standard_normal((20_000, 2))
    log_normal = lambda v, mu, sd: np.sum(-0.5 * ((v - mu) / sd) ** 2 - np.log(sd), axis=1)
    log_w = log_normal(x, 0.5, 0.7) - log_normal(x, 0.0, 1.0)
    x[:50], log_w[:50] = 99.0, -np.inf
    picked, ess, k = _importance_resample(x, log_w, 5000, np.random.default_rng(4))
    assert picked.shape == (5000, 2) and not np.any(picked == 99.0)
    np.testing.assert_allclose(picked.mean(axis=0), 0.5, atol=0.05)
    np.testing.assert_allclose(picked.std(axis=0), 0.7, atol=0.05)
    assert 0.3 * len(x) < ess < len(x) and k < PARETO_K
    wide = log_normal(x[50:], 0.0, 3.0) - log_normal(x[50:], 0.0, 1.0)
    assert _importance_resample(x[50:], wide, 1000, np.random.default_rng(4))[2] > PARETO_K


def test_flow_density_in_the_unit_cube_is_the_sampling_maps_change_of_variables(data):
    """Estimator.log_density(u) = log p_base(ε) − log |det ∂u/∂ε| for u the sampler's image of
    base draws ε (flowjax's forward map, then the standardisation and the logistic map into the
    unit cube), the Jacobian by automatic differentiation of that whole map: no term of the
    change of variables (the flow's, the standard deviations', the logit's) is missing."""
    import jax
    import jax.numpy as jnp
    import paramax

    from lvenv.identification import ParameterSpace

    estimator = data[2]
    flow = paramax.unwrap(estimator.flow)
    obs, hr, shape = np.array([0.6, 0.3, 0.08, 10.0, 12.5, 6.0]), 70.0, amortised.covered_geometry(builtin("heart_failure").heart, amortised.BASES)
    cond = jnp.asarray(estimator.condition(obs[None], np.array([hr]), shape[None])[0])
    mean, sd = (jnp.asarray(estimator.arrays[k]) for k in ("theta_mean", "theta_sd"))
    to_unit = lambda e: jax.nn.sigmoid(flow.bijection.transform(e, cond) * sd + mean)
    base_dist = flow.base_dist  # trained: its loc and scale are not 0 and 1
    eps = np.asarray(base_dist.loc) + np.asarray(base_dist.scale) * np.random.default_rng(6).standard_normal((5, 6))
    u = np.asarray(jax.vmap(to_unit)(eps))
    expected = [float(base_dist.log_prob(jnp.asarray(e)) - jnp.linalg.slogdet(jax.jacfwd(to_unit)(jnp.asarray(e)))[1]) for e in eps]
    x = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS).from_unit(u)
    got = estimator.log_density(x, np.tile(obs, (5, 1)), np.full(5, hr), np.tile(shape, (5, 1)))
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_importance_weighting_flags_a_poor_flow_and_trusts_the_shipped_one(data):
    """amortised(importance=N): resampled draws of N simulated proposals (sampler 'importance',
    N evaluations). The tiny test estimator is far from the posterior: its weights' Pareto k̂ is
    above the limit and the patient is flagged with the reason. The shipped estimator's weights
    are reliable for the built-in patient (k̂ below the limit, ESS over a fifth of the
    proposals), so it is not flagged. Fewer proposals than draws is refused."""
    from optim.identify.sampler import PARETO_K

    normal = builtin("normal")
    poor, = amortised_posteriors(normal, n_samples=400, estimator=data[2], importance=800, seed=1)
    assert poor.sampler == "importance" and poor.evaluations == 800 and poor.failed < 800
    assert poor.pareto_k > PARETO_K and "Pareto k" in poor.out_of_distribution and poor.ess["Sa"] < 800
    shipped, = amortised_posteriors(normal, n_samples=1000, importance=2000, seed=1)
    assert shipped.pareto_k < PARETO_K and shipped.ess["tau2"] > 400 and shipped.out_of_distribution == ""
    assert all(len(v) == 1000 for v in shipped.samples.values()) and np.isnan(amortised_posteriors(normal, 100, estimator=data[2])[0].pareto_k)
    with pytest.raises(InputError, match="importance = 50"):
        amortised_posteriors(normal, n_samples=100, estimator=data[2], importance=50)


@pytest.fixture(scope="module")
def mixed():
    """Pairs over every heart kind (presets and anatomies) and a tiny estimator trained on them."""
    draws = amortised.simulate(90, bases=amortised.KINDS, seed=5, batch=64)
    return draws, amortised.train(draws, bases=amortised.KINDS, architecture=TINY, batch_size=32, max_epochs=3, seed=0)


def test_anatomy_pairs_carry_the_geometry_of_the_heart_that_made_them(mixed):
    """simulate over the presets and the anatomy kind: equal shares, each pair's kind index
    (optim.amortised.KINDS) and geometry; anatomies inside the box, several pairs each; a pair's
    noise-free observation is what its own heart (anatomy_heart of its geometry, its parameters
    and heart rate) gives when simulated again."""
    from optim.campaign import BOX
    from optim.identify.density import _evaluate
    from optim.fit import make_env

    draws, _ = mixed
    kinds = np.bincount(draws.base, minlength=3)
    assert list(kinds) == [60 - kinds[1], kinds[1], 30] and kinds[0] > 0 and kinds[1] > 0
    anat = draws.base == amortised.KINDS.index(amortised.ANATOMY)
    lo, hi = np.array([BOX[g][0] for g in amortised.GEOMETRY]), np.array([BOX[g][1] for g in amortised.GEOMETRY])
    assert np.all((draws.geometry[anat] >= lo) & (draws.geometry[anat] <= hi))
    assert 1 < len(np.unique(draws.geometry[anat], axis=0)) <= 30
    presets = [amortised.covered_geometry(builtin(n).heart, amortised.BASES) for n in ("normal", "heart_failure")]
    assert all(np.array_equal(draws.geometry[j], presets[draws.base[j]]) for j in np.flatnonzero(~anat))
    j = int(np.flatnonzero(anat)[0])
    from lvenv.geometry import Geometry

    heart = amortised.anatomy_heart(Geometry(**dict(zip(amortised.GEOMETRY, map(float, draws.geometry[j]))))).replace(HR=float(draws.heart_rate[j]))
    venv = make_env(Patient("again", heart, amortised._TARGETS), 4, 500, 60)
    venv.reset(seed=0)
    obs = _evaluate(venv, draws.parameters[j:j + 1], amortised.OBSERVED, [])[0][0]
    venv.close()
    np.testing.assert_allclose(obs, draws.observations[j], rtol=1e-6)


def test_an_anatomy_estimator_covers_regression_mapped_hearts_in_the_box_only(mixed):
    """covered_geometry: a patient record with a geometry and the regression's maps is covered by
    an estimator with the anatomy kind (its own geometry enters the condition) and not by one of
    the presets only; a geometry outside the box names the field, and other maps are refused.
    The artefact records the anatomy regression's dataset and round-trips."""
    _, estimator = mixed
    shape = {"Rb": 33.0, "L": 9.0, "Z": 50.0, "H": 9.0, "e": 0.7, "C0": -60.0}
    record = Patient.from_dict({"name": "imaged", "geometry": shape, "lo": "regression", "targets": {"EF": 0.55, "ET": 0.3}})
    np.testing.assert_array_equal(amortised.covered_geometry(record.heart.replace(tau2=0.3, HR=80.0), amortised.KINDS), [shape[g] for g in amortised.GEOMETRY])
    with pytest.raises(InputError, match="none of the estimator's hearts"):
        amortised.covered_geometry(record.heart, amortised.BASES)
    with pytest.raises(InputError, match="Rb = 60 outside"):
        amortised.covered_geometry(record.heart.replace(geometry=dataclasses.replace(record.heart.geometry, Rb=60.0)), amortised.KINDS)
    with pytest.raises(InputError, match="none of the estimator's hearts"):
        amortised.covered_geometry(record.heart.replace(mu1=record.heart.get("mu1") * 1.1), amortised.KINDS)
    post, = amortised_posteriors(record, n_samples=64, estimator=estimator)
    assert post.sampler == "amortised" and all(len(v) == 64 for v in post.samples.values())
    assert estimator.meta["prior"]["anatomy"]["regression"]["dataset_sha256"]
    assert amortised.load(amortised.save(estimator, pathlib.Path(tempfile.mkdtemp()) / "a.npz")).bases == amortised.KINDS
