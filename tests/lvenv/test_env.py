"""``lvenv/LVHeart-v0``: Gymnasium API conformance, vector semantics, cohorts, bad input."""

import dataclasses
import warnings

import gymnasium
import jax
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import lvenv
from lvenv import devices, presets
from lvenv.env import LVHeartVectorEnv
from lvenv.metrics import FRAME_NAMES
from lvenv.patients import OBS_NAMES, Patient, builtin

FAST = dict(steps_per_beat=500, max_beats=40)
ENV_ID = "lvenv/LVHeart-v0"
# A healthy action (τ2, Sa, R2, R3, C, Cat in the action space's physical units). A random one
# fails now and then (about 1 draw in 60 gives no valve cycle), which would make the
# episode-bookkeeping tests below depend on the draw.
HEALTHY = np.array([0.15, 1.2, 0.02, 0.3, 10.0, 5.0])


@pytest.fixture(scope="module")
def venv():
    env = gymnasium.make_vec(ENV_ID, num_envs=4, max_episode_steps=3, **FAST)
    yield env
    env.close()


def test_registration_gives_our_single_and_vector_envs(venv):
    assert isinstance(venv, LVHeartVectorEnv)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    env = gymnasium.make(ENV_ID, **FAST)
    assert isinstance(env.unwrapped, lvenv.env.LVHeartEnv)
    assert env.unwrapped.action_space.names == ("tau2", "Sa", "R2", "R3", "C", "Cat")
    assert env.unwrapped.obs_names == OBS_NAMES


# Justified: in the default physical mode the action space is in physical units on purpose (the
# inverse problem identifies physical parameters); action_mode="normalized" is there for RL.
JUSTIFIED = {"physical": ("symmetric and normalized space",), "normalized": ()}


@pytest.mark.parametrize("mode", ["physical", "normalized"])
def test_check_env_passes_with_only_justified_warnings(mode):
    env = gymnasium.make(ENV_ID, render_mode="rgb_array", action_mode=mode, **FAST).unwrapped
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=False)
    unexplained = [str(w.message) for w in caught if not any(j in str(w.message) for j in JUSTIFIED[mode])]
    assert not unexplained, unexplained


def test_shapes_dtypes_and_spaces_contain_observations(venv):
    obs, info = venv.reset(seed=3)
    assert obs.shape == (4, len(OBS_NAMES)) and obs.dtype == np.float64
    assert venv.observation_space.contains(obs)
    venv.action_space.seed(3)
    obs, reward, terminated, truncated, info = venv.step(venv.action_space.sample())
    assert obs.shape == (4, len(OBS_NAMES)) and venv.observation_space.contains(obs)
    assert reward.shape == (4,) and reward.dtype == np.float64 and np.all(np.isfinite(reward))
    assert terminated.dtype == bool and truncated.dtype == bool
    usable = np.isin(info["status"], ("ok", "not_converged"))
    for name in OBS_NAMES:  # a failed member: NaN by name, zeros in the observation
        column = obs[:, OBS_NAMES.index(name)]
        if name in FRAME_NAMES:  # no patient targets the volume trace: not recorded, not in info
            assert name not in info and np.all(column == 0.0)
            continue
        np.testing.assert_array_equal(info[name][usable], column[usable])
        assert np.all(np.isnan(info[name][~usable])) and np.all(column[~usable] == 0.0)
    assert np.all(terminated[~usable]) and np.all(reward[~usable] == -10.0)


def test_next_step_autoreset(venv):
    venv.reset(seed=0)
    action = np.tile(HEALTHY, (4, 1))
    for _ in range(2):
        _, _, terminated, truncated, info = venv.step(action)
        assert np.all(info["status"] == "ok")
        assert not info["reset"].any() and not (terminated | truncated).any()
    _, _, terminated, truncated, info = venv.step(action)
    assert truncated.all(), "max_episode_steps = 3"
    obs_reset, reward, terminated, truncated, info = venv.step(action)
    assert info["reset"].all() and np.all(reward == 0.0) and not (terminated | truncated).any()
    reset_obs, _ = venv.reset(seed=0)
    np.testing.assert_allclose(obs_reset, reset_obs, rtol=1e-10)


def test_reset_is_deterministic_including_noise():
    env = gymnasium.make_vec(ENV_ID, num_envs=3, obs_noise=0.02, **FAST)
    actions = np.tile(HEALTHY, (3, 1))
    runs = []
    for _ in range(2):
        obs0, _ = env.reset(seed=42)
        obs1 = env.step(actions)[0]
        runs.append((obs0, obs1))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    other = env.reset(seed=43)[0]
    assert not np.array_equal(other, runs[0][0]), "noise comes from the seeded key"


