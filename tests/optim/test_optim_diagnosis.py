"""The congruency diagnosis: valve events as lvenv.events finds them, windows that split C²
exactly, and a pure delay recognised as timing; the wall diagnosis's driven cell and stretch maps."""

import numpy as np
import pytest

import fe_oracle
from lvenv import coupling, presets
from optim import congruency, diagnosis
from scripts import wall_diagnosis


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


def test_a_cell_driven_by_an_lo_beats_own_stretch_gives_back_its_tension_and_the_stretch_map_its_slope():
    """scripts/wall_diagnosis.py: the Land cell driven by the trained LO heart's own λ(t), sampled
    every 5 ms as the FE beat is, gives back that heart's Ta(t) (the driven test's only error is
    its integration), and a 10 ms later onset does not; a stretch trace that is a line in V plus
    a pressure term is read back exactly by the stretch-map plane and not by a line in V, and a
    pressure law whose gain follows the volume by the gain fit and not by a constant gain."""
    from lvenv.geometry import cavity_volume
    from lvenv.simulation import simulate
    from lvenv.trained import builtin

    trained = builtin("normal")
    lo, v0 = trained.lo, float(cavity_volume(trained.geometry))
    sim = simulate(trained.heart(presets.training_circulation(2)), beats=1, steps_per_beat=1000)
    t, v, p = (np.asarray(getattr(sim.traces, k), float)[::5] for k in ("t", "V", "P_lv"))
    assert np.diff(t).max() == pytest.approx(0.005, rel=0.05)
    ta = (p - np.asarray(coupling.passive_pressure(v, v0, lo))) / lo.mu2
    lam = np.asarray(coupling.stretch(v, v0, lo))[:, None]
    driven = np.asarray(wall_diagnosis.driven_tension(t, lam, np.array([lo.delay])))[:, 0]
    late = np.asarray(wall_diagnosis.driven_tension(t, lam, np.array([lo.delay + 0.01])))[:, 0]
    error = lambda x: np.linalg.norm(x - ta) / np.linalg.norm(ta)
    assert error(driven) < 0.01 and error(late) > 0.05, (error(driven), error(late))

    x = v / v0 - 1.0
    line = 1.0 + 0.2 * x - 0.004 * p
    fit = wall_diagnosis.stretch_map(x, p, line, diagnosis.window_masks(t, {"mvc": 0.05, "avo": 0.1, "avc": 0.4, "mvo": 0.5}))
    assert fit["rms_plane"] < 1e-12 and fit["dlam_dP_per_kPa"] == pytest.approx(-0.004, rel=1e-9)
    assert fit["rms_poly"] <= fit["rms_linear"] and fit["rms_linear"] > 1e-3
    assert sum(fit["share"].values()) == pytest.approx(1.0) and fit["swing"]["upstroke"] > 0.0

    passive = np.asarray(coupling.passive_pressure(v, v0, lo))
    law = passive + lo.mu2 * (1.0 - 0.3 * x) * ta
    misfit, (mu2, mu2_kappa) = wall_diagnosis.pressure_law(ta, x, passive, law, gain=True)
    assert misfit < 1e-12 and mu2 == pytest.approx(lo.mu2, rel=1e-9) and mu2_kappa / mu2 == pytest.approx(-0.3, rel=1e-9)
    assert wall_diagnosis.pressure_law(ta, x, passive, law, gain=False)[0] > 1e-3
