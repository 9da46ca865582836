"""`lvenv.plausibility`: the filling-pressure bands enter the env's reward (and LM's residuals)
exactly as documented, only outside the bands, and can be switched off."""

import gymnasium
import numpy as np
import pytest

from lvenv.patients import builtin
from lvenv.plausibility import FILLING, Band, inside_bands, report, resolve
from lvenv.validation import InputError
from optim.lm import _Problem
from lvenv.identification import ParameterSpace

MMHG = 101.325 / 760  # kPa per mmHg (1 atm = 760 mmHg), typed here independently of lvenv.units
# (τ2, Sa, R2, R3, C, Cat): a healthy heart, and one that meets N's targets within 2 % while
# filling at a mean atrial pressure near 90 mmHg (a kriging fit without the bands)
HEALTHY = [0.15, 1.2, 0.02, 0.3, 10.0, 5.0]
CONGESTED = [0.5431, 2.0394, 0.0075, 0.0356, 1.4975, 2.7036]


def _expected_penalty(metrics):
    """Σ (d / 25 mmHg)² over mean atrial pressure and EDP outside 4–25 mmHg."""
    total = 0.0
    for name in ("P_at_mean", "EDP"):
        value = metrics[name] / MMHG
        d = max(0.0, 4.0 - value, value - 25.0)
        total += (d / 25.0) ** 2
    return total


@pytest.fixture(scope="module")
def stepped():
    out = {}
    for on in (True, False):
        env = gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=2, patient="normal", autoreset_mode="Disabled", max_episode_steps=None,
                                 tolerance=0.0, plausibility=on)
        env.reset(seed=0)
        _, reward, _, _, info = env.step(np.array([HEALTHY, CONGESTED]))
        out[on] = (reward, info)
        env.close()
    return out


def test_the_bands_subtract_their_documented_penalty_only_outside_and_change_nothing_else(stepped):
    (r_on, info_on), (r_off, info_off) = stepped[True], stepped[False]
    assert list(info_on["status"]) == ["ok", "ok"]
    for name in ("EF", "IVRT", "EDV", "P_ao_mean", "EDP", "P_at_mean"):
        np.testing.assert_array_equal(info_on[name], info_off[name])  # the simulation is the same
    np.testing.assert_array_equal(info_on["mismatch"], info_off["mismatch"])  # the mismatch is targets only
    healthy = {k: float(info_on[k][0]) for k in ("P_at_mean", "EDP")}
    congested = {k: float(info_on[k][1]) for k in ("P_at_mean", "EDP")}
    assert 4.0 < healthy["P_at_mean"] / MMHG < 25.0 and 4.0 < healthy["EDP"] / MMHG < 25.0
    assert congested["P_at_mean"] / MMHG > 40.0, "the congested heart fills far above the band"
    assert r_on[0] == r_off[0], "inside the bands the reward is unchanged"
    # rel 1e-5: lvenv.units rounds the mmHg conversion to six figures
    assert r_on[1] - r_off[1] == pytest.approx(-_expected_penalty(congested), rel=1e-5)
    assert r_on[1] < r_off[1] - 1.0


def test_least_squares_band_residuals_and_their_jacobian_match_central_differences():
    """LM's band residuals r_b = d_b / s_b and their autodiff rows, at the congested heart, against central differences."""
    space = ParameterSpace.for_names(("tau2", "Sa", "R2", "R3", "C", "Cat"))
    problem = _Problem(builtin("normal"), space, 1000, 200, resolve(True))
    u = space.to_unit(np.array(CONGESTED))
    step, columns = 1e-4, (1, 5)  # Sa and Cat
    shifted = [u + sign * step * np.eye(space.dimension)[j] for j in columns for sign in (1.0, -1.0)]
    (residual, jacobian), *others = problem.evaluate([u, *shifted], [0] * (1 + len(shifted)))  # one batch
    n_targets = len(problem.targets)
    band_res = residual[n_targets:]
    assert band_res[0] == 0.0, "the aortic band holds"
    assert band_res[1] > 0.5 and band_res[2] > 0.3, "mean atrial pressure and EDP above 25 mmHg"
    for i, j in enumerate(columns):
        numeric = (others[2 * i][0][n_targets:] - others[2 * i + 1][0][n_targets:]) / (2 * step)
        np.testing.assert_allclose(jacobian[n_targets:, j], numeric, rtol=1e-3, atol=1e-6)


def test_switches_reports_and_bad_bands():
    assert resolve(False)[0].metric == "P_ao_mean" and len(resolve(False)) == 1
    assert [b.metric for b in resolve(True)] == ["P_ao_mean", "P_at_mean", "EDP"]
    narrow = (Band.mmhg("P_at_mean", 4.0, 12.0, 12.0),)
    assert resolve(narrow)[1:] == narrow
    metrics = {"P_ao_mean": np.array([93.0, 93.0, np.nan]) * MMHG, "P_at_mean": np.array([10.0, 30.0, 10.0]) * MMHG,
               "EDP": np.array([8.0, 8.0, 8.0]) * MMHG}
    assert list(inside_bands(metrics)) == [True, False, False]
    assert list(inside_bands(metrics, False)) == [True, True, False]
    rep = report({k: float(v[1]) for k, v in metrics.items()})
    assert rep["P_at_mean"]["inside"] is False and rep["P_at_mean"]["value"] == pytest.approx(30.0, rel=1e-4)
    assert (rep["P_at_mean"]["low"], rep["P_at_mean"]["high"], rep["P_at_mean"]["units"]) == (pytest.approx(4.0), pytest.approx(25.0), "mmHg")
    assert [b.metric for b in FILLING] == ["P_at_mean", "EDP"]
    with pytest.raises(InputError, match="P_xx"):
        Band("P_xx", 0.0, 1.0, 1.0)
    with pytest.raises(InputError, match="low < high"):
        Band.mmhg("EDP", 25.0, 4.0, 25.0)
    with pytest.raises(InputError, match="plausibility"):
        resolve(["EDP"])
    with pytest.raises(InputError, match="plausibility"):
        gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=1, plausibility="yes")