def test_vector_env_equals_sync_vector_env_of_single_envs():
    n = 3
    ours = gymnasium.make_vec(ENV_ID, num_envs=n, **FAST)
    sync = gymnasium.make_vec(ENV_ID, num_envs=n, vectorization_mode="sync", **FAST)
    rng = np.random.default_rng(0)
    o1, _ = ours.reset(seed=5)
    o2, _ = sync.reset(seed=5)
    np.testing.assert_allclose(o1, o2, rtol=1e-12)
    for _ in range(3):
        a = rng.uniform(ours.single_action_space.low, ours.single_action_space.high, (n, 6))
        r1, r2 = ours.step(a), sync.step(a)
        for x, y in zip(r1[:4], r2[:4]):
            np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-12)


#: Programs this process has compiled or loaded from the persistent compilation cache so far
#: (JAX's events; the run has a cache, tests/conftest.py).
COMPILES = [0]
_PROGRAM_EVENTS = ("/jax/core/compile/backend_compile_duration", "/jax/compilation_cache/cache_hits")
_count_programs = lambda event, *args, **kwargs: COMPILES.__setitem__(0, COMPILES[0] + (event in _PROGRAM_EVENTS))
jax.monitoring.register_event_duration_secs_listener(_count_programs)
jax.monitoring.register_event_listener(_count_programs)


@pytest.mark.parametrize("sharded, max_episode_steps", [(False, 11), (True, 12)], ids=["one-device", "sharded"])
def test_one_program_is_traced_and_compiled_once_for_resets_and_steps(sharded, max_episode_steps):
    """A reset is a step of members that all need one (lvenv.env.vector): an env of a
    configuration no other test uses traces and compiles one program at its first reset, and
    nothing after, also where the step returns its state and key laid out otherwise than its
    first call took them (on one device, and sharded over all devices) and after a state is restored."""
    num_envs = devices.MIN_MEMBERS_PER_DEVICE * len(jax.devices()) if sharded else 4
    assert devices.layout(num_envs)[0] == (len(jax.devices()) if sharded else 1)
    venv = gymnasium.make_vec(ENV_ID, num_envs=num_envs, max_episode_steps=max_episode_steps, **FAST)
    compiled = COMPILES[0]
    venv.reset(seed=1)
    assert venv.trace_count == 1 and COMPILES[0] > compiled, "the first reset compiles or loads the step (and the count sees it)"
    compiled = COMPILES[0]
    for _ in range(4):
        venv.step(venv.action_space.sample())
    venv.reset(seed=2)
    venv.step(venv.action_space.sample())
    venv.unwrapped.set_state(venv.unwrapped.get_state())
    venv.step(venv.action_space.sample())
    assert venv.trace_count == 1, "no re-tracing after the first reset"
    assert COMPILES[0] == compiled, "no compilation after the first reset"
    venv.close()


def test_cohort_of_three_patients_matches_separate_envs(tmp_path):
    custom = Patient(
        "custom", presets.heart_failure().replace(HR=72.0, Pat=1.2), {"EF": 0.5, "ET": 0.28, "P_ao_mean": 11.0}, {"ET": 2.0}
    )
    path = tmp_path / "custom.json"
    custom.to_json(path)
    roundtrip = Patient.from_json(path)
    assert roundtrip == custom
    cohort = [builtin("normal"), builtin("heart_failure"), roundtrip]
    together = gymnasium.make_vec(ENV_ID, num_envs=3, patient=cohort, **FAST)
    actions = np.array([[0.12, 1.0, 0.02, 0.25, 12.0, 3.0], [0.2, 1.3, 0.03, 0.2, 15.0, 2.0], [0.15, 0.9, 0.01, 0.3, 8.0, 6.0]])
    obs_t, _ = together.reset(seed=0)
    step_t = together.step(actions)
    for i, patient in enumerate(cohort):
        alone = gymnasium.make_vec(ENV_ID, num_envs=1, patient=patient, **FAST)
        obs_a, _ = alone.reset(seed=0)
        step_a = alone.step(actions[i : i + 1])
        np.testing.assert_allclose(obs_t[i], obs_a[0], rtol=1e-10)
        np.testing.assert_allclose(step_t[0][i], step_a[0][0], rtol=1e-10)
        np.testing.assert_allclose(step_t[1][i], step_a[1][0], rtol=1e-10)
    assert len({round(float(x), 6) for x in step_t[1]}) == 3, "members really hold different patients"


