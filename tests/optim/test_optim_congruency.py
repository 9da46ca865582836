"""Congruency training: the C² of DESIGN §3, passive and active fits that recover known LO
parameters from data the LO heart generated (the multi-element backend with one element), and
the trained record."""

import dataclasses

import numpy as np
import pytest

import lvenv
from lvenv import presets
from lvenv.params import LOParams
from lvenv.trained import TrainedLO
from lvenv.validation import InputError
from optim import congruency as cg

#: Known maps: Table 3 with μ1 at the one-element value of the parallel arrangement (the midpoint
#: of its μ1 range), another μ2 and γ, and a delay.
TRUTH = dataclasses.replace(presets.N_LO, mu1=0.0945, mu2=0.2, gamma=2.5, delay=0.03)


def lo_data(tmp_path, truth=TRUTH):
    return dict(arrangement="parallel", n_elements=1, lo=truth, cache_dir=tmp_path)


def test_congruency_is_the_relative_l2_error_of_design_section_3():
    t = np.linspace(0.0, 1.0, 201)
    fe = {"t": t, "V": 50.0 + 10.0 * np.sin(2 * np.pi * t), "P_lv": 5.0 + 4.0 * np.cos(2 * np.pi * t)}
    t_lo = np.linspace(0.0, 1.0, 1001)
    v = 50.0 + 10.0 * np.sin(2 * np.pi * t_lo)
    p = 5.0 + 4.0 * np.cos(2 * np.pi * t_lo)
    c2 = cg.congruency(fe, t_lo, np.stack([v, 1.01 * v, v]), np.stack([p, p, 0.98 * p]))
    np.testing.assert_allclose(c2, [0.0, 1e-4, 4e-4], atol=2e-6)


def test_passive_fit_recovers_known_parameters_from_a_synthetic_curve(tmp_path):
    truth = dataclasses.replace(TRUTH, gamma=1.0)
    data = cg.oracle_data(presets.N_UNLOADED, "multielement", **lo_data(tmp_path, truth))
    assert data.passive.traces["P_lv"].min() < 0.0 < data.passive.traces["P_lv"].max()
    fitted, rmse = cg.fit_passive(data, LOParams())
    for name in cg.PASSIVE_NAMES:
        assert getattr(fitted, name) == pytest.approx(getattr(truth, name), rel=1e-6), name
    assert rmse < 1e-8 and fitted.gamma == 1.0


def test_training_recovers_known_lo_parameters_and_writes_a_record(tmp_path):
    trained = cg.train(presets.N_UNLOADED, "multielement", start=LOParams(mu1=0.15, mu2=0.15, gamma=1.5), delay="always",
                       budget=720, progress=False, **lo_data(tmp_path))
    lo = trained.lo
    # γ only scales β in compression: the passive fit (γ = 1) takes the product into β
    assert lo.beta * lo.gamma == pytest.approx(TRUTH.beta * TRUTH.gamma, rel=0.01)
    for name in ("mu1", "mu2", "delay", "alpha", "a", "b", "c"):
        assert getattr(lo, name) == pytest.approx(getattr(TRUTH, name), rel=0.01), name
    assert trained.congruency["C"] < 0.01 and set(trained.congruency) == {"1", "2", "3", "C"}
    prov = trained.provenance
    assert prov["backend"] == "multielement" and set(prov["oracle_keys"]) == {"passive", "1", "2", "3"}
    assert prov["code_version"]["oracle"] and prov["dt_s"] == 0.001
    path = tmp_path / "trained.json"
    trained.to_json(path)
    back = TrainedLO.from_json(path)
    assert back == trained
    res = lvenv.simulate(presets.training_condition(2, back.heart()), beats=1)
    assert res.status == "ok"


def test_a_damaged_record_is_named(tmp_path):
    path = tmp_path / "t.json"
    path.write_text("{}")
    with pytest.raises(ValueError, match=r"t.json.*record lacks the field\(s\) \[.geometry."):
        TrainedLO.from_json(path)
    with pytest.raises(ValueError, match="cannot read the trained-LO record"):
        TrainedLO.from_json(tmp_path / "missing.json")


