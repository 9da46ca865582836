"""Bad input at every public entry point: a clear error naming field, value and what is allowed,
or a correct result; non-physical beats and failed members are never reported as numbers."""

import dataclasses
import json

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lvenv
from lvenv import coupling, presets
from lvenv.env.functional import LVHeart
from lvenv.metrics import OBS_NAMES
from lvenv.patients import Patient, builtin
from lvenv.simulation import DEFAULT_STEP_TOL
from lvenv.status import EF_MIN
from lvenv.validation import InputError

FAST = dict(steps_per_beat=200, max_beats=30)
ENV_ID = "lvenv/LVHeart-v0"
N_GEOMETRY = dataclasses.asdict(presets.N_UNLOADED)
#: In-range parameters whose beat ejects more than the heart holds (EF 1.015, ESV −0.6 ml).
OVERDRIVEN = dict(Sa=10.0, Cmax=10.0, Tref=1000.0)


def record(**changes):
    return {"name": "x", "geometry": N_GEOMETRY, "targets": {"EF": 0.6, "ET": 0.3}, **changes}


@pytest.fixture(scope="module")
def venv():
    env = gymnasium.make_vec(ENV_ID, num_envs=3, max_episode_steps=None, tolerance=0.0, **FAST)
    env.reset(seed=0)
    yield env
    env.close()


# ------------------------------------------------------------------ non-physical beats, failed members
def test_an_overdriven_beat_is_non_physical_not_ok():
    res = lvenv.simulate([presets.normal(), presets.normal().replace(**OVERDRIVEN)], beats=2)
    assert res.status.tolist() == ["ok", "non_physical"]
    assert all(np.isnan(v[1]) for v in res.metrics.values())
    assert 0.3 < res.metrics["EF"][0] < 0.8


def test_a_heart_that_fills_by_suction_is_non_physical_not_ok():
    # R3 at 45× its default pools the blood behind it: the atrium would run at −21 mmHg
    res = lvenv.simulate([presets.normal(), presets.normal().replace(R3=10.0)], steps_per_beat=250, traces=False)
    assert res.status.tolist() == ["ok", "non_physical"]
    assert all(np.isnan(v[1]) for v in res.metrics.values()) and res.metrics["EDP"][0] > 0.0


def test_no_ok_beat_is_non_physical_over_random_hearts():
    rng = np.random.default_rng(7)
    ranges = lvenv.params.ranges()
    hearts = []
    for _ in range(96):
        pick = {n: float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))) * presets.normal().get(n)) for n in ("Sa", "Cmax", "tau2", "R3", "C", "Cat")}
        pick = {n: float(np.clip(v, ranges[n][0], ranges[n][1])) for n, v in pick.items()}
        hearts.append(presets.normal().replace(**pick))
    res = lvenv.simulate(hearts, traces=False, steps_per_beat=500, max_beats=40)
    ok = np.isin(res.status, ("ok", "not_converged"))
    m = res.metrics
    assert ok.sum() > 48
    assert np.all((m["EF"][ok] >= EF_MIN) & (m["EF"][ok] <= 1.0) & (m["ESV"][ok] > 0.0) & (m["ESV"][ok] < m["EDV"][ok]))
    assert np.all((m["EDP"][ok] >= 0.0) & (m["P_at_mean"][ok] >= 0.0) & (m["P_ao_dia"][ok] >= 0.0))
    for value in m.values():
        assert np.all(np.isfinite(value[ok])) and np.all(np.isnan(value[~ok]))


def test_an_overdriven_member_fails_its_env_step_and_only_it():
    hot = Patient("hot", presets.normal().replace(**OVERDRIVEN), {"EF": 0.6})
    settings = dict(num_envs=3, action_params=("R3",), max_episode_steps=None, tolerance=0.0, **FAST)
    steps = []
    for patients in (["normal"] * 3, ["normal", hot, "normal"]):
        env = gymnasium.make_vec(ENV_ID, patient=patients, **settings)
        env.reset(seed=0)
        steps.append(env.step(np.full((3, 1), 0.22)))
    (clean_obs, *_), (obs, reward, terminated, _, info) = steps
    assert info["status"][1] in ("non_physical", "diverged", "nonfinite") and terminated[1] and reward[1] == -10.0
    assert np.all(obs[1] == 0.0) and np.isnan(info["EF"][1]) and np.isinf(info["mismatch"][1])
    for k in (0, 2):
        np.testing.assert_array_equal(obs[k], clean_obs[k])


