"""Fuzzing the public API with 1,300 malformed inputs (patient records, settings, actions, hearts).

Every input must either work or raise lvenv's own :class:`~lvenv.validation.InputError` (no
traceback from NumPy, JAX or Python internals); nothing may return a silent NaN (a NaN metric
only with a failed status), and no non-physical beat may carry status ``ok``.
"""

import dataclasses
import math

import gymnasium
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import lvenv
from lvenv import presets
from lvenv.metrics import FRAME_NAMES, METRIC_NAMES, OBS_NAMES
from lvenv.patients import Patient
from lvenv.simulation import check_settings
from lvenv.status import EF_MIN, is_usable
from lvenv.validation import InputError

FUZZ = dict(deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
FAST = dict(steps_per_beat=100, max_beats=8)

junk = st.one_of(
    st.none(), st.booleans(), st.text(max_size=4), st.integers(-10**6, 10**6),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -1.0, 1e308, -1e308, 1e-320, 0.5, 2.0]),
    st.lists(st.floats(-10, 10), max_size=3), st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)
names = st.sampled_from(["name", "geometry", "lo", "cell", "circulation", "targets", "weights", "extra"])


def valid_record():
    return {"name": "fuzz", "geometry": dataclasses.asdict(presets.N_UNLOADED), "cell": {"tau2": 0.15},
            "targets": {"EF": 0.55, "ET": 0.3, "P_ao_pulse": 6.0}, "weights": {"EF": 2.0}}


@st.composite
def malformed_records(draw):
    rec = valid_record()
    for _ in range(draw(st.integers(1, 3))):
        where = draw(names)
        if where in ("geometry", "lo", "cell", "circulation", "targets", "weights") and draw(st.booleans()):
            inner = dict(rec[where]) if isinstance(rec.get(where), dict) else {}
            key = draw(st.sampled_from([*OBS_NAMES, "Rb", "e", "C0", "mu1", "tau2", "Sa", "closed_loop", "HR", "R3", "bogus"]))
            inner[key] = draw(junk)
            rec[where] = inner
        else:
            rec[where] = draw(junk)
    return rec


@settings(max_examples=400, **FUZZ)
@given(rec=malformed_records())
def test_patient_records(rec):
    try:
        patient = Patient.from_dict(rec)
    except InputError:
        return
    for key, value in patient.targets.items():
        assert math.isfinite(value) and value > 0
    assert any(patient.weight(k) > 0 for k in patient.targets)
    from lvenv.env.core import env_params

    p = env_params([patient])
    assert np.all(np.isfinite(p.targets)) and np.all(np.isfinite(p.weights)) and np.all(np.isfinite(p.y_cold))


setting_values = st.one_of(junk, st.integers(-5, 2000), st.floats(-1.0, 2.0))


@settings(max_examples=300, **FUZZ)
@given(spb=setting_values, mb=setting_values, rtol=setting_values, beats=setting_values, env_kw=st.sampled_from(
    ["num_envs", "max_episode_steps", "tolerance", "obs_noise", "action_mode", "autoreset_mode", "patient", "action_params"]), env_value=junk)
def test_settings(spb, mb, rtol, beats, env_kw, env_value):
    try:
        s = check_settings(steps_per_beat=spb, max_beats=mb, rtol=rtol, beats=beats)
    except InputError:
        pass
    else:
        assert s["steps_per_beat"] >= 10 and s["max_beats"] >= 1 and 0 < s["rtol"] < 1
    try:
        env = gymnasium.make_vec("lvenv/LVHeart-v0", **{"num_envs": 2, **FAST, env_kw: env_value})
    except InputError:
        return
    assert env.unwrapped.num_envs >= 1


@pytest.fixture(scope="module")
def venv():
    env = gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=4, max_episode_steps=None, tolerance=0.0, **FAST)
    env.reset(seed=0)
    yield env
    env.close()


element = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -1.0, 1e300, 0.2, 15.0]))
actions = st.one_of(
    st.lists(st.lists(element, min_size=6, max_size=6), min_size=4, max_size=4),
    st.lists(st.lists(element, min_size=0, max_size=7), min_size=0, max_size=5),
    st.lists(st.lists(st.one_of(element, st.text(max_size=2), st.booleans(), st.none()), min_size=6, max_size=6), min_size=4, max_size=4),
    junk,
)


@settings(max_examples=300, **FUZZ)
@given(action=actions)
def test_actions(venv, action):
    try:
        obs, reward, terminated, truncated, info = venv.step(action)
    except InputError:
        return
    assert venv.observation_space.contains(obs) and np.all(np.isfinite(reward))
    usable = is_usable(info["status"])
    for name in OBS_NAMES:
        if name in FRAME_NAMES and not venv.unwrapped.config.volume_trace:
            assert name not in info
            continue
        assert np.all(np.isfinite(info[name][usable])) and np.all(np.isnan(info[name][~usable]))
    bad = ~np.all(np.isfinite(np.asarray(action, float)), axis=1) & ~info["reset"]  # a reset step ignores the action
    assert np.all(info["status"][bad] == "invalid_action") and np.all(terminated[bad])


parameter = st.sampled_from(["tau2", "Sa", "Cmax", "Tref", "R3", "C", "Cat", "mu2", "c", "HR", "closed_loop", "Pat", "n0", "nA"])


@settings(max_examples=300, **FUZZ)
@given(changes=st.dictionaries(parameter, st.one_of(junk, st.floats(1e-3, 1e3)), min_size=1, max_size=3))
def test_hearts(changes):
    try:
        heart = presets.normal().replace(**changes)
        res = lvenv.simulate([heart] * 2, beats=2, traces=False, **{k: v for k, v in FAST.items() if k != "max_beats"})
    except InputError:
        return
    for i in range(2):
        m = {k: res.metrics[k][i] for k in METRIC_NAMES}
        if is_usable(res.status[i]):
            assert all(np.isfinite(v) for v in m.values())
            assert EF_MIN <= m["EF"] <= 1.0 and 0.0 < m["ESV"] < m["EDV"]
        else:
            assert all(np.isnan(v) for v in m.values())
