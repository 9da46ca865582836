"""Patient records: a cine volume trace becomes frame targets that the model's own frames meet."""

import numpy as np
import pytest

import lvenv
from lvenv.metrics import FRAME_NAMES
from lvenv.patients import builtin
from lvenv.validation import InputError


def test_a_volume_trace_sampled_from_the_model_gives_the_models_own_frames_as_targets():
    patient = builtin("heart_failure")
    res = lvenv.simulate(patient.heart, steps_per_beat=1000, scheme="fixed")
    t = np.asarray(res.traces.t) - float(res.traces.t[0])
    period = t[-1]
    cine = np.arange(25) * period / 25  # a 25-phase cine, not our 20 frames
    traced = patient.with_volume_trace(cine, np.interp(cine, t, np.asarray(res.traces.V)), weight=0.5)
    assert set(traced.targets) == set(patient.targets) | set(FRAME_NAMES)
    assert all(traced.weights[k] == 0.5 for k in FRAME_NAMES) and traced.weight("EF") == 1.0
    frames = np.array([res.metrics[k] for k in FRAME_NAMES])
    targets = np.array([traced.targets[k] for k in FRAME_NAMES])
    assert np.max(np.abs(targets - frames)) < 0.02 * float(res.metrics["SV"]), "resampled from 25 phases: within 2 % of SV"
    assert targets[0] == pytest.approx(float(res.traces.V[0]), abs=1e-9), "frame 0 is the onset, a cine phase too"


@pytest.mark.parametrize(("t", "v", "message"), [
    ([0.0, 0.1, 0.1, 0.3], [60, 50, 40, 50], "increase strictly"),
    ([0.0, 0.3, 0.6, 1.2], [60, 50, 40, 50], "increase strictly within"),
    ([0.0, 0.1, 0.2], [60, 50, 40], "length ≥ 4"),
    ([0.0, 0.1, 0.2, 0.3], [60, 50, 40], "one length"),
])
def test_a_bad_volume_trace_is_refused_naming_what_is_wrong(t, v, message):
    with pytest.raises(InputError, match=message):
        builtin("normal").with_volume_trace(t, v)


def test_a_trace_with_an_impossible_volume_is_refused_by_the_target_check():
    with pytest.raises(InputError, match="V_frame_00"):
        builtin("normal").with_volume_trace([0.0, 0.2, 0.4, 0.6], [-5.0, 50.0, 40.0, 50.0])


def test_the_env_records_the_frames_only_for_patients_that_target_them():
    import gymnasium

    patient = builtin("normal")
    sim = lvenv.simulate(patient.heart, scheme="adaptive", acceleration="anderson", traces=False)
    frames = np.array([sim.metrics[k] for k in FRAME_NAMES])
    traced = patient.with_volume_trace(np.arange(20) * 0.05, frames)
    kwargs = dict(num_envs=2, autoreset_mode="Disabled", max_episode_steps=None)
    with_trace = gymnasium.make_vec("lvenv/LVHeart-v0", patient=[traced, patient], **kwargs)
    without = gymnasium.make_vec("lvenv/LVHeart-v0", patient=patient, **kwargs)
    assert with_trace.unwrapped.config.volume_trace and not without.unwrapped.config.volume_trace
    obs_t, info_t = with_trace.reset(seed=0)
    obs_n, info_n = without.reset(seed=0)
    columns = [with_trace.unwrapped.obs_names.index(k) for k in FRAME_NAMES]
    np.testing.assert_allclose([info_t[k][0] for k in FRAME_NAMES], frames, atol=0.005 * float(sim.metrics["EDV"]))
    assert np.all(obs_n[:, columns] == 0.0) and not set(FRAME_NAMES) & set(info_n), "not recorded: 0 seen, not in info"
    assert without.observation_space.contains(obs_n)
    for k in ("EF", "ET", "P_at_mean"):  # the rest is the same computation
        assert info_t[k][1] == info_n[k][0]
    with pytest.raises(InputError, match="volume_trace=True"):
        without.unwrapped.replace_patients([0], [traced])
    with_trace.close()
    without.close()