# ------------------------------------------------------------------ settings
@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(rtol=float("nan")), r"rtol = nan must be a finite real number in \(0, 1\)"),
        (dict(rtol=0.0), "rtol = 0.0"),
        (dict(beats=1.5), r"beats = 1.5 must be an integer in \[1, 10000\]"),
        (dict(beats=0), "beats = 0"),
        (dict(beats=True), "beats = True"),
        (dict(max_beats="10"), "max_beats = '10'"),
        (dict(steps_per_beat=5), r"steps_per_beat = 5 must be an integer in \[10, 50000\]"),
        (dict(steps_per_beat=10**7), r"steps_per_beat = 10000000 must be an integer in \[10, 50000\]"),
        (dict(beats=10**9), r"beats = 1000000000 must be an integer in \[1, 10000\]"),
        (dict(max_beats=10**9), r"max_beats = 1000000000 must be an integer in \[1, 10000\]"),
        (dict(steps_per_beat=100.5), "steps_per_beat = 100.5"),
        (dict(traces="yes"), "traces = 'yes' must be True or False"),
        (dict(dtype="int32"), "dtype"),
        (dict(initial_state=np.zeros(5)), r"initial_state has shape \(5,\)"),
        (dict(initial_state="abc"), "initial_state"),
    ],
)
def test_simulate_settings_are_checked(kwargs, message):
    with pytest.raises(InputError, match=message):
        lvenv.simulate(presets.normal(), **kwargs)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(max_beats=0), r"max_beats = 0 must be an integer in \[1, 10000\]"),
        (dict(steps_per_beat=10**7), "steps_per_beat = 10000000"),
        (dict(steps_per_beat=5), "steps_per_beat = 5"),
        (dict(rtol=float("inf")), "rtol = inf"),
        (dict(num_envs=2.5), "num_envs = 2.5"),
        (dict(num_envs=True), "num_envs = True"),
        (dict(num_envs=2.811547515849893e16), r"num_envs = 2.8\d*e\+16 must be an integer in \[1, 4194304\]"),  # found by test_fuzz
        (dict(tolerance=-1.0), "tolerance = -1.0"),
        (dict(max_episode_steps=0), "max_episode_steps = 0"),
        (dict(obs_noise=[0.1, 0.2]), "obs_noise"),
        (dict(obs_noise=-0.1), "obs_noise"),
        (dict(action_params="tau2"), "sequence of names"),
        (dict(action_params=("tau2", "mu1")), "'mu1' has no identification bounds"),
        (dict(action_mode="log"), "action_mode = 'log' is not one of"),
        (dict(autoreset_mode="Sometimes"), "autoreset_mode = None is not one of"),
        (dict(render_mode="human"), "render_mode = 'human'"),
        (dict(patient="nobody"), "neither a built-in patient"),
        (dict(patient=3.5), "patient must be"),
    ],
)
def test_env_settings_are_checked(kwargs, message):
    with pytest.raises(InputError, match=message):
        gymnasium.make_vec(ENV_ID, **{"num_envs": 1, **kwargs})


# ------------------------------------------------------------------ actions
@pytest.mark.parametrize(
    "actions, message",
    [
        (np.zeros((6, 3)), r"actions has shape \(6, 3\); expected \(num_envs, 6\) = \(3, 6\)"),
        (np.zeros(18), r"actions has shape \(18,\)"),
        (np.zeros((3, 6, 1)), r"actions has shape \(3, 6, 1\)"),
        ([["a"] * 6] * 3, "must be a real number or an array of real numbers"),
        (np.ones((3, 6), bool), "dtype bool"),
        ([[1.0] * 6, [1.0] * 5, [1.0] * 6], "actions"),
    ],
)
def test_malformed_vector_actions_are_refused_before_anything_runs(venv, actions, message):
    before = venv.get_state()
    with pytest.raises(InputError, match=message):
        venv.step(actions)
    after = venv.get_state()
    for key in before:
        np.testing.assert_array_equal(before[key], after[key])


def test_single_env_takes_one_action_of_its_own_shape():
    env = gymnasium.make(ENV_ID, **FAST)
    env.reset(seed=0)
    with pytest.raises(InputError, match=r"action has shape \(3, 2\); expected \(6,\)"):
        env.step(np.zeros((3, 2)))
    with pytest.raises(InputError, match=r"action has shape \(1, 6\)"):
        env.step(np.zeros((1, 6)))


