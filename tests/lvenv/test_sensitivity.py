"""`lvenv.jacobian`: forward-mode derivatives of the steady-state metrics against central
differences of `lvenv.simulate`, closed and open loop, batched, with failures and bad input."""

import numpy as np
import pytest

import lvenv
from lvenv import presets, sensitivity
from lvenv.identification import DEFAULT_ACTION_PARAMS

STEPS = 250
METRICS = ("EF", "EDV", "ESV", "IVCT", "ET", "IVRT", "P_lv_peak", "P_ao_sys", "P_ao_dia", "P_ao_mean", "CO")
WRT = (*DEFAULT_ACTION_PARAMS, "Pat", "HR")


def _random_hearts(count=20):
    """``count`` hearts around N, HF and an open-loop N in turn, each action parameter scaled by
    a factor in [0.8, 1.25] and the heart rate drawn in 55–85 /min."""
    rng = np.random.default_rng(11)
    bases = (presets.normal(), presets.heart_failure(), presets.normal().replace(closed_loop=0.0, Pat=1.2))
    hearts = []
    for i in range(count):
        base = bases[i % 3]
        factors = rng.uniform(0.8, 1.25, len(DEFAULT_ACTION_PARAMS))
        hearts.append(base.replace(**{n: float(base.get(n)) * f for n, f in zip(DEFAULT_ACTION_PARAMS, factors)}, HR=float(rng.uniform(55, 85))))
    return hearts


def _central_differences(hearts, wrt, metrics, rel=1e-6):
    """Central differences of the steady-state metrics at steps h and 2h, each (n, m, k), from
    one batched simulation of all hearts."""
    perturbed, steps = [], []
    for heart in hearts:
        for name in wrt:
            value = float(heart.get(name))
            step = rel * max(abs(value), 1e-3)
            steps.append(step)
            perturbed += [heart.replace(**{name: value + f * step}) for f in (1.0, -1.0, 2.0, -2.0)]
    sim = lvenv.simulate(perturbed, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000, traces=False)
    assert set(sim.status) == {"ok"}
    values = np.stack([np.asarray(sim.metrics[m]).reshape(len(hearts), len(wrt), 4) for m in metrics], axis=1)  # (n, m, k, 4)
    h = np.array(steps).reshape(len(hearts), 1, len(wrt))
    return (values[..., 0] - values[..., 1]) / (2.0 * h), (values[..., 2] - values[..., 3]) / (4.0 * h)


def _relative_error(ad, fd):
    """|ad − fd| relative to |fd|, or to 1e-2 of its metric's largest derivative at that heart
    where that is larger (the derivatives of one metric share its units; a near-zero entry is
    only as exact as the largest one's round-off)."""
    scale = np.max(np.abs(fd), axis=-1, keepdims=True)
    return np.abs(ad - fd) / np.maximum(np.abs(fd), 1e-2 * scale)


@pytest.mark.parametrize("count", [6, pytest.param(20, marks=pytest.mark.slow)])
def test_derivatives_match_central_differences_closed_and_open_loop_and_in_a_batch(count):
    """Over ``count`` random hearts (N, HF, open loop; heart rate and atrial pressure among the
    parameters) every derivative agrees with the central difference to 1e-4 relative wherever
    the metric is smooth at the difference's scale: where the differences at steps h and 2h agree
    to 1e-4 (across a kink, where a valve event crosses an integrator step, they differ by
    O(1)). Such points are rare, so at most 2 % of the entries may be set aside."""
    hearts = _random_hearts(count)
    batch = lvenv.jacobian(hearts, wrt=WRT, metrics=METRICS, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000)
    assert batch.values.shape == (len(hearts), len(METRICS), len(WRT)) and list(batch.status) == ["ok"] * len(hearts)
    fd, fd_2h = _central_differences(hearts, WRT, METRICS)
    smooth = _relative_error(fd_2h, fd) < 1e-4
    assert smooth.mean() > 0.98, f"{np.sum(~smooth)} of {smooth.size} entries are not smooth at the difference's scale"
    error = _relative_error(batch.values, fd)
    bad = smooth & (error > 1e-4)
    assert not bad.any(), f"autodiff {batch.values[bad]} against differences {fd[bad]} at (heart, metric, parameter) {np.argwhere(bad).tolist()}"
    single = lvenv.jacobian(hearts[2], wrt=WRT, metrics=METRICS, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000)
    np.testing.assert_allclose(single.values, batch.values[2], rtol=1e-9, atol=1e-12)
    assert single["EF", "tau2"] == pytest.approx(batch.values[2, 0, 0])


def test_the_closed_loop_volume_constraint_matters():
    """dEDV/dCat comes mostly from the blood volume that Cat holds at the cold start: without the
    volume row the system would be singular, and a wrong row gives a wrong sign or size."""
    heart = presets.normal()
    jac = lvenv.jacobian(heart, wrt=WRT, metrics=METRICS, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000)
    fd = _central_differences([heart], ("Cat", "C"), ("EDV",))[0][0]
    assert np.all(_relative_error(np.array([[jac["EDV", "Cat"], jac["EDV", "C"]]]), fd) < 1e-4), (jac["EDV", "Cat"], jac["EDV", "C"], fd)
    assert np.all(np.abs(fd) > 1e-3)


def test_the_frames_are_differentiated_when_asked_for_and_other_metrics_compile_nothing_more():
    """The beat's tangents carry the volume-trace frames only where a frame is among the metrics,
    and every metric otherwise: a frame's derivative agrees with the central difference, as a
    summary metric's beside it does, and other metrics in another order reuse the program
    (their rows are the same numbers)."""
    heart = presets.normal()
    metrics = ("V_frame_05", "EF")
    jac = lvenv.jacobian(heart, wrt=("Sa",), metrics=metrics, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000)
    fd = _central_differences([heart], ("Sa",), metrics)[0][0]
    assert np.all(np.abs(fd) > 1e-3) and np.all(_relative_error(jac.values, fd) < 1e-4), (jac.values, fd)
    programs = sensitivity._beat_tangents._cache_size()
    other = lvenv.jacobian(heart, wrt=("Sa",), metrics=("ET", "V_frame_05", "EDV", "EF"), steps_per_beat=STEPS, rtol=1e-12, max_beats=3000)
    assert sensitivity._beat_tangents._cache_size() == programs, "another choice of metrics compiled the tangents again"
    assert other["V_frame_05", "Sa"] == jac["V_frame_05", "Sa"] and other["EF", "Sa"] == jac["EF", "Sa"]


def test_a_member_without_a_usable_steady_state_gets_nan_rows_and_the_others_numbers():
    bad = presets.normal().replace(Sa=10.0, Cmax=10.0, Tref=1000.0)
    jac = lvenv.jacobian([presets.normal(), bad], wrt=WRT, metrics=METRICS, steps_per_beat=STEPS)
    assert jac.status[1] in ("non_physical", "diverged") and np.isnan(jac.values[1]).all()
    assert np.isfinite(jac.values[0]).all()


@pytest.mark.parametrize("kwargs, message", [
    ({"wrt": ("tau3",)}, "'tau3', which is not an LO, cell or circulation parameter"),
    ({"wrt": "tau2"}, "sequences of names"),
    ({"wrt": ("closed_loop",)}, "is a switch"),
    ({"metrics": ("EFF",)}, "metrics contains 'EFF'"),
    ({"wrt": ()}, "must be non-empty"),
    ({"steps_per_beat": 5}, "steps_per_beat"),
])
def test_bad_input_names_the_field(kwargs, message):
    with pytest.raises(ValueError, match=message):
        lvenv.jacobian(presets.normal(), **kwargs)
