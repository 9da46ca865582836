"""A batch equals its members; a poisoned member is flagged and leaves the others bit-identical."""

import dataclasses
import os
import pathlib
import re
import subprocess
import sys

import numpy as np
import pytest

import lvenv
from lvenv import devices, presets
from tests.conftest import OPTIMISATION_LEVEL


def cohort():
    base = [presets.normal(), presets.heart_failure()]
    return [base[i % 2].replace(tau2=0.1 + 0.02 * i, Sa=0.9 + 0.05 * i, R3=0.15 + 0.02 * i, HR=60 + 3 * i) for i in range(6)]


def test_batch_equals_members_run_one_by_one():
    hearts = cohort()
    batch = lvenv.simulate(hearts, beats=3)
    for i, heart in enumerate(hearts):
        single = lvenv.simulate(heart, beats=3)
        assert batch.status[i] == single.status
        for key, value in single.metrics.items():
            assert batch.metrics[key][i] == pytest.approx(value, rel=1e-12, abs=1e-12), key
        np.testing.assert_allclose(batch.traces.V[i], single.traces.V, rtol=1e-12)


@pytest.mark.parametrize("scheme", [pytest.param("fixed", marks=pytest.mark.users_level), "adaptive"])
def test_a_member_is_bit_identical_in_batches_of_any_size(scheme):
    """Padding to lvenv.devices.LANES per device: sizes below, at and above one pad block, sizes
    that shard over two devices and sizes that run in several CPU blocks per device give the
    same bits for the same members (metrics and final state), with fixed steps and with
    step-size control. Several hearts: on one heart alone a layout's last-bit difference can
    miss every event (the fixed scheme's precomputed [Ca] agreed for tau2 = 0.15 s and differed
    for 0.10, 0.18, 0.22 and 0.30 s between one device and two)."""
    hearts, other = [presets.normal().replace(tau2=t, HR=72.0) for t in (0.10, 0.15, 0.18, 0.22, 0.30)], presets.heart_failure()
    reference = None
    for n in (5, 8, 9, 17, 128, 200, 600) if scheme == "fixed" else (5, 17, 200, 600):
        res = lvenv.simulate(hearts + [other] * (n - len(hearts)), beats=2, steps_per_beat=200, traces=False, scheme=scheme)
        values = np.concatenate([np.stack([res.metrics[k][: len(hearts)] for k in res.metrics]), res.final_state[: len(hearts)].T])
        reference = values if reference is None else reference
        np.testing.assert_array_equal(values, reference, err_msg=f"batch of {n}")


def test_layout_checks_hold_as_users_compile():
    """The run compiles at XLA's optimisation level 1 (tests/conftest.py), users at its default,
    3, where LLVM vectorises the members' loops differently. A member's bits in batches of any
    size (the single cell) and beside a failing member or another heart (the 3-cell heart)
    therefore hold at level 3 too. Checks like these failed there with jax 0.12.1 (see
    pyproject.toml), where XLA fused multiply-adds in some vector lanes of the multi-element beat
    loop and not in others. The two checks carry the ``users_level`` marker, which the default
    run leaves out of its own level-1 processes: their bits at level 1 are nobody's, and they
    cost 70 s there. The child selects them by that marker, so a check that lost it fails here."""
    checks = ["tests/lvenv/test_batching.py::test_a_member_is_bit_identical_in_batches_of_any_size[fixed]",
              "tests/lvenv/test_lo_model.py::test_a_members_result_does_not_depend_on_its_neighbours"]
    flags = re.sub(rf"{OPTIMISATION_LEVEL}=\d+", "", os.environ.get("XLA_FLAGS", ""))
    env = {key: value for key, value in os.environ.items() if not key.startswith("PYTEST_XDIST")}
    env["XLA_FLAGS"] = f"{flags} {OPTIMISATION_LEVEL}=3".strip()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "users_level", *checks], cwd=pathlib.Path(__file__).resolve().parents[2],
                          env=env, capture_output=True, text=True)
    assert done.returncode == 0 and "2 passed" in done.stdout, done.stdout[-4000:]


