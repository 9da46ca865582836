"""ROS2 order, the analytic Jacobian, conservation and the steady-state loop."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lvenv
from lvenv import cell, integrator, model, presets
from lvenv.circulation import total_volume


def _scan(f, y0, t_end, steps):
    h = jnp.full(y0.shape[1:], t_end / steps)

    def body(y, n):
        return integrator.ros2_step(f, y, h, n * h, (n + 1) * h, jnp.ones_like(h)), None

    return jax.lax.scan(body, y0, jnp.arange(steps, dtype=float))[0]


def test_ros2_is_second_order_on_a_stiff_nonautonomous_problem():
    # Prothero–Robinson: y' = −λ (y − cos t) − sin t, exact y = cos t, stiff for λ = 1e4
    f = lambda t, y: -1e4 * (y - jnp.cos(t)) - jnp.sin(t)
    y0 = jnp.ones((1, 1))
    errs = [abs(float(_scan(f, y0, 1.0, n)[0, 0]) - np.cos(1.0)) for n in (10, 20, 40)]
    # and on a non-stiff one with a curved solution: y' = y cos t, y = exp(sin t)
    g = lambda t, y: y * jnp.cos(t)
    errs_g = [abs(float(_scan(g, y0, 2.0, n)[0, 0]) - np.exp(np.sin(2.0))) for n in (20, 40, 80, 160)]
    orders = np.log2(np.array(errs_g[:-1]) / np.array(errs_g[1:]))
    assert np.all(orders > 1.8), orders
    # stiff (h λ = 250 … 1000): L-stable and still order 2 thanks to the f_t terms
    stiff_orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(stiff_orders > 1.8), (errs, stiff_orders)


def _random_states(seed=0, n=64):
    rng = np.random.default_rng(seed)
    hearts = [presets.normal().replace(closed_loop=float(rng.integers(2)), Sa=rng.uniform(0.5, 2.0), nA=rng.uniform(2, 8), n0=rng.uniform(0.5, 0.9)) for _ in range(n)]
    p = jax.tree.map(jnp.asarray, model.model_params(lvenv.stack(hearts)))
    y = np.stack([
        rng.uniform(0.01, 0.9, n), rng.uniform(0, 0.5, n), rng.uniform(0, 0.2, n), rng.uniform(0, 0.2, n),
        rng.uniform(-2, 1, n), rng.uniform(-1, 1, n), rng.uniform(20, 90, n), rng.uniform(0, 15, n), rng.uniform(0, 3, n),
    ])
    return p, jnp.asarray(y), jnp.asarray(rng.uniform(0.1, 2.5, n))


def test_analytic_jacobian_equals_forward_mode_ad():
    p, y, ca = _random_states()
    k = cell.rates(p.cell)
    _, ad = integrator.ad_jacobian(lambda u, yy: model.rhs_at_calcium(u, yy, p, k), ca, y)
    an = model.jacobian(ca, y, p, k)
    for i in range(model.N_STATES):
        for j in range(model.N_STATES):
            np.testing.assert_allclose(np.broadcast_to(an[i][j], y.shape[1:]), ad[i][j], rtol=1e-10, atol=1e-10, err_msg=f"J[{i}][{j}]")


def test_halving_the_step_shrinks_the_ef_change_at_the_scheme_order():
    heart = presets.training_condition(1)
    ef = {n: lvenv.simulate(heart, beats=1, steps_per_beat=n).metrics["EF"] for n in (250, 500, 1000, 2000)}
    d1, d2, d3 = abs(ef[250] - ef[500]), abs(ef[500] - ef[1000]), abs(ef[1000] - ef[2000])
    # order 2 predicts each halving to shrink the change 4×; require at least 2^1.5 per halving
    assert d2 < d1 / 2**1.5 and d3 < d2 / 2**1.5, (d1, d2, d3)
    assert d2 < 1e-3, "the default step is converged in EF to better than 0.1 percentage points"


@pytest.mark.parametrize("scheme", ["fixed", "adaptive"])
def test_closed_loop_conserves_blood_volume_over_20_beats(scheme):
    heart = presets.normal().replace(closed_loop=1.0)
    res = lvenv.simulate(heart, beats=20, traces=False, scheme=scheme)
    assert res.status == "ok"
    p = model.model_params(heart and lvenv.stack([heart]))
    y0 = model.initial_state(p)[:, 0]
    circ = heart.circulation
    v_start = total_volume(y0[model.IDX_V], y0[model.IDX_PC], y0[model.IDX_PAT], circ)
    y1 = res.final_state
    v_end = total_volume(y1[model.IDX_V], y1[model.IDX_PC], y1[model.IDX_PAT], circ)
    assert abs(v_end - v_start) / v_start < 1e-6
    assert res.beats == 20


@pytest.mark.parametrize("scheme", ["fixed", "adaptive"])
def test_steady_state_loop_converges_and_reports_it(scheme):
    settings = dict(scheme=scheme, traces=scheme == "fixed")
    res = lvenv.simulate(presets.normal(), rtol=1e-5, **settings)
    assert res.status == "ok" and res.converged
    again = lvenv.simulate(presets.normal(), beats=1, initial_state=res.final_state, **settings)
    for key in ("EDV", "ESV", "P_lv_peak"):
        assert again.metrics[key] == pytest.approx(res.metrics[key], rel=1e-4)
    capped = lvenv.simulate(presets.normal(), max_beats=2, rtol=1e-12, **settings)
    assert capped.status == "not_converged" and not capped.converged


def test_anderson_acceleration_reaches_the_same_steady_state_in_fewer_beats():
    """Open loop from a cold start (the slow arterial mode: plain beats contract it by a factor
    of about 0.6 each): the accelerated iteration needs at most half the beats, lands as close to
    a tightly converged reference (within a factor 2: both stop at the same beat-to-beat test),
    and conserves the closed-loop blood volume."""
    rng = np.random.default_rng(4)
    hearts = [presets.normal().replace(tau2=rng.uniform(0.12, 0.22), R3=rng.uniform(0.15, 0.35), C=rng.uniform(8.0, 20.0), closed_loop=0.0)
              for _ in range(4)]
    reference = lvenv.simulate(hearts, rtol=1e-8, max_beats=300, traces=False)
    plain = lvenv.simulate(hearts, traces=False)
    fast = lvenv.simulate(hearts, traces=False, acceleration="anderson")
    assert list(fast.status) == ["ok"] * 4 and list(plain.status) == ["ok"] * 4
    assert np.median(fast.beats) <= np.median(plain.beats) / 2, (fast.beats, plain.beats)
    for key in ("EF", "ESV", "P_ao_sys", "P_ao_dia"):
        err = lambda r: np.max(np.abs(r.metrics[key] / reference.metrics[key] - 1))
        assert err(fast) <= 2 * max(err(plain), 1e-4), key

    closed = presets.heart_failure().replace(closed_loop=1.0)
    res = lvenv.simulate(closed, traces=False, acceleration="anderson", scheme="adaptive")
    y0 = model.initial_state(model.model_params(lvenv.stack([closed])))[:, 0]
    volume = lambda y: total_volume(y[model.IDX_V], y[model.IDX_PC], y[model.IDX_PAT], closed.circulation)
    assert res.status == "ok" and abs(volume(res.final_state) / volume(y0) - 1) < 1e-6


def test_the_number_of_beats_is_an_argument_of_the_compiled_loops_not_a_setting():
    """`simulation.run_beats_jit` compiles once for runs that differ only in ``beats`` or
    ``max_beats`` (a steps-per-beat no other test uses keeps the count its own), and each run
    still stops where it was told."""
    from lvenv.simulation import run_beats_jit

    heart = presets.normal()
    before = run_beats_jit._cache_size()
    one, three = (lvenv.simulate(heart, beats=n, steps_per_beat=333) for n in (1, 3))
    capped, free = (lvenv.simulate(heart, max_beats=n, steps_per_beat=333, traces=False) for n in (2, 200))
    assert run_beats_jit._cache_size() == before + 2, "one program for beats = 1 and 3, one for steady state within 2 and 200 beats"
    assert (one.beats, three.beats, capped.beats) == (1, 3, 2) and one.metrics["EF"] != three.metrics["EF"]
    assert capped.status == "not_converged" and free.status == "ok" and 2 < free.beats < 200
