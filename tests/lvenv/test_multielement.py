"""Multi-element LO hearts (DESIGN §1.4): reduction to one element, the series DAE constraint,
the arrow-matrix solve, convergence order and physiology at 256 elements."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lvenv
from lvenv import cell, coupling, multielement as me, presets
from lvenv.params import as_batch

#: The paper's Table 3 maps: the multi-element models are defined with them (DESIGN §1.4).
TABLE3 = presets.normal(lo="table3")

CONDITIONS = (1, 2, 3)


def _hearts():
    return [presets.training_condition(k, TABLE3) for k in CONDITIONS]


@pytest.mark.parametrize("kind", me.ARRANGEMENTS)
def test_one_element_reproduces_the_single_element_heart(kind):
    """n = 1 (μ1 = μ1 of the heart, w = 1): the traces and metrics of ``lvenv.simulate`` under ①②③.

    Tolerances are 10× below the integrator's own error at 1000 steps per beat (pointwise V
    ~0.05 ml, EF ~1e-5 against 4000 steps): the two differ only by the W-matrix at the |ζw|
    kink (the ζ̃ form carries round-off in ζ, flipping the one-sided derivative there).
    """
    hearts = _hearts()
    single = lvenv.simulate(hearts, beats=1)
    spread = (hearts[0].lo.mu1,) * 2 if kind == "parallel" else (1.0, 1.0)
    res = me.simulate(hearts, me.Arrangement(kind, 1, spread))
    assert list(res.status) == ["ok"] * 3
    np.testing.assert_allclose(res.traces["t"], single.traces.t, rtol=1e-12)
    np.testing.assert_allclose(res.traces["V"], single.traces.V, atol=5e-3)
    np.testing.assert_allclose(res.traces["P_lv"], single.traces.P_lv, atol=2e-3)
    np.testing.assert_allclose(res.traces["P_ao"], single.traces.P_ao, atol=2e-3)
    for name in ("EDV", "ESV", "SV", "P_lv_peak", "P_ao_sys", "P_ao_dia"):
        np.testing.assert_allclose(res.metrics[name], single.metrics[name], rtol=1e-5, err_msg=name)
    np.testing.assert_allclose(res.metrics["EF"], single.metrics["EF"], atol=1e-5)
    for name in ("IVCT", "ET", "IVRT", "filling_time"):
        np.testing.assert_allclose(res.metrics[name], single.metrics[name], atol=1e-5, err_msg=name)


def test_series_keeps_equal_pressures_to_newton_tolerance():
    """Series, 256 elements, at HR = 240 so that the beat ends in relaxation with high active
    tension: every element's pressure, recomputed from lvenv.cell and lvenv.coupling, equals P."""
    heart = presets.training_condition(2, TABLE3).replace(HR=240.0)
    arr = me.Arrangement("series", 256)
    res = me.simulate(heart, arr, steps_per_beat=500)
    assert res.constraint_residual <= 1e-10 and np.max(res.traces["residual"]) <= 1e-10
    p = me.element_params(as_batch(heart)[0], arr)
    state = me.State(*(np.asarray(x)[..., None] for x in res.final))
    v_el = state.v_el[:, 0]
    lam = np.asarray(coupling.stretch(state.v_el, p.v0, p.lo))[:, 0]
    y = np.asarray(me.zeta(state, p))[:, :, 0]
    ta = np.asarray(cell.active_tension(y, lam, heart.cell))
    w = arr.element_values()
    p_el = w * (heart.lo.mu2 * ta + np.asarray(coupling.passive_pressure(v_el, p.v0[0], heart.lo)))
    assert ta.min() > 5.0, "the check is made under active tension"
    assert np.ptp(v_el) > 5.0, "the elements' volumes differ: the constraint is not trivial"
    np.testing.assert_allclose(p_el, state.p_lv[0], rtol=0, atol=1e-9)
    assert np.mean(v_el) == pytest.approx(state.circ[0, 0], rel=1e-13)