# ------------------------------------------------------------------ patients
@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(targets={"EDV": -10.0}), r"targets\['EDV'\] = -10.0 must be a finite real number in \(0, 1000\]"),
        (dict(targets={"EF": 1.2}), r"targets\['EF'\] = 1.2 must be a finite real number in \(0, 1\]"),
        (dict(targets={"EDV": 50.0, "ESV": 60.0}), r"targets\['ESV'\] = 60 must be below patient.targets\['EDV'\] = 50"),
        (dict(targets={"P_ao_sys": 10.0, "P_ao_dia": 12.0}), "P_ao_dia"),
        (dict(targets={"IVCT": 0.3, "ET": 0.5, "IVRT": 0.3}), "add up to more than one beat"),
        (dict(targets=[0.6]), "patient.targets must be an object"),
        (dict(targets={}), "at least one observation"),
        (dict(weights={"EF": 0.0, "ET": 0.0}), "are all zero"),
        (dict(weights={"EF": -1.0}), r"weights\['EF'\] = -1.0"),
        (dict(weights={"EF": float("nan")}), r"weights\['EF'\] = nan"),
        (dict(weights={"EF": "1"}), r"weights\['EF'\] = '1' must be a number"),
        (dict(weights=[1.0]), "patient.weights must be an object"),
        (dict(circulation={"closed_loop": 0.5}), r"circulation.closed_loop = 0.5 must be one of 0, 1"),
        (dict(cell={"tau2": "slow"}), r"cell.tau2 = 'slow' must be a number"),
        (dict(cell={"tau2": [0.1, 0.2]}), r"cell.tau2 = \[0.1, 0.2\] must be a number"),
        (dict(geometry={**N_GEOMETRY, "Rb": True}), "geometry.Rb = True"),
        (dict(geometry=None), "geometry must be an object"),
        (dict(name=""), "name must be a non-empty string"),
    ],
)
def test_malformed_patient_records_are_named(changes, message):
    with pytest.raises(InputError, match=message):
        Patient.from_dict(record(**changes))


def test_null_weights_mean_default_weights_and_huge_weights_change_nothing(venv):
    base = Patient.from_dict(record(weights=None))
    assert base.weight("EF") == base.weight("ET") == 1.0
    huge = Patient.from_dict(record(weights={"EF": 1e300, "ET": 1e300}))
    uneven = Patient.from_dict(record(weights={"EF": 1e308, "ET": 1e-300}))
    env = gymnasium.make_vec(ENV_ID, num_envs=3, patient=[base, huge, uneven], max_episode_steps=None, tolerance=0.0, **FAST)
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step(np.array([[0.15, 1.1, 0.02, 0.25, 12.0, 3.0]] * 3))
    assert np.all(np.isfinite(reward)) and reward[0] == pytest.approx(reward[1], rel=1e-12)
    assert info["mismatch"][0] == pytest.approx(info["mismatch"][1], rel=1e-12) and info["mismatch"][1] > 0.001
    assert info["mismatch"][2] == pytest.approx(abs(info["EF"][2] / 0.6 - 1.0), rel=1e-9)  # only EF counts
    assert not terminated.any()


def test_patient_from_json_text_or_path_and_clear_errors(tmp_path):
    text = json.dumps(record())
    assert Patient.from_json(text).targets == {"EF": 0.6, "ET": 0.3}
    path = tmp_path / "p.json"
    path.write_text(text)
    assert Patient.from_json(path) == Patient.from_json(str(path))
    env = gymnasium.make_vec(ENV_ID, num_envs=1, patient=str(path), **FAST)
    assert env.unwrapped.patients[0].name == "x"
    with pytest.raises(InputError, match="cannot read the patient record .*missing.json"):
        Patient.from_json(tmp_path / "missing.json")
    with pytest.raises(InputError, match="patient JSON text is not valid JSON"):
        Patient.from_json("{not json")
    with pytest.raises(InputError, match="a patient record must be a JSON object, got list"):
        Patient.from_json("[1, 2]")


# ------------------------------------------------------------------ hearts and parameters
def test_wrong_types_are_named_not_raised_from_inside_jax():
    with pytest.raises(InputError, match="expected a sequence of lvenv.Heart, got str"):
        lvenv.simulate("normal")
    with pytest.raises(InputError, match="member 1 is a int"):
        lvenv.simulate([presets.normal(), 3])
    with pytest.raises(InputError, match="cell.tau2 = '0.2' must be a real number"):
        lvenv.simulate(presets.normal().replace(tau2="0.2"))
    with pytest.raises(InputError, match="cell.Sa = .* must be a real number .*complex"):
        lvenv.simulate(presets.normal().replace(Sa=1 + 2j))
    with pytest.raises(InputError, match=r"circulation.closed_loop = 0.5 must be one of 0, 1"):
        lvenv.simulate(presets.normal().replace(closed_loop=0.5))
    with pytest.raises(InputError, match=r"cell.tau2 has shape \(2, 1\)"):
        lvenv.simulate(presets.normal().replace(tau2=[[0.1], [0.2]]))
    with pytest.raises(InputError, match="training condition k = 4 is not one of"):
        presets.training_condition(4)
    with pytest.raises(InputError, match="training condition k = True"):
        presets.training_condition(True)
    with pytest.raises(TypeError, match="unknown Heart parameter"):
        presets.normal().replace(tau3=0.1)


