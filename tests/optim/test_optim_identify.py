"""`optim.identify`: the sensitivity's null directions and profile likelihoods whose every point
is a real constrained fit, checked by an independent simulation."""

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


def test_posterior_samples_stay_in_bounds_count_their_evaluations_and_follow_the_likelihood():
    from optim.identify import NOISE, posterior, probability_lower

    patient = builtin("normal")
    wide = {k: 100 * v for k, v in NOISE.items()}
    narrow = {k: v / 100 for k, v in NOISE.items()}
    kwargs = dict(walkers=16, steps=30, burn=10, steps_per_beat=STEPS, max_beats=30, seed=3)
    flat, sharp = posterior(patient, noise=wide, **kwargs), posterior(patient, noise=narrow, **kwargs)
    for post in (flat, sharp):
        assert post.evaluations == 16 * (30 + 1), "the initial ensemble plus one proposal per walker and step"
        assert 0.0 <= post.acceptance <= 1.0 and 0 <= post.failed <= post.evaluations
        for name, values in post.samples.items():
            bound = ACTION_BOUNDS[name]
            assert values.shape == (20 * 16,) and np.all((values >= bound.lo) & (values <= bound.hi))
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