def _dense_reference(kind, p, state, ca):
    """f(y) of the state-space ODE y' = f(y, z(y)) and its dense Jacobian by the implicit
    function theorem, J = f_y − f_z g_z⁻¹ g_y, with every partial from forward-mode AD of the
    constraint g(y, z) = 0 written out directly (no arrow-matrix algebra)."""
    n = state.cells.shape[1]
    k = cell.rates(p.cell)
    lo_el = me._element_lo(p)

    def split(y, z):
        cells, glob = y[: 6 * n].reshape(6, n, 1), y[6 * n :, None]
        v_el, p_lv = z[:n, None], z[n:]
        lam = coupling.stretch(v_el, p.v0, lo_el)
        zeta_form = cells.at[4:6].add(k.a_eff * lam)  # ζ = ζ̃ + A λ
        p_el = p.w * (p.lo.mu2 * cell.active_tension(zeta_form, lam, p.cell) + coupling.passive_pressure(v_el, p.v0, p.lo))
        return glob, v_el, p_lv, lam, zeta_form, p_el[:, 0]

    def g(y, z):
        glob, v_el, p_lv, _, _, p_el = split(y, z)
        if kind == "parallel":  # equal volumes, mean pressure
            return jnp.concatenate([v_el[:, 0] - glob[0], jnp.mean(p_el, keepdims=True) - p_lv])
        return jnp.concatenate([p_el - p_lv, jnp.mean(v_el[:, 0], keepdims=True) - glob[0]])  # equal pressures, mean volume

    def f(y, z):
        glob, _, p_lv, lam, zeta_form, _ = split(y, z)
        q = lvenv.circulation.flows(p_lv, glob[1], glob[2], p.circ)
        return jnp.concatenate([cell.derivatives(zeta_form, ca, lam, 0.0, p.cell, k).ravel(), jnp.stack(lvenv.circulation.windkessel_derivatives(q, p.circ)).ravel()])

    y = jnp.concatenate([state.cells.ravel(), state.circ.ravel()])
    z = jnp.concatenate([state.v_el[:, 0], state.p_lv])
    for _ in range(6):
        z = z - jnp.linalg.solve(jax.jacfwd(g, 1)(y, z), g(y, z))
    g_z, g_y = jax.jacfwd(g, 1)(y, z), jax.jacfwd(g, 0)(y, z)
    jac = jax.jacfwd(f, 0)(y, z) - jax.jacfwd(f, 1)(y, z) @ jnp.linalg.solve(g_z, g_y)
    return f(y, z), jac, jnp.abs(g(y, z)).max()


def _arrow_solve(kind, p, cells, glob, v_el_guess, ca, h):
    """The module's own first ROS2 stage: consistent (V_ξ, P), f, and k = (I − γhJ)⁻¹ f."""
    k = cell.rates(p.cell)
    v_el, p_lv, _, _ = me._algebraic(p, k, cells, glob[0], v_el_guess, glob[0] * 0.0 + 5.0, 1e-13)
    state = me.State(cells, glob, v_el, p_lv)
    f_cells, f_glob = me._rhs(p, k, ca, *state)
    lin = me._linearise(p, k, ca, *state, f_cells, f_glob, h)
    k_cells, k_glob, _ = me._solve(kind, lin, me.GAMMA * h, f_cells, f_glob)
    return state, f_cells, f_glob, k_cells, k_glob


@pytest.mark.parametrize("kind", me.ARRANGEMENTS)
def test_arrow_solve_equals_dense_jacobian_solve(kind):
    """The O(n) block elimination solves the same ROS2 system (I − γhJ) k = f as a dense
    solve with J from forward-mode AD (5 elements, contracting and ejecting: every coupling of
    cells, pressure and circulation is active)."""
    heart = presets.training_condition(2, TABLE3)
    arr = me.Arrangement(kind, 5)
    p = jax.tree.map(jnp.asarray, me.element_params(as_batch(heart)[0], arr))
    s0 = me.initial_state(p)
    rng = np.random.default_rng(3)
    cells = np.array(s0.cells)
    cells[0] = 0.6  # CaTRPN: calcium bound
    cells[1] = 0.5  # B: half the tropomyosin blocked
    cells[2] = 0.15 + 0.02 * rng.random((5, 1))  # S: strongly bound bridges (active tension)
    cells[3] = 0.1 + 0.02 * rng.random((5, 1))  # W
    cells[4:6] += 0.05 * rng.standard_normal((2, 5, 1))  # distortions ζ̃
    p_c = 6.0  # aortic valve wide open
    glob = np.array(s0.circ)
    glob[1] = p_c
    ca = cell.calcium(jnp.asarray([0.08]), p.cell)
    h = jnp.asarray([1e-4])
    state, f_cells, f_glob, k_cells, k_glob = jax.jit(_arrow_solve, static_argnums=0)(kind, p, jnp.asarray(cells), jnp.asarray(glob), jnp.asarray(s0.v_el), ca, h)
    assert float(state.p_lv[0]) > p_c + 1.0, "ejecting"
    f_ref, jac, constraint = jax.jit(_dense_reference, static_argnums=0)(kind, p, state, ca)
    assert constraint < 1e-11
    np.testing.assert_allclose(np.concatenate([np.ravel(f_cells), np.ravel(f_glob)]), f_ref, rtol=1e-10, atol=1e-10)
    dense = np.linalg.solve(np.eye(len(f_ref)) - me.GAMMA * float(h[0]) * np.asarray(jac), np.asarray(f_ref))
    np.testing.assert_allclose(np.concatenate([np.ravel(k_cells), np.ravel(k_glob)]), dense, rtol=1e-8, atol=1e-8 * np.abs(dense).max())


