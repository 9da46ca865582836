"""`optim.lm.fit_lm`: least squares with autodiff Jacobians converges on a zero-residual problem
and reports the same result type as the other methods."""

import numpy as np
import pytest

import lvenv
from lvenv import presets
from lvenv.patients import Patient
from optim.lm import fit_lm
from optim.minimize import MinimizeResult

STEPS = 1000  # at 250 the interpolated valve events put O(h) kinks into the residuals that stall the trust region early


def test_gauss_newton_reaches_a_zero_residual_fit_from_a_nearby_start_and_reports_it():
    """On the Table 3 heart: near the trained N preset the IVRT of the model jumps by about a step
    (the P_lv − P_at crossing at mitral opening grazes zero), a discontinuity no least-squares
    method is built for (README, "Derivatives")."""
    base = presets.normal(lo="table3")
    truth = base.replace(tau2=float(base.get("tau2")) * 1.15, Sa=float(base.get("Sa")) * 0.9, R3=float(base.get("R3")) * 1.1)
    targets = ("EF", "ET", "IVRT", "P_ao_pulse")
    sim = lvenv.simulate(truth, steps_per_beat=STEPS, rtol=1e-10, max_beats=2000, traces=False)
    patient = Patient("synthetic", base, {k: float(sim.metrics[k]) for k in targets})
    res = fit_lm(patient, budget=20, starts=1, steps_per_beat=STEPS)
    assert isinstance(res, MinimizeResult) and res.method == "lm" and res.status == "ok"
    assert res.evaluations <= 20 and len(res.history.mismatch) == res.evaluations
    assert res.mismatch == pytest.approx(float(np.min(res.history.mismatch)))
    assert res.history.mismatch[0] > 0.05, "it started away from the solution"
    assert res.mismatch < 5e-3, "Gauss-Newton on a consistent problem heads for a zero residual"
    check = lvenv.simulate(base.replace(**res.parameters), steps_per_beat=STEPS, rtol=1e-10, max_beats=2000, traces=False)
    for k in targets:
        assert check.metrics[k] == pytest.approx(patient.targets[k], rel=2e-2)


def test_starts_run_as_one_batch_and_each_takes_the_path_it_takes_alone():
    """Two starts share each batched evaluation; start 0's points and objective values are those
    of a run with start 0 alone (the batch's members do not interact), and the history lists the
    starts' points in batch order, start by start."""
    base = presets.normal(lo="table3")
    patient = Patient("synthetic", base, {"EF": 0.55, "ET": 0.29, "IVRT": 0.08, "P_ao_pulse": 5.3})
    alone = fit_lm(patient, budget=6, starts=1, steps_per_beat=STEPS)
    both = fit_lm(patient, budget=12, starts=2, steps_per_beat=STEPS)
    start = both.optim_result.history.batch  # the optimiser's history: the start of each row
    assert set(start) == {0, 1} and both.optim_result.info["starts"] == 2
    np.testing.assert_array_equal(both.history.x[start == 0], alone.history.x)
    np.testing.assert_array_equal(both.history.f[start == 0], alone.history.f)
    assert np.sum(start == 0) <= 6 and np.sum(start == 1) <= 6 and both.evaluations == len(start)
    # the env history counts batched evaluations: the two starting points went together
    assert list(start[:2]) == [0, 1] and list(both.history.batch[:2]) == [0, 0]
    assert both.optim_result.batches == both.history.batch[-1] + 1 < both.evaluations
    assert both.mismatch == pytest.approx(float(np.min(both.history.mismatch)))