def test_fidelity_of_the_lo_heart_against_itself_is_within_every_tolerance(tmp_path):
    heart = presets.normal().replace(lo=TRUTH)
    report = cg.check_fidelity(heart, "multielement", beats=3, **lo_data(tmp_path))
    assert report.ok and report.C < 0.02, report  # the oracle starts at its own passive equilibrium: a small transient remains
    assert set(report.rows) == set(cg.FIDELITY_TOLERANCE) and report.lo_status == "ok"
    lo_ef, fe_ef, diff = report.rows["EF"]
    assert diff == pytest.approx(fe_ef - lo_ef) and abs(diff) < 0.005
    # a heart the oracle does not share (another μ2 in the oracle) is caught
    other = cg.check_fidelity(heart, "multielement", beats=3, **lo_data(tmp_path, dataclasses.replace(TRUTH, mu2=0.15)))
    assert not other.ok and other.C > 2 * report.C, (other.C, report.C)



def test_fidelity_refits_the_maps_on_the_oracle_beat_and_compares_again(tmp_path):
    """``retune``: against an oracle whose μ2 the heart does not share, μ2 refitted on the
    oracle's last beat comes back most of the way to the oracle's, and C and the targets' misses
    shrink. (Not all the way: the oracle starts its closed loop at its own passive equilibrium,
    so it holds another blood volume than the LO heart, and its beat differs a little.)"""
    heart = presets.normal().replace(lo=TRUTH)
    oracle = lo_data(tmp_path, dataclasses.replace(TRUTH, mu2=0.15))
    report = cg.check_fidelity(heart, "multielement", beats=3, retune=("mu2",), retune_budget=48, **oracle)
    again = report.retuned
    assert abs(again["lo"]["mu2"] - 0.15) < 0.1 * abs(TRUTH.mu2 - 0.15) and again["lo_status"] == "ok"
    assert not report.ok and again["C"] < report.C / 5, (again["C"], report.C)
    assert set(again["rows"]) == set(cg.FIDELITY_TOLERANCE) and all(again["within"].values())
    assert sum(abs(again["rows"][n][2]) for n in again["rows"]) < sum(abs(report.rows[n][2]) for n in report.rows)
    assert report.to_dict()["retuned"]["lo"] == again["lo"]
    assert cg.check_fidelity(heart, "multielement", beats=3, **oracle).retuned is None
    with pytest.raises(InputError, match=r"retune = \['Sa'\]: only the active maps, the delay and the parameters `bounds` boxes"):
        cg.check_fidelity(heart, "multielement", retune=("Sa",), **oracle)


def test_fidelity_refits_a_passive_map_only_inside_the_box_it_is_given(tmp_path):
    """``retune`` with ``bounds`` (`map_refit` with ``passive``: every passive map within its own
    value ÷ and × `PASSIVE_FREEDOM`): against an oracle whose passive c is 1.5 times the heart's,
    c refitted on the oracle's beat comes back at least two thirds of the way to the oracle's; a
    box that ends below the oracle's c holds it at the box's edge; without a box c is refused by
    name."""
    heart = presets.normal().replace(lo=TRUTH)
    oracle = lo_data(tmp_path, dataclasses.replace(TRUTH, c=1.5 * TRUTH.c))
    names, boxes = cg.map_refit(TRUTH, passive=True)
    assert names == (*cg.MAP_NAMES, *cg.PASSIVE_NAMES) and cg.map_refit(TRUTH) == (cg.MAP_NAMES, None)
    assert boxes["c"] == pytest.approx((TRUTH.c / cg.PASSIVE_FREEDOM, TRUTH.c * cg.PASSIVE_FREEDOM))
    report = cg.check_fidelity(heart, "multielement", beats=3, retune=("c",), retune_budget=48, bounds=boxes, **oracle)
    assert abs(report.retuned["lo"]["c"] - 1.5 * TRUTH.c) < 0.5 * TRUTH.c / 3 and report.retuned["C"] < report.C / 3
    held = cg.check_fidelity(heart, "multielement", beats=3, retune=("c",), retune_budget=48, bounds={"c": (0.5 * TRUTH.c, 1.2 * TRUTH.c)},
                             **oracle)
    assert held.retuned["lo"]["c"] == pytest.approx(1.2 * TRUTH.c, rel=1e-6)
    with pytest.raises(InputError, match=r"retune = \['c'\]"):
        cg.check_fidelity(heart, "multielement", retune=("c",), **oracle)