def test_queued_members_are_bit_identical_to_a_lone_run():
    """The adaptive scheme to steady state queues a device's members through lanes
    (lvenv.simulation.run_beats_queued): members finish after different numbers of beats, lanes
    take the next member when theirs finishes, and every member (converged, out of beats or
    failed) still gets exactly the bits, beats and steps of a run on its own."""
    rng = np.random.default_rng(3)
    base = presets.normal()
    hearts = [base.replace(tau2=float(t), Sa=float(a), R3=float(r), C=float(c)) for t, a, r, c in
              zip(rng.uniform(0.1, 0.4, 300), rng.uniform(0.6, 1.6, 300), rng.uniform(0.08, 0.3, 300), rng.uniform(3.0, 25.0, 300))]
    y0 = np.stack([lvenv.simulate(h, beats=1, steps_per_beat=200, traces=False).final_state for h in hearts[:2]])
    y_bad = np.repeat(y0[:1], len(hearts), axis=0)
    y_bad[:2] = y0
    y_bad[150, 6] = np.nan  # one member fails at once, and its lane is refilled
    _, blocks, block = devices.layout(len(hearts))
    assert blocks > 1 and blocks * block > devices.queue_lanes(blocks * block), "several blocks per device: the queue is used"
    settings = dict(scheme="adaptive", acceleration="anderson", traces=False, max_beats=5)
    batch = lvenv.simulate(hearts, initial_state=y_bad, **settings)
    assert len(set(batch.beats.tolist())) >= 3 and batch.status[150] == "nonfinite"
    assert {"ok", "not_converged"} <= set(batch.status.tolist()), "some members ran out of beats"
    for i in (0, 1, 63, 64, 150, 151, 298, 299) + tuple(rng.choice(300, 6, replace=False)):
        lone = lvenv.simulate([hearts[i]], initial_state=y_bad[i:i + 1], **settings)
        assert (batch.status[i], batch.beats[i], batch.steps[i]) == (lone.status[0], lone.beats[0], lone.steps[0]), f"member {i}"
        np.testing.assert_array_equal(batch.final_state[i], lone.final_state[0], err_msg=f"member {i}")
        for key in batch.metrics:
            np.testing.assert_array_equal(batch.metrics[key][i], lone.metrics[key][0], err_msg=f"member {i}, {key}")


def test_stacked_pytree_equals_sequence_and_geometry_may_differ():
    hearts = cohort()
    a = lvenv.simulate(hearts, beats=2)
    b = lvenv.simulate(lvenv.stack(hearts), beats=2)
    for key in a.metrics:
        np.testing.assert_array_equal(a.metrics[key], b.metrics[key])
    assert len({round(float(v), 6) for v in a.metrics["EDV"]}) == len(hearts)


@pytest.mark.parametrize("scheme", ["fixed", "adaptive"])
@pytest.mark.parametrize("poison, value, expected", [("nan", np.nan, "nonfinite"), ("huge_volume", 1e4, "diverged")])
def test_poisoned_member_is_flagged_and_others_bit_identical(poison, value, expected, scheme):
    hearts = cohort()
    y0 = np.stack([lvenv.simulate(h, beats=1).final_state for h in hearts])
    y_bad = y0.copy()
    y_bad[2, 6] = value  # LV volume of member 2
    settings = dict(scheme=scheme, traces=scheme == "fixed")
    clean = lvenv.simulate(hearts, initial_state=y0, **settings)
    dirty = lvenv.simulate(hearts, initial_state=y_bad, **settings)
    assert dirty.status[2] == expected
    assert all(np.isnan(v[2]) for v in dirty.metrics.values()), "a failed member's metrics are NaN, never numbers"
    others = [i for i in range(len(hearts)) if i != 2]
    for key in clean.metrics:
        np.testing.assert_array_equal(dirty.metrics[key][others], clean.metrics[key][others])
    np.testing.assert_array_equal(dirty.final_state[others], clean.final_state[others])
    np.testing.assert_array_equal(dirty.status[others], clean.status[others])