def test_replace_patients_restarts_those_members_cold_and_leaves_the_others_bit_identical():
    optimise = dict(autoreset_mode="Disabled", tolerance=0.0, max_episode_steps=None, **FAST)
    env = gymnasium.make_vec(ENV_ID, num_envs=4, patient="normal", **optimise)
    ref = gymnasium.make_vec(ENV_ID, num_envs=4, patient="normal", **optimise)
    first = np.array([[0.12, 1.0, 0.02, 0.25, 12.0, 3.0]] * 4)
    second = np.array([[0.2, 1.3, 0.03, 0.2, 15.0, 2.0], [0.15, 0.9, 0.01, 0.3, 8.0, 6.0],
                       [0.25, 1.1, 0.02, 0.4, 10.0, 4.0], [0.1, 0.8, 0.015, 0.3, 9.0, 5.0]])
    for e in (env, ref):
        e.reset(seed=0)
        e.step(first)
    hf = builtin("heart_failure")
    env.unwrapped.replace_patients([1, 2], [hf, hf])
    assert [p.name for p in env.unwrapped.patients] == ["normal", "heart_failure", "heart_failure", "normal"]
    got, expected = env.step(second), ref.step(second)
    for i in (0, 3):
        assert np.array_equal(got[0][i], expected[0][i]) and got[1][i] == expected[1][i]
    names = env.unwrapped.action_names
    cold = lvenv.simulate([hf.heart.replace(**dict(zip(names, map(float, second[i])))) for i in (1, 2)], traces=False, scheme="adaptive", acceleration="anderson",
                          volume_trace=False, **FAST)
    for j, i in enumerate((1, 2)):
        np.testing.assert_allclose(got[0][i], [np.nan_to_num(cold.metrics[k][j]) for k in OBS_NAMES], rtol=1e-10)  # frames: 0
    assert got[1][1] != expected[1][1], "the replaced members are scored against their new patient"
    with pytest.raises(ValueError, match="distinct member indices"):
        env.unwrapped.replace_patients([1, 1], [hf, hf])
    with pytest.raises(ValueError, match="one patient per member: got 1 for the 2 members"):
        env.unwrapped.replace_patients([0, 3], [hf])


def test_a_cold_start_without_the_reset_steps_like_a_cold_simulation_and_compiles_no_reset():
    """start_cold puts every member at its patient's cold start without simulating (what
    optim.cohort needs before it fills every member): its first step equals simulate() from the
    cold start, and no reset is traced."""
    from lvenv.env.vector import TRACES

    optimise = dict(autoreset_mode="Disabled", tolerance=0.0, max_episode_steps=None, **FAST)
    hf = builtin("heart_failure")
    env = gymnasium.make_vec(ENV_ID, num_envs=2, patient=[builtin("normal"), hf], **optimise)
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.zeros((2, 6)))
    traced = sum(TRACES.values())
    env.unwrapped.start_cold(seed=3)
    assert sum(TRACES.values()) == traced, "start_cold simulates nothing"
    actions = np.array([[0.2, 1.3, 0.03, 0.2, 15.0, 2.0], [0.15, 0.9, 0.01, 0.3, 8.0, 6.0]])
    assert np.array_equal(env.unwrapped.get_state()["parameters"][1], [float(hf.heart.get(n)) for n in env.unwrapped.action_names])
    obs, *_ = env.step(actions)
    names = env.unwrapped.action_names
    patients = env.unwrapped.patients
    cold = lvenv.simulate([patients[i].heart.replace(**dict(zip(names, map(float, actions[i])))) for i in (0, 1)], traces=False,
                          scheme="adaptive", acceleration="anderson", volume_trace=False, **FAST)
    for i in (0, 1):
        np.testing.assert_allclose(obs[i], [np.nan_to_num(cold.metrics[k][i]) for k in OBS_NAMES], rtol=1e-10)


@pytest.fixture(scope="module")
def fuzz_env():
    return gymnasium.make_vec(ENV_ID, num_envs=32, steps_per_beat=250, max_beats=8)


extreme = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([np.nan, np.inf, -np.inf, 1e300, -1e300, 0.0, -1.0]),
    st.floats(-10.0, 300.0),
)