def test_series_dae_is_second_order_in_the_time_step():
    """Series, 256 elements, an isovolumic twitch (P_c = 40 kPa keeps the aortic valve shut,
    Pat = 0.5 kPa the mitral one): the elements trade volume under the equal-pressure
    constraint all beat long. Halving h (500 → 1000 → 2000 steps) shrinks the change of the
    end-of-beat state (cells, element volumes, P) ~4×: ROS2's order 2 on the state-space form.

    (Valve switching is left out: across a valve kink even the single-element heart's P_c
    converges at about first order between 1000 and 4000 steps; and the pointwise P trace
    converges at first order through the stiff CaTRPN clamp of the cell model, in both hearts.)
    """
    heart = presets.training_condition(2, TABLE3).replace(Pat=0.5, Pc0=40.0, R3=10.0, C=200.0)
    arr = me.Arrangement("series", 256)
    ends = []
    for steps in (500, 1000, 2000):
        r = me.simulate(heart, arr, steps_per_beat=steps)
        assert r.constraint_residual <= 1e-10 and r.traces["P_lv"].max() < r.traces["P_c"].min()
        ends.append(np.concatenate([r.final.cells.ravel(), r.final.v_el, [r.final.p_lv]]))
    assert np.ptp(r.final.v_el) > 5.0
    d1, d2 = np.abs(ends[0] - ends[1]).max(), np.abs(ends[1] - ends[2]).max()
    order = np.log2(d1 / d2)
    assert 1.8 < order < 2.3, (d1, d2, order)


@pytest.fixture(scope="module")
def single_element():
    return lvenv.simulate(_hearts(), beats=1)


@pytest.mark.parametrize("kind", me.ARRANGEMENTS)
def test_256_elements_beat_physiologically_under_training_conditions(kind, single_element):
    """A full valve cycle with a physiological EF under ①②③, close to the single-element heart."""
    arr = me.Arrangement(kind, 256)
    runs = [me.simulate(h, arr) for h in _hearts()]
    edv = []
    for i, r in enumerate(runs):
        m = r.metrics
        assert r.status == "ok", (kind, i, r.status)
        assert 0.35 < m["EF"] < 0.75, (kind, i, m["EF"])
        assert 0.015 < m["IVCT"] < 0.08 and 0.12 < m["ET"] < 0.32 and 0.04 < m["IVRT"] < 0.2, (kind, i, m)
        assert 8.0 < m["P_lv_peak"] < 20.0
        assert abs(m["EF"] - single_element.metrics["EF"][i]) < 0.1
        assert m["EDV"] == pytest.approx(single_element.metrics["EDV"][i], rel=0.1)
        assert np.all(np.isfinite(r.traces["V"])) and r.traces["V"].shape == (1001,)
        edv.append(m["EDV"])
    assert edv[0] < edv[1] < edv[2], "EDV follows Pat (0.33 < 0.66 < 1.5 kPa)"
    lam = runs[1].stretch
    assert lam[0] < 1.0 < lam[1], "stretch spans shortening and lengthening elements"