def test_out_of_range_parameters_raise_naming_field_value_and_range():
    with pytest.raises(ValueError, match=r"cell\.tau2 = 5 s is outside the allowed range \[0\.01, 2\]"):
        lvenv.simulate(presets.normal().replace(tau2=5.0))
    with pytest.raises(ValueError, match=r"circulation\.R3 = -1 .*\(batch member 1\)"):
        lvenv.simulate([presets.normal(), presets.normal().replace(R3=-1.0)])
    with pytest.raises(ValueError, match="tau1"):
        lvenv.simulate(presets.normal().replace(tau1=0.3, tau2=0.2))
    with pytest.raises(ValueError, match=r"geometry\.L"):
        lvenv.simulate(dataclasses.replace(presets.normal(), geometry=lvenv.Geometry(30, 31, 50, 10, 0.7, -50)))
    with pytest.raises(TypeError, match="unknown Heart parameter"):
        presets.normal().replace(tau3=0.1)


def test_float32_mode_runs_and_stays_close():
    r64 = lvenv.simulate(presets.normal(), beats=2)
    import jax.numpy as jnp

    r32 = lvenv.simulate(presets.normal(), beats=2, dtype=jnp.float32)
    assert r32.status == "ok"
    assert r32.metrics["EF"] == pytest.approx(r64.metrics["EF"], abs=2e-3)
    assert r32.metrics["P_ao_sys"] == pytest.approx(r64.metrics["P_ao_sys"], rel=5e-3)


def test_layout_is_read_back_from_a_padded_batch():
    """Jitted code reads (devices, blocks, block) from the padded size alone: the layout of the
    padded size is the layout of the original size, and blocks never exceed the CPU limit."""
    for n in range(1, 3000, 7):
        used, blocks, block = devices.layout(n)
        assert used * blocks * block == devices.padded_size(n) >= n
        assert devices.layout(devices.padded_size(n)) == (used, blocks, block)
        assert block % devices.LANES == 0 and (blocks == 1 or block <= devices.CPU_BLOCK)


def test_queue_lanes_give_each_lane_several_members(monkeypatch):
    """The adaptive queue's lanes: multiples of LANES between 32 and CPU_BLOCK, at least
    QUEUE_MEMBERS_PER_LANE members each where the range allows, never fewer as the batch grows;
    LVENV_CPU_QUEUE_LANES overrides them and a bad value is refused by name."""
    monkeypatch.delenv("LVENV_CPU_QUEUE_LANES", raising=False)
    members = range(devices.LANES, 4097, devices.LANES)
    lanes = [devices.queue_lanes(m) for m in members]
    assert all(n % devices.LANES == 0 and 2 * devices.LANES <= n <= devices.CPU_BLOCK for n in lanes)
    assert all(n * devices.QUEUE_MEMBERS_PER_LANE <= m or n == 2 * devices.LANES for m, n in zip(members, lanes))
    assert lanes == sorted(lanes) and lanes[0] < lanes[-1] == devices.CPU_BLOCK
    assert devices.queue_lanes(128) == 32 and devices.queue_lanes(512) == 64
    monkeypatch.setenv("LVENV_CPU_QUEUE_LANES", "48")
    assert devices.queue_lanes(128) == 48
    for bad in ("40", "0", "x"):
        monkeypatch.setenv("LVENV_CPU_QUEUE_LANES", bad)
        with pytest.raises(ValueError, match=rf"LVENV_CPU_QUEUE_LANES = '{bad}' must be a positive multiple of 16"):
            devices.queue_lanes(128)


def test_bad_scheme_settings_are_rejected_naming_the_field():
    with pytest.raises(ValueError, match=r"scheme.*'rk4'.*'fixed', 'adaptive'"):
        lvenv.simulate(presets.normal(), scheme="rk4")
    with pytest.raises(ValueError, match="step_tol"):
        lvenv.simulate(presets.normal(), scheme="adaptive", step_tol=0.0, traces=False)
    with pytest.raises(ValueError, match="traces = True needs scheme = 'fixed'"):
        lvenv.simulate(presets.normal(), scheme="adaptive")
    with pytest.raises(ValueError, match=r"acceleration = 'newton' is not one of 'none', 'anderson'"):
        lvenv.simulate(presets.normal(), acceleration="newton")
