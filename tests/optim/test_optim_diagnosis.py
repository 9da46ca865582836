"""The congruency diagnosis: valve events as lvenv.events finds them, windows that split C²
exactly, and a pure delay recognised as timing."""

import numpy as np
import pytest

import fe_oracle
from lvenv import presets
from optim import congruency, diagnosis


@pytest.fixture(scope="module")
def beat():
    """A real oracle beat (the multielement backend) under condition ②."""
    return fe_oracle.run(presets.N_UNLOADED, presets.training_circulation(2), "multielement", n_elements=8, use_cache=False)


def test_valve_events_give_the_phase_durations_of_lvenv_events(beat):
    events = diagnosis.valve_events(beat.traces)
    metrics = fe_oracle.beat_metrics(beat)
    assert events["avo"] - events["mvc"] == pytest.approx(metrics["IVCT"], abs=1e-9)
    assert events["avc"] - events["avo"] == pytest.approx(metrics["ET"], abs=1e-9)
    assert events["mvo"] - events["avc"] == pytest.approx(metrics["IVRT"], abs=1e-9)
    masks = diagnosis.window_masks(beat.traces["t"], events)
    assert np.all(sum(m.astype(int) for m in masks.values()) == 1)


def test_windows_split_c_squared_exactly_and_a_pure_delay_is_timing(beat):
    tr = beat.traces
    delay = 0.02
    t_lo = tr["t"] - delay  # the LO beat runs 20 ms early: V_FE(t) = V_LO(t - delay)
    out = diagnosis.decompose(tr, t_lo, tr["V"][None], tr["P_lv"][None])
    assert out["C"] == pytest.approx(float(np.sqrt(congruency.congruency(tr, t_lo, tr["V"][None], tr["P_lv"][None])[0])), rel=1e-12)
    assert sum(out["share"].values()) == pytest.approx(1.0, abs=1e-12)
    assert out["shift_s"] == pytest.approx(delay, abs=diagnosis.SHIFT_STEP_S / 2)
    assert out["timing_share"] > 0.99 and out["C_shifted"] < 0.05 * out["C"]
    scaled = diagnosis.decompose(tr, tr["t"], 1.05 * tr["V"][None], tr["P_lv"][None])
    assert abs(scaled["shift_s"]) <= 0.005 and scaled["timing_share"] < 0.2  # an amplitude error is not timing
