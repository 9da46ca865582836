"""Physiology of the presets under the training protocol."""

import numpy as np
import pytest

import lvenv
from lvenv import presets
from lvenv.geometry import cavity_volume
from lvenv.units import kpa_to_mmhg


@pytest.mark.parametrize("name", ["normal", "heart_failure"])
def test_training_protocol_beats_are_physiological(name):
    base = getattr(presets, name)()
    v0 = cavity_volume(base.geometry)
    hearts = [presets.training_condition(k, base) for k in (1, 2, 3)]
    res = lvenv.simulate(hearts, beats=1)
    assert list(res.status) == ["ok"] * 3
    ef = res.metrics["EF"]
    peak = kpa_to_mmhg(res.metrics["P_lv_peak"])
    assert np.all((ef > 0.35) & (ef < 0.65)), ef
    # condition 2's low afterload (R3 = 0.05) keeps peak P_lv near 70 mmHg, in the 3-D oracle too
    assert np.all((peak > 65) & (peak < 160)), peak
    assert res.traces.V[1].min() < 0.85 * v0, "condition 2 contracts below 85 % of V0"
    # the LV starts at passive equilibrium with Pat: EDV ordering follows Pat (0.33 < 0.66 < 1.5 kPa)
    assert res.metrics["EDV"][0] < res.metrics["EDV"][1] < res.metrics["EDV"][2]


def test_training_condition_rejects_unknown_k():
    with pytest.raises(ValueError, match="training condition"):
        presets.training_condition(4)