def test_a_list_valued_parameter_is_a_batch_equal_to_its_members():
    batch = lvenv.simulate(presets.normal().replace(tau2=[0.12, 0.2]), beats=2, traces=False)
    one = lvenv.simulate([presets.normal().replace(tau2=0.12), presets.normal().replace(tau2=0.2)], beats=2, traces=False)
    for key in batch.metrics:
        np.testing.assert_array_equal(batch.metrics[key], one.metrics[key])


def test_passive_equilibrium_of_a_member_does_not_depend_on_the_batch():
    lo = presets.N_LO
    pressures = np.array([1e-6, 0.66, 9.9, 3.3e-3, 1.5])
    together = coupling.passive_volume(pressures, 35.8, lo)
    for i, p in enumerate(pressures):
        assert coupling.passive_volume(np.array([p]), 35.8, lo)[0] == together[i]


def test_extreme_members_leave_the_others_bit_identical():
    normal = [presets.normal().replace(tau2=t) for t in (0.1, 0.15, 0.2)]
    extreme = [presets.normal().replace(Pat=9.9, Cat=999.0), presets.normal().replace(**OVERDRIVEN), presets.heart_failure().replace(Pat=1e-6, R3=1e-3)]
    alone = lvenv.simulate(normal, beats=3)
    mixed = lvenv.simulate([normal[0], extreme[0], normal[1], extreme[1], extreme[2], normal[2]], beats=3)
    picked = [0, 2, 5]
    for key in alone.metrics:
        np.testing.assert_array_equal(mixed.metrics[key][picked], alone.metrics[key])
    assert not all(s == "ok" for s in mixed.status[[1, 3, 4]])
    np.testing.assert_array_equal(mixed.final_state[picked], alone.final_state)
    np.testing.assert_array_equal(mixed.traces.V[picked], alone.traces.V)


# ------------------------------------------------------------------ state and functional APIs
def test_env_state_round_trips_and_bad_states_are_refused(venv):
    venv.reset(seed=1)
    venv.step(np.array([[0.15, 1.1, 0.02, 0.25, 12.0, 3.0]] * 3))
    saved = venv.get_state()
    nxt = venv.step(np.array([[0.2, 1.0, 0.02, 0.3, 10.0, 3.0]] * 3))
    venv.step(np.array([[0.3, 2.0, 0.0, 1.0, 20.0, 50.0]] * 3))
    venv.set_state(saved)
    again = venv.step(np.array([[0.2, 1.0, 0.02, 0.3, 10.0, 3.0]] * 3))
    np.testing.assert_array_equal(again[0], nxt[0])
    assert venv.parameters["tau2"].tolist() == [0.2] * 3
    with pytest.raises(InputError, match=r"state\['y'\] has shape \(2, 9\)"):
        venv.set_state({**saved, "y": saved["y"][:2]})
    with pytest.raises(InputError, match="fields"):
        venv.set_state({"y": saved["y"]})


@pytest.mark.parametrize("scheme, rtol", [("fixed", 1e-12), ("adaptive", DEFAULT_STEP_TOL)])
def test_functional_api_jits_vmaps_and_agrees_with_the_vector_env(scheme, rtol):
    """Exactly with fixed steps; with step-size control, last-bit differences between the vmapped
    and the batched program may flip an accept/reject decision, so agreement is to the step tolerance."""
    env = LVHeart(**FAST, tolerance=0.0, scheme=scheme)
    patients = ["normal", "heart_failure", "normal"]
    batch = env.params(patients)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    obs, state = jax.jit(jax.vmap(env.reset))(keys, batch)
    action = jnp.array([[0.15, 1.1, 0.02, 0.25, 12.0, 3.0], [0.2, 0.9, 0.01, 0.3, 10.0, 4.0], [np.nan] * 6])
    obs2, state2, reward, done, info = jax.jit(jax.vmap(env.step))(keys, state, action, batch)
    venv = gymnasium.make_vec(ENV_ID, num_envs=3, patient=patients, max_episode_steps=None, tolerance=0.0, scheme=scheme, **FAST)
    ref_obs, _ = venv.reset(seed=0)
    ref = venv.step(np.asarray(action))
    np.testing.assert_allclose(np.asarray(obs), ref_obs, rtol=rtol)
    np.testing.assert_allclose(np.asarray(obs2), ref[0], rtol=rtol)
    np.testing.assert_allclose(np.asarray(reward), ref[1], rtol=10 * rtol)
    assert np.asarray(done).tolist() == [False, False, True] and int(info["status"][2]) == 100
    assert obs.shape == (3, len(OBS_NAMES)) and env.action_space.shape == (6,)
    single_obs, _ = jax.jit(env.reset)(keys[0], env.params("heart_failure"))
    np.testing.assert_allclose(np.asarray(single_obs), np.asarray(obs[1]), rtol=rtol)


def test_builtin_patients_are_valid_records():
    for name in ("normal", "heart_failure"):
        p = builtin(name)
        assert Patient.from_json(p.to_json()) == p