def test_the_aortic_term_is_the_relative_l2_error_of_the_aortic_pressure():
    """`trace_residuals` of any trace is the relative L2 error that C uses for V and P_lv: an LO
    aortic pressure 2 % above the oracle's gives A = 0.02, and V and P_lv's give `residuals`."""
    t = np.linspace(0.0, 1.0, 201)
    fe = {"t": t, "V": 50.0 + 10.0 * np.sin(2 * np.pi * t), "P_lv": 5.0 + 4.0 * np.cos(2 * np.pi * t), "P_ao": 12.0 + np.sin(2 * np.pi * t)}
    t_lo = np.linspace(0.0, 1.0, 1001)
    p_ao = 12.0 + np.sin(2 * np.pi * t_lo)
    a = np.sqrt(np.sum(cg.trace_residuals(fe, "P_ao", t_lo, np.stack([p_ao, 1.02 * p_ao])) ** 2, axis=1))
    np.testing.assert_allclose(a, [0.0, 0.02], atol=2e-6)
    v, p = 50.0 + 10.0 * np.sin(2 * np.pi * t_lo), 5.0 + 4.0 * np.cos(2 * np.pi * t_lo)
    np.testing.assert_array_equal(cg.residuals(fe, t_lo, 1.01 * v, p),
                                  np.concatenate([cg.trace_residuals(fe, "V", t_lo, 1.01 * v), cg.trace_residuals(fe, "P_lv", t_lo, p)], axis=1))


def test_a_refit_weighing_the_aortic_pressure_in_trades_c_for_it():
    """`fit_maps` with ``aortic_weight``: against the heart's own steady beat (C = 0 at its maps)
    whose aortic pressure is raised 3 %, the refit without the weight keeps the maps exactly,
    and with it moves μ1 to where C² + w A² is smaller, at a C above 0. An oracle beat
    without an aortic pressure, a negative weight, and a weight without maps to refit are refused."""
    heart = presets.normal()
    sim = lvenv.simulate(heart, steps_per_beat=500)
    own = {name: np.asarray(getattr(sim.traces, name)) for name in ("t", "V", "P_lv", "P_ao")}
    raised = dict(own, P_ao=1.03 * own["P_ao"])
    hearts = lambda lo: [dataclasses.replace(heart, lo=lo)]

    def misfits(lo):
        run = lvenv.simulate(hearts(lo), steps_per_beat=500)
        c = np.sqrt(cg.congruency(raised, run.traces.t[0], run.traces.V, run.traces.P_lv)[0])
        return c, np.sqrt(np.sum(cg.trace_residuals(raised, "P_ao", run.traces.t[0], run.traces.P_ao) ** 2))

    settings = dict(budget=32, steps_per_beat=500, run_beats=None, progress=False)
    kept, c_kept = cg.fit_maps(hearts, [raised], heart.lo, ("mu1",), **settings)
    assert kept == heart.lo and c_kept[0] == 0.0
    moved, c_moved = cg.fit_maps(hearts, [raised], heart.lo, ("mu1",), aortic_weight=4.0, **settings)
    (c, a), (_, a_start) = misfits(moved), misfits(heart.lo)
    assert moved.mu1 != heart.lo.mu1 and c_moved[0] == pytest.approx(c, rel=1e-9) and c > 0.0
    assert a < a_start and c**2 + 4.0 * a**2 < 4.0 * a_start**2
    with pytest.raises(InputError, match="aortic_weight = 1 .* P_ao"):
        cg.fit_maps(hearts, [{k: own[k] for k in ("t", "V", "P_lv")}], heart.lo, ("mu1",), aortic_weight=1.0, **settings)
    with pytest.raises(InputError, match="aortic_weight = -1"):
        cg.fit_maps(hearts, [raised], heart.lo, ("mu1",), aortic_weight=-1.0, **settings)
    with pytest.raises(InputError, match="name the maps in retune"):
        cg.check_fidelity(heart, "multielement", aortic_weight=1.0)


