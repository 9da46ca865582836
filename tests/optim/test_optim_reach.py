"""Reachability of human resting values by the identification parameters (optim.reach)."""

import numpy as np

from lvenv import presets
from lvenv.identification import ACTION_BOUNDS, OBSERVATION_TARGETS
from optim.reach import reach


def test_human_resting_values_are_reachable_within_bounds():
    r = reach(presets.normal(), seed=0, progress=False)
    for name, value in r.parameters.items():
        assert ACTION_BOUNDS[name].lo <= value <= ACTION_BOUNDS[name].hi
    assert set(r.relative_error) == set(OBSERVATION_TARGETS)
    for key, target in OBSERVATION_TARGETS.items():
        assert r.relative_error[key] == (r.observation[key] - target) / target
    assert max(abs(e) for e in r.relative_error.values()) < 0.01, r.relative_error
    assert np.isfinite(r.mismatch) and r.status in ("ok", "not_converged")
