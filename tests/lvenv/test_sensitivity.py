"""`lvenv.jacobian`: forward-mode derivatives of the steady-state metrics against central
differences of `lvenv.simulate`, closed and open loop, batched, with failures and bad input."""

import numpy as np
import pytest

import lvenv
from lvenv import presets
from lvenv.identification import DEFAULT_ACTION_PARAMS

STEPS = 250
METRICS = ("EF", "EDV", "ESV", "IVCT", "ET", "IVRT", "P_lv_peak", "P_ao_sys", "P_ao_dia", "P_ao_mean", "CO")
WRT = (*DEFAULT_ACTION_PARAMS, "Pat", "HR")


def _random_hearts():
    rng = np.random.default_rng(11)
    hearts = []
    for base in (presets.normal(), presets.heart_failure(), presets.normal().replace(closed_loop=0.0, Pat=1.2)):
        factors = rng.uniform(0.8, 1.25, len(DEFAULT_ACTION_PARAMS))
        hearts.append(base.replace(**{n: float(base.get(n)) * f for n, f in zip(DEFAULT_ACTION_PARAMS, factors)}, HR=float(rng.uniform(55, 85))))
    return hearts


def _central_differences(heart, wrt, metrics, rel=1e-6):
    """(m, k) central differences of the steady-state metrics, one batched simulation."""
    perturbed, steps = [], []
    for name in wrt:
        value = float(heart.get(name))
        step = rel * max(abs(value), 1e-3)
        steps.append(step)
        perturbed += [heart.replace(**{name: value + step}), heart.replace(**{name: value - step})]
    sim = lvenv.simulate(perturbed, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000, traces=False)
    assert set(sim.status) == {"ok"}
    values = np.array([[sim.metrics[m][2 * j] - sim.metrics[m][2 * j + 1] for j in range(len(wrt))] for m in metrics])
    return values / (2.0 * np.array(steps))[None, :]


def _assert_close(ad, fd, where, rtol=2e-3):
    """Each entry within rtol of the difference quotient, or within rtol of its metric's largest
    derivative (the derivatives of one metric share its units; a near-zero entry is only as exact
    as the largest one's round-off)."""
    scale = np.max(np.abs(fd), axis=1, keepdims=True)
    bad = np.abs(ad - fd) > rtol * np.maximum(np.abs(fd), 1e-2 * scale)
    assert not bad.any(), f"{where}: autodiff {ad[bad]} against differences {fd[bad]} at (metric, parameter) {np.argwhere(bad).tolist()}"


def test_derivatives_match_central_differences_closed_and_open_loop_and_in_a_batch():
    hearts = _random_hearts()
    batch = lvenv.jacobian(hearts, wrt=WRT, metrics=METRICS, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000)
    assert batch.values.shape == (3, len(METRICS), len(WRT)) and list(batch.status) == ["ok"] * 3
    for i, heart in enumerate(hearts):
        fd = _central_differences(heart, WRT, METRICS)
        _assert_close(batch.values[i], fd, f"heart {i} (closed_loop = {float(heart.circulation.closed_loop):g})")
    single = lvenv.jacobian(hearts[2], wrt=WRT, metrics=METRICS, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000)
    np.testing.assert_allclose(single.values, batch.values[2], rtol=1e-9, atol=1e-12)
    assert single["EF", "tau2"] == pytest.approx(batch.values[2, 0, 0])


def test_the_closed_loop_volume_constraint_matters():
    """dEDV/dCat comes mostly from the blood volume that Cat holds at the cold start: without the
    volume row the system would be singular, and a wrong row gives a wrong sign or size."""
    heart = presets.normal()
    jac = lvenv.jacobian(heart, wrt=WRT, metrics=METRICS, steps_per_beat=STEPS, rtol=1e-12, max_beats=3000)
    fd = _central_differences(heart, ("Cat", "C"), ("EDV",))
    _assert_close(np.array([[jac["EDV", "Cat"], jac["EDV", "C"]]]), fd, "normal")
    assert np.all(np.abs(fd) > 1e-3)


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