def test_fit_active_searches_a_further_lo_parameter_inside_the_box_it_is_given():
    """``bounds`` adds a parameter to the search: against beats the single cell generated with a
    20 % stiffer passive map, fitting {μ2, c} from the trained c recovers that c; a box that
    excludes it keeps c at the box's edge; a box of b two thirds of which makes Ppass non-monotone
    (maps `lvenv.simulate` refuses) is searched without an error, and b is found."""
    import fe_oracle

    truth = dataclasses.replace(presets.N_LO, c=1.2 * presets.N_LO.c)
    sim = lvenv.simulate(cg.training_hearts(presets.N_UNLOADED, presets.normal().cell, [truth]), beats=1, steps_per_beat=500)
    beats = {k: fe_oracle.OracleResult({name: np.asarray(getattr(sim.traces, name))[j] for name in ("t", "V", "P_lv")}, {}, [])
             for j, k in enumerate(cg.CONDITIONS)}
    data = cg.OracleData(presets.N_UNLOADED, presets.normal().cell, None, beats, "lo", {})
    lo, c = cg.fit_active(data, presets.N_LO, ("mu2", "c"), budget=96, steps_per_beat=500, bounds={"c": (0.5 * truth.c, 1.5 * truth.c)})
    assert lo.c == pytest.approx(truth.c, rel=1e-3) and np.all(c < 1e-3)
    capped, _ = cg.fit_active(data, presets.N_LO, ("mu2", "c"), budget=32, steps_per_beat=500, bounds={"c": (0.5 * truth.c, 0.9 * truth.c)})
    assert capped.c == pytest.approx(0.9 * truth.c, rel=1e-3)
    edge = -np.sqrt(3.0 * truth.a * truth.c)  # below it, Ppass is not monotone and the heart is refused
    lo, c = cg.fit_active(data, dataclasses.replace(presets.N_LO, c=truth.c), ("mu2", "b"), budget=96, steps_per_beat=500,
                          bounds={"b": (3.0 * edge, 0.0)})
    assert lo.b == pytest.approx(truth.b, rel=1e-3) and np.all(c < 1e-3), "a box holding refused maps still finds the truth"


def test_a_multi_element_candidate_is_trained_against_beats_it_generated():
    """fit_active with an arrangement trains that arrangement: against beats of 3 cells in series
    with spread onsets (known maps), it recovers μ2 and the delay from a 10 % start with C ≈ 0,
    and its C is the one run_congruency reports for the arrangement, not for the single cell."""
    import fe_oracle
    from lvenv import multielement as me

    truth = dataclasses.replace(presets.N_LO, delay=0.03)
    arr = me.Arrangement("series", 3, (1.0, 1.0), onsets=(-0.02, 0.0, 0.03))
    hearts = cg.training_hearts(presets.N_UNLOADED, presets.normal().cell, [truth])
    sim = me.simulate(hearts, arr, steps_per_beat=500)
    beats = {k: fe_oracle.OracleResult({name: sim.traces[name][j] for name in ("t", "V", "P_lv", "P_ao", "P_c", "P_at")}, {}, [])
             for j, k in enumerate(cg.CONDITIONS)}
    data = cg.OracleData(presets.N_UNLOADED, presets.normal().cell, None, beats, "multielement", {})
    start = dataclasses.replace(truth, mu2=1.1 * truth.mu2, delay=0.9 * truth.delay)
    lo, c = cg.fit_active(data, start, ("mu2", "delay"), budget=64, steps_per_beat=500, arrangement=arr)
    assert lo.mu2 == pytest.approx(truth.mu2, rel=1e-3) and lo.delay == pytest.approx(truth.delay, rel=1e-3)
    assert np.all(c < 1e-3)
    single = cg.overall(cg.run_congruency(data, [lo], 500))
    assert single > 10 * cg.overall(c)