@settings(max_examples=32, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(actions=hnp.arrays(np.float64, (32, 6), elements=extreme))
def test_fuzzing_random_actions_never_raise_or_return_nonfinite(fuzz_env, actions):
    # 32 examples × 32 members = 1,024 actions per run, NaN / ±inf / huge included
    if not hasattr(fuzz_env, "_fuzz_reset"):
        fuzz_env.reset(seed=0)
        fuzz_env._fuzz_reset = True
    obs, reward, terminated, truncated, info = fuzz_env.step(actions)
    assert np.all(np.isfinite(obs)) and np.all(np.isfinite(reward))
    assert fuzz_env.observation_space.contains(obs)
    bad = ~np.all(np.isfinite(actions), axis=1) & ~info["reset"]
    assert np.all(terminated[bad]) and np.all(info["status"][bad] == "invalid_action")


def test_non_finite_action_ends_only_that_member():
    env = gymnasium.make_vec(ENV_ID, num_envs=3, **FAST)
    good = np.array([[0.15, 1.1, 0.02, 0.25, 12.0, 3.0]] * 3)
    bad = good.copy()
    bad[1, 2] = np.nan
    env.reset(seed=0)
    clean = env.step(good)
    env.reset(seed=0)
    dirty = env.step(bad)
    assert dirty[2][1] and dirty[4]["status"][1] == "invalid_action" and np.isfinite(dirty[1][1])
    for i in (0, 2):
        for k in range(4):
            np.testing.assert_array_equal(dirty[k][i], clean[k][i])


def test_out_of_bounds_action_is_clipped_and_reported():
    env = gymnasium.make_vec(ENV_ID, num_envs=2, **FAST)
    env.reset(seed=0)
    a = np.array([[5.0, 1.0, 0.02, 0.25, 12.0, 3.0], [0.15, 1.0, 0.02, 0.25, 12.0, 3.0]])
    _, _, _, _, info = env.step(a)
    assert info["clipped"].tolist() == [True, False]
    assert info["parameters"]["tau2"][0] == pytest.approx(0.6)


def test_normalized_actions_map_onto_bounds():
    env = gymnasium.make_vec(ENV_ID, num_envs=2, action_mode="normalized", **FAST)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([[-1.0] * 6, [1.0] * 6]))
    space = env.unwrapped.config.actions.space
    np.testing.assert_allclose([info["parameters"][n][0] for n in space.names], space.lower, rtol=1e-12)
    np.testing.assert_allclose([info["parameters"][n][1] for n in space.names], space.upper, rtol=1e-12)
    assert env.single_action_space.names == space.names and float(env.single_action_space.high[0]) == 1.0


@pytest.mark.parametrize(
    "record, field",
    [
        ({"name": "x", "geometry": {"Rb": 35}, "targets": {"EF": 0.6}}, "geometry"),
        ({"name": "x", "geometry": dataclasses.asdict(presets.N_UNLOADED), "targets": {"EFF": 0.6}}, "targets"),
        ({"name": "x", "geometry": dataclasses.asdict(presets.N_UNLOADED), "targets": {"EF": "high"}}, "targets"),
        ({"name": "x", "geometry": dataclasses.asdict(presets.N_UNLOADED), "circulation": {"R3": -1}, "targets": {"EF": 0.6}}, "R3"),
        ({"geometry": dataclasses.asdict(presets.N_UNLOADED), "targets": {"EF": 0.6}}, "name"),
    ],
)
def test_malformed_patient_is_rejected_at_construction(record, field):
    with pytest.raises(ValueError, match=field):
        gymnasium.make_vec(ENV_ID, num_envs=1, patient=record, **FAST)


def test_standard_wrappers_and_a_random_search_agent_improve_reward():
    from gymnasium.wrappers import FlattenObservation, NormalizeObservation, RecordEpisodeStatistics

    env = gymnasium.make(ENV_ID, action_mode="normalized", max_episode_steps=40, **FAST)
    env = FlattenObservation(NormalizeObservation(RecordEpisodeStatistics(env)))
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    first = None
    best_r, best_a, scale = -np.inf, np.zeros(6), 0.6
    for i in range(36):
        a = np.clip(best_a + scale * rng.standard_normal(6), -1.0, 1.0)
        _, r, terminated, truncated, info = env.step(a)
        first = r if first is None else first
        if r > best_r:
            best_r, best_a = r, a
        scale *= 0.95
        if terminated or truncated:
            env.reset()
    assert best_r > first + 0.05, (first, best_r)
    assert "episode" in info or env.unwrapped is not None


def test_rgb_array_render_draws_pv_loop():
    env = gymnasium.make(ENV_ID, render_mode="rgb_array", **FAST)
    env.reset(seed=0)
    env.step(HEALTHY)
    img = env.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8
    assert img.std() > 10, "not a blank canvas"
