"""The multi-element heart as a first-class LO heart (issue 30, item 3): a Heart carries it
(``Heart.elements``), and lvenv.simulate, the env, lvenv.jacobian, patients and presets take it."""

import dataclasses

import gymnasium
import numpy as np
import pytest

import lvenv
from lvenv import lo_model, multielement as me, presets
from lvenv.env.core import default_scheme
from lvenv.params import Arrangement
from lvenv.patients import Patient, builtin
from lvenv.validation import InputError

STEPS = 300
#: The shipped 3-cell series heart of N (its wall's onsets and its own maps).
SERIES3 = presets.normal(model="series3")


def test_simulate_runs_the_model_the_heart_carries():
    """lvenv.simulate of a Heart with elements is lvenv.multielement.simulate's beat, and a
    single-cell Heart with the same maps beats differently (the dispatch is not a no-op)."""
    hearts = [presets.training_condition(k, SERIES3) for k in (1, 3)]
    ours = lvenv.simulate(hearts, beats=2, steps_per_beat=STEPS)
    direct = me.simulate(hearts, SERIES3.elements, beats=2, steps_per_beat=STEPS)
    assert list(ours.status) == list(direct.status) == ["ok", "ok"]
    for name in ("EF", "EDV", "ESV", "ET", "IVRT", "P_lv_peak"):
        np.testing.assert_allclose(ours.metrics[name], direct.metrics[name], rtol=1e-10, err_msg=name)
    single = lvenv.simulate([h.replace(elements=None) for h in hearts], beats=2, steps_per_beat=STEPS)
    assert np.max(np.abs(single.metrics["ET"] - ours.metrics["ET"])) > 1e-3


def test_steady_state_is_a_fixed_point_of_the_beat_and_its_state_is_laid_out_as_documented():
    """To steady state: converged, the final state of 7n + 4 rows, and one more beat from it
    changes EDV and ESV by less than the tolerance; V, P_c and P_at sit where
    lvenv.lo_model.circulation_index says (V: the last trace sample)."""
    res = lvenv.simulate(SERIES3, steps_per_beat=STEPS, rtol=1e-6)
    assert res.status == "ok" and res.converged and res.final_state.shape == (me.n_states(3),)
    again = lvenv.simulate(SERIES3, beats=1, steps_per_beat=STEPS, initial_state=res.final_state)
    for name in ("EDV", "ESV"):
        assert abs(again.metrics[name] - res.metrics[name]) / res.metrics["EDV"] < 1e-5, name
    i_v, i_pc, i_pat = lo_model.circulation_index(SERIES3)
    assert res.final_state[i_v] == pytest.approx(res.traces.V[-1], rel=1e-12)
    state = me.unflatten(res.final_state[:, None], 3)
    assert state.circ[:, 0] == pytest.approx(res.final_state[[i_v, i_pc, i_pat]])
    assert float(np.mean(state.v_el)) == pytest.approx(res.final_state[i_v], rel=1e-9)  # series: V = mean V_ξ


@pytest.mark.users_level
def test_a_members_result_does_not_depend_on_its_neighbours():
    """A failing member is flagged and the others are bit-identical to a run without it; so are
    they beside a member whose series Newton needs other iterations (another heart, HF's wall)."""
    good = [SERIES3, SERIES3.replace(Sa=1.2)]
    y0 = np.array([lvenv.simulate(SERIES3, beats=1, steps_per_beat=STEPS, traces=False).final_state] * 3)
    y0[1, 0] = np.nan
    mixed = lvenv.simulate([good[0], SERIES3, good[1]], steps_per_beat=STEPS, traces=False, initial_state=y0)
    assert mixed.status[1] == "nonfinite" and np.isnan(mixed.metrics["EF"][1])
    plain = lvenv.simulate(good, steps_per_beat=STEPS, traces=False, initial_state=y0[[0, 2]])
    beside = lvenv.simulate([good[0], presets.heart_failure(model="series3").replace(tau2=0.2), good[1]], steps_per_beat=STEPS, traces=False)
    alone = lvenv.simulate(good, steps_per_beat=STEPS, traces=False)
    assert list(alone.status) == ["ok", "ok"] and beside.status[1] == "ok"
    for name in ("EF", "ET", "P_ao_sys"):
        assert np.array_equal(mixed.metrics[name][[0, 2]], plain.metrics[name]), name
        assert np.array_equal(beside.metrics[name][[0, 2]], alone.metrics[name]), name


def test_walls_with_their_own_onsets_batch_together():
    """N's and HF's 3-cell hearts (different onsets) stack into one batch with per-member onsets,
    each member as it runs alone; the stacked arrangement round-trips through its record."""
    hf = presets.heart_failure(model="series3")
    batch = lvenv.stack([SERIES3, hf])
    assert batch.elements.onsets == (SERIES3.elements.onsets, hf.elements.onsets)
    assert Arrangement.from_dict(batch.elements.to_dict()) == batch.elements
    together = lvenv.simulate(batch, steps_per_beat=STEPS, traces=False)
    for i, heart in enumerate((SERIES3, hf)):
        assert together.metrics["EF"][i] == lvenv.simulate(heart, steps_per_beat=STEPS, traces=False).metrics["EF"]
    with pytest.raises(InputError, match="elements.onsets has 2 rows"):
        lvenv.simulate(dataclasses.replace(SERIES3, elements=batch.elements))