def test_arrangement_is_validated_with_field_value_and_allowed():
    with pytest.raises(ValueError, match=r"arrangement = 'diagonal' is not one of 'parallel', 'series'"):
        me.Arrangement("diagonal")
    with pytest.raises(ValueError, match=r"n_elements = 0 must be an integer in \[1, 4096\]"):
        me.Arrangement("series", 0)
    with pytest.raises(ValueError, match=r"n_elements = 2.5"):
        me.Arrangement("parallel", 2.5)
    with pytest.raises(ValueError, match=r"spread \(w_ξ\)\[0\] = -1"):
        me.Arrangement("series", 4, (-1.0, 1.0))
    values = me.Arrangement("parallel", 256).element_values()
    assert values[0] == 0.01 and values[-1] == pytest.approx(0.179) and np.all(np.diff(values) > 0)
    assert me.Arrangement("series", 1).element_values() == pytest.approx([0.8])


@pytest.mark.parametrize("onset", [0.025, -0.02, -0.05])
def test_an_elements_onset_moves_its_calcium_like_the_single_hearts_delay(onset):
    """One element whose onset is δ is the single-element heart with delay max(delay + δ, 0): an
    onset that ignored its sign, its size or the clip at 0 would miss these traces."""
    hearts = [h.replace(delay=0.03) for h in _hearts()[1:2]]
    shifted = [h.replace(delay=max(0.03 + onset, 0.0)) for h in hearts]
    single = lvenv.simulate(shifted, beats=1)
    res = me.simulate(hearts, me.Arrangement("series", 1, (1.0, 1.0), onsets=(onset,)))
    assert list(res.status) == ["ok"]
    np.testing.assert_allclose(res.traces["V"], single.traces.V, atol=5e-3)
    np.testing.assert_allclose(res.traces["P_lv"], single.traces.P_lv, atol=2e-3)


@pytest.mark.parametrize("kind", me.ARRANGEMENTS)
def test_zero_onsets_are_bit_identical_to_none(kind):
    hearts = _hearts()[:2]
    plain = me.simulate(hearts, me.Arrangement(kind, 3))
    zero = me.simulate(hearts, me.Arrangement(kind, 3, onsets=(0.0, 0.0, 0.0)))
    for name in ("V", "P_lv", "P_ao"):
        np.testing.assert_array_equal(zero.traces[name], plain.traces[name])


def test_onsets_are_validated_with_field_value_and_allowed():
    with pytest.raises(ValueError, match=r"one onset \(s\) per element, 3 in all"):
        me.Arrangement("series", 3, onsets=(0.0, 0.01))
    with pytest.raises(ValueError, match=r"onsets\[1\] = 0.5 must be"):
        me.Arrangement("series", 2, onsets=(0.0, 0.5))
    assert np.array_equal(me.Arrangement("parallel", 2, onsets=(-0.01, 0.01)).element_onsets(), [-0.01, 0.01])
    assert np.array_equal(me.Arrangement("parallel", 2).element_onsets(), [0.0, 0.0])


def test_series_passive_volume_puts_each_cell_at_the_pressure_and_averages_their_volumes():
    """Cells in series of weights w_ξ inflate to the V_ξ with w_ξ Ppass(V_ξ) = P (found here by
    root-finding on the passive law), and the heart's volume is their mean: a heart that used
    one cell's curve, or the sum, or P × w_ξ, would miss it. Equal weights give one cell's curve."""
    from scipy.optimize import brentq

    lo, v0 = TABLE3.lo, 35.8
    arr = me.Arrangement("series", 3, (0.7, 1.3))
    pressures = np.array([0.2, 1.0, 2.5])
    volumes = me.passive_volume(pressures, v0, lo, arr)
    for p, v in zip(pressures, volumes):
        cells = [brentq(lambda x, w=w: w * float(coupling.passive_pressure(x, v0, lo)) - p, v0, 5 * v0, xtol=1e-12) for w in (0.7, 1.0, 1.3)]
        assert v == pytest.approx(np.mean(cells), abs=1e-8)
    assert np.all(np.diff(volumes) > 0)
    np.testing.assert_allclose(me.passive_volume(pressures, v0, lo, me.Arrangement("series", 3, (1.0, 1.0))), coupling.passive_volume(pressures, v0, lo), rtol=1e-14)
