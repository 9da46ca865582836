"""`optim.minimize` through a real, small vector env (8 members, 500 steps per beat)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import lvenv  # noqa: F401  (registers lvenv/LVHeart-v0)
import optim
from lvenv.identification import ACTION_BOUNDS
from lvenv.identification import ParameterSpace
from lvenv.metrics import OBS_NAMES
from optim.minimize import EnvObjective

N = 8
#: A corner of the bounds where the heart never opens a valve (status "no_valve_cycle").
FAILING = {"tau2": 0.05, "Sa": 0.2, "R2": 0.05, "R3": 0.02, "C": 1.0, "Cat": 1.0}
SMALL = {
    "mads": (48, {"n_candidates": 128}),
    "cma": (48, {}),
}


def make_env(patient="normal", **kwargs):
    settings = dict(num_envs=N, patient=patient, max_episode_steps=None, tolerance=0.0,
                    autoreset_mode="Disabled", steps_per_beat=500, max_beats=60)
    return gymnasium.make_vec("lvenv/LVHeart-v0", **{**settings, **kwargs})


@pytest.fixture(scope="module")
def venv():
    env = make_env()
    yield env
    env.close()


# kriging: its guarantees and a median over seeds in tests/optim/test_optim_kriging.py
@pytest.mark.parametrize("method", ["mads", "cma"])
def test_minimize_reduces_the_mismatch_and_reports_by_name(venv, method):
    budget, options = SMALL[method]
    res = optim.minimize(venv, method, budget=budget, seed=1, progress=False, **options)
    h = res.history
    assert res.evaluations == budget == len(h.mismatch)
    assert set(res.parameters) == set(ACTION_BOUNDS) and set(res.observation) == set(OBS_NAMES)
    for name, value in res.parameters.items():
        assert ACTION_BOUNDS[name].lo <= value <= ACTION_BOUNDS[name].hi
    assert set(res.mismatch_per_target) == {"EF", "ET", "IVRT", "P_ao_pulse"}
    # equal weights: the mismatch is the mean of the per-target errors, from the env's own number
    assert res.mismatch == pytest.approx(np.mean(list(res.mismatch_per_target.values())), rel=1e-9)
    assert res.mismatch == np.min(h.mismatch[h.feasible & (h.f == res.objective)])
    first_round = np.min(h.mismatch[h.batch == 0])
    assert res.mismatch < 0.8 * first_round, (res.mismatch, first_round)
    assert res.status in ("ok", "not_converged") and res.wall_time > 0 and res.stop_reason


def test_best_parameters_reproduce_the_best_observation(venv):
    res = optim.minimize(venv, "cma", budget=16, seed=0, progress=False)
    heart = venv.unwrapped.patients[0].heart.replace(**res.parameters)
    # a batch of 13, as in test_optim_fit, so the two share one compilation
    sim = lvenv.simulate([heart] * 13, scheme="adaptive", acceleration="anderson", max_beats=60, traces=False)
    for name in res.targets:
        assert sim.metrics[name][0] == pytest.approx(res.observation[name], rel=2e-3)


def test_failed_members_are_infeasible_points_not_a_crash():
    """FAILING has no valve cycle the fixed scheme at 500 steps per beat can resolve (its IVCT,
    0.6 ms by Radau, is shorter than one 1.6 ms step), so that env reports it failed; the
    adaptive scheme resolves its weak beat (EF 9 %, as Radau)."""
    venv = make_env(scheme="fixed")
    objective = EnvObjective(venv, ParameterSpace.for_names(venv.unwrapped.action_names))
    venv.reset(seed=0)
    x = np.array([[FAILING[n] for n in objective.space.names], [0.17, 1.0, 0.025, 0.2, 15.0, 2.0]])
    ev = objective.objective()(objective.space.to_unit(x))
    assert ev.feasible.tolist() == [False, True]
    assert objective.records[-1]["status"][0] == "no_valve_cycle"
    assert np.isinf(objective.records[-1]["mismatch"][0]) and np.isfinite(objective.records[-1]["mismatch"][1])
    # a fit started at the failing point goes on (a Latin-hypercube batch follows) and reports a valid best point
    res = optim.minimize(venv, "mads", budget=1 + N, seed=0, progress=False, x0=FAILING, n_candidates=64)
    assert not res.history.feasible[0] and res.history.status[0] == "no_valve_cycle"
    assert np.isfinite(res.mismatch) and res.status in ("ok", "not_converged")
    venv.close()


@pytest.mark.parametrize("method", ["mads", "cma"])
def test_checkpoint_resume_reproduces_an_uninterrupted_run(venv, method, tmp_path):
    budget, options = SMALL[method]
    full = optim.minimize(venv, method, budget=budget, seed=2, progress=False, **options)

    class Interrupt(Exception):
        pass

    rounds = []

    def stop_after_three(opt):
        rounds.append(opt.evaluations)
        if len(rounds) == 3:
            raise Interrupt

    path = tmp_path / "fit.ckpt"
    with pytest.raises(Interrupt):
        optim.minimize(venv, method, budget=budget, seed=2, progress=False, checkpoint=path,
                       callback=stop_after_three, **options)
    assert path.exists()
    venv.step(np.tile(venv.single_action_space.high, (N, 1)))  # disturb the env's warm-start state
    resumed = optim.minimize(venv, method, budget=budget, seed=2, progress=False, checkpoint=path, **options)
    assert resumed.parameters == full.parameters and resumed.mismatch == full.mismatch
    for field in ("x", "f", "mismatch", "observations", "batch"):
        np.testing.assert_array_equal(getattr(resumed.history, field), getattr(full.history, field))
    assert resumed.evaluations == full.evaluations


def test_checkpoint_of_another_configuration_is_refused(venv, tmp_path):
    path = tmp_path / "fit.ckpt"
    optim.minimize(venv, "cma", budget=8, seed=0, progress=False, checkpoint=path)
    with pytest.raises(optim.CheckpointError, match="different optimiser configuration"):
        optim.minimize(venv, "cma", budget=8, seed=1, progress=False, checkpoint=path)
    with pytest.raises(optim.CheckpointError, match="different env or patient"):
        optim.minimize(make_env(patient="heart_failure"), "cma", budget=8, seed=0, progress=False, checkpoint=path)


def test_damaged_checkpoint_is_refused_with_its_path(venv, tmp_path):
    path = tmp_path / "fit.ckpt"
    optim.minimize(venv, "cma", budget=8, seed=0, progress=False, checkpoint=path)
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(optim.CheckpointError, match="fit.ckpt.*damaged"):
        optim.minimize(venv, "cma", budget=8, seed=0, progress=False, checkpoint=path)


def test_bad_input_gives_clear_errors(venv):
    with pytest.raises(ValueError, match="unknown method 'nelder'"):
        optim.minimize(venv, "nelder", budget=100)
    with pytest.raises(ValueError, match="below one batch of 8"):
        optim.minimize(venv, "mads", budget=N - 1)
    with pytest.raises(ValueError, match="below one batch of 16"):
        optim.minimize(venv, "cma", budget=10, popsize_factor=2)
    with pytest.raises(ValueError, match=r"bounds of C = \[20, 5\] ml/kPa: lower must be below upper"):
        optim.minimize(venv, "mads", budget=100, bounds={"C": (20.0, 5.0)})
    with pytest.raises(ValueError, match=r"lower bound of Sa = 0.1 must be a finite real number in \[0.2, 4\]"):
        optim.minimize(venv, "mads", budget=100, bounds={"Sa": (0.1, 2.0)})
    with pytest.raises(ValueError, match="not among the parameters"):
        optim.minimize(venv, "mads", budget=100, bounds={"mu1": (0.1, 0.2)})
    with pytest.raises(ValueError, match="budget = 1.5 must be an integer"):
        optim.minimize(venv, "mads", budget=1.5)
    with pytest.raises(TypeError, match="no option"):
        optim.minimize(venv, "cma", budget=100, poll_size=0.1)
    with pytest.raises(ValueError, match="autoreset_mode='Disabled'"):
        optim.minimize(make_env(autoreset_mode="NextStep"), "mads", budget=100)


@pytest.mark.slow
def test_normalized_action_mode_evaluates_the_same_points(venv):
    physical = optim.minimize(venv, "cma", budget=16, seed=3, progress=False)
    normalized = optim.minimize(make_env(action_mode="normalized"), "cma", budget=16, seed=3, progress=False)
    np.testing.assert_allclose(normalized.history.x, physical.history.x, rtol=1e-12)
    np.testing.assert_allclose(normalized.history.mismatch, physical.history.mismatch, rtol=1e-6)