def test_what_a_multi_element_heart_cannot_do_is_refused_by_name():
    with pytest.raises(InputError, match="scheme = 'adaptive' is not available for a multi-element heart"):
        lvenv.simulate(SERIES3, scheme="adaptive", traces=False)
    with pytest.raises(InputError, match=r"member 1 has elements = None but member 0 has Arrangement"):
        lvenv.stack([SERIES3, presets.normal()])
    with pytest.raises(InputError, match=r"member 1 has elements = Arrangement\(kind='parallel'"):
        lvenv.stack([SERIES3, SERIES3.replace(elements=Arrangement("parallel", 3))])
    with pytest.raises(InputError, match="a multi-element heart runs in float64"):
        lvenv.simulate(SERIES3, dtype="float32")
    with pytest.raises(InputError, match=r"initial_state has shape \(9,\); expected \(25,\)"):
        lvenv.simulate(SERIES3, initial_state=np.zeros(9))
    with pytest.raises(InputError, match="heart.elements must be None .* or an lvenv.params.Arrangement"):
        lvenv.simulate(dataclasses.replace(SERIES3, elements="series3"))
    with pytest.raises(InputError, match="model 'series3' has trained maps only"):
        presets.normal(lo="table3", model="series3")


def test_jacobian_of_the_multi_element_heart_matches_finite_differences():
    """d EF / d τ2, d ET / d Sa and d EF / d μ1 by the implicit-function method over the flat state, against
    central differences of steady states (relative step 1e-3: kinks of the step grid are O(h))."""
    jac = lvenv.jacobian(SERIES3, wrt=("tau2", "Sa", "mu1"), metrics=("EF", "ET"), steps_per_beat=STEPS)
    assert jac.status == "ok"
    for metric, name in (("EF", "tau2"), ("ET", "Sa"), ("EF", "mu1")):  # the heart's μ1 sets its cells' (series)
        value = SERIES3.get(name)
        step = 1e-3 * value
        sims = lvenv.simulate([SERIES3.replace(**{name: value + step}), SERIES3.replace(**{name: value - step})],
                              steps_per_beat=STEPS, rtol=1e-9, max_beats=400, traces=False)
        fd = (sims.metrics[metric][0] - sims.metrics[metric][1]) / (2 * step)
        assert jac[metric, name] == pytest.approx(fd, rel=0.05, abs=0.02 * abs(fd) + 1e-6), (metric, name)


def test_the_env_steps_a_multi_element_patient_and_flags_a_bad_action_alone():
    patient = builtin("normal", "series3")
    assert patient.heart.elements == SERIES3.elements and default_scheme(patient.heart) == "fixed"
    with pytest.raises(InputError, match="scheme = 'adaptive' is not available"):
        gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=2, patient=patient, scheme="adaptive")
    venv = gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=3, patient=patient, steps_per_beat=STEPS, autoreset_mode="Disabled")
    assert venv.unwrapped.config.scheme == "fixed", "the env's default scheme follows the patients' model"
    assert gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=1, patient="normal").unwrapped.config.scheme == "adaptive"
    _, info = venv.reset(seed=0)
    assert list(info["status"]) == ["ok"] * 3
    start = np.stack([info["parameters"][n] for n in venv.unwrapped.action_names], 1)
    act = start.copy()
    act[1, 0] = np.nan
    _, reward, _, _, info = venv.step(act)
    assert list(info["status"]) == ["ok", "invalid_action", "ok"] and reward[0] == reward[2]
    state = venv.unwrapped.get_state()
    assert state["y"].shape == (3, me.n_states(3))
    with pytest.raises(InputError, match="different LO heart models"):
        venv.unwrapped.replace_patients([0], [builtin("normal")])
    venv.close()


def test_patient_records_carry_the_model(tmp_path):
    patient = builtin("heart_failure", "series3")
    path = tmp_path / "hf.json"
    patient.to_json(path)
    again = Patient.from_json(path)
    assert again.heart == patient.heart and again.heart.elements.n_elements == 3
    record = patient.to_dict()
    record["elements"] = {"kind": "series", "n_elements": 2, "cells": 2}
    with pytest.raises(InputError, match=r"patient.elements has the unknown field\(s\) \['cells'\]"):
        Patient.from_dict(record)
    assert "elements" not in builtin("normal").to_dict()


def test_arrangement_round_trips_through_its_record():
    arr = Arrangement("parallel", 4, spread=(0.1, 0.2), onsets=(0.0, 0.01, 0.02, 0.03))
    assert Arrangement.from_dict(arr.to_dict()) == arr
    assert Arrangement.from_dict({"kind": "series"}) == Arrangement("series")
