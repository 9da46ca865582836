"""The LO heart as one ODE system: cell unit + LO coupling + circulation (DESIGN §1).

State vector (9 entries, on the *first* axis; batches and cells broadcast along the rest)::

    y = [CaTRPN, B, S, W, ζs, ζw,  V (ml),  P_c (kPa),  P_at (kPa)]

``P_at`` is the atrial capacitor pressure in the closed loop; in the open loop it stays constant
(its derivative is zero) and the atrium is held at ``Pat``. The right-hand side is explicit:
P_lv depends on the state only (Ta needs S, W, ζs, ζw and λ(V)), and dλ/dt follows from the
valve flows.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from lvenv import cell, circulation, coupling
from lvenv.params import CellParams, Circulation, Heart, LOParams, cavity_volumes

__all__ = ["ModelParams", "Observables", "N_STATES", "IDX_V", "IDX_PC", "IDX_PAT", "rhs", "rhs_at_calcium", "jacobian", "observe", "initial_state", "model_params"]

N_STATES = cell.N_STATES + 3
IDX_V, IDX_PC, IDX_PAT = cell.N_STATES, cell.N_STATES + 1, cell.N_STATES + 2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ModelParams:
    """What the jitted core needs of a Heart: V0 (ml, derived from the geometry) and the three parts."""

    v0: jax.Array
    lo: LOParams
    cell: CellParams
    circ: Circulation


def model_params(heart: Heart) -> ModelParams:
    """Host-side conversion Heart → ModelParams (computes V0 from each member's geometry)."""
    as_array = lambda tree: jax.tree.map(lambda x: np.asarray(x, dtype=float), tree)
    return ModelParams(
        v0=np.asarray(cavity_volumes(heart), dtype=float),
        lo=as_array(heart.lo),
        cell=as_array(heart.cell),
        circ=as_array(heart.circulation),
    )


@dataclasses.dataclass(frozen=True)
class Observables:
    """Algebraic outputs of a state: stretch, tension (kPa), pressures (kPa) and flows (ml/s)."""

    lam: jax.Array
    ta: jax.Array
    p_lv: jax.Array
    p_at: jax.Array
    p_ao: jax.Array
    flows: circulation.Flows


def observe(y, p: ModelParams) -> Observables:
    """Pressures and flows of state ``y`` (first axis: the 9 states)."""
    v, p_c, p_at_state = y[IDX_V], y[IDX_PC], y[IDX_PAT]
    lam = coupling.stretch(v, p.v0, p.lo)
    ta = cell.active_tension(y[: cell.N_STATES], lam, p.cell)
    p_lv = coupling.lv_pressure(ta, v, p.v0, p.lo)
    q = circulation.flows(p_lv, p_c, p_at_state, p.circ)
    return Observables(
        lam=lam,
        ta=ta,
        p_lv=p_lv,
        p_at=circulation.atrial_pressure(p_at_state, p.circ),
        p_ao=circulation.aortic_pressure(p_c, q, p.circ),
        flows=q,
    )


def rhs(t, y, p: ModelParams):
    """dy/dt of the LO heart; ``t`` is the time since the beat's onset (s)."""
    return rhs_at_calcium(cell.calcium(t, p.cell), y, p, cell.rates(p.cell))


def rhs_at_calcium(ca, y, p: ModelParams, k: cell.Rates):
    """dy/dt given the calcium input ``ca`` (µM) and precomputed cell rates ``k``."""
    obs = observe(y, p)
    d_v, d_pc, d_pat = circulation.windkessel_derivatives(obs.flows, p.circ)
    d_lam = coupling.stretch_rate(d_v, p.v0, p.lo)
    d_cell = cell.derivatives(y[: cell.N_STATES], ca, obs.lam, d_lam, p.cell, k)
    return jnp.concatenate([d_cell, jnp.stack([d_v, d_pc, d_pat])])


def initial_state(p: ModelParams) -> np.ndarray:
    """Training-protocol initial state (DESIGN §1.2), host-side, shape ``(9, ...)``.

    LV at passive equilibrium with the atrial pressure Pat, Windkessel capacitor at Pc0, atrial
    capacitor at Pat, cell at diastolic rest (isometric steady state at Cdia and λ(V)).
    """
    v = coupling.passive_volume(p.circ.Pat, p.v0, p.lo)
    lam = np.asarray(coupling.stretch(v, p.v0, p.lo))
    y_cell = np.asarray(cell.rest_state(lam, p.cell))
    shape = np.shape(v)
    return np.concatenate([y_cell, np.stack([v, np.broadcast_to(p.circ.Pc0, shape), np.broadcast_to(p.circ.Pat, shape)])])


def jacobian(ca, y, p: ModelParams, k: cell.Rates, lookahead=None) -> list[list]:
    """Analytic ∂f/∂y of :func:`rhs_at_calcium` as a 9×9 list of lists (row i = ∂f_i/∂y).

    Structural zeros are the Python float ``0.0`` so that the unrolled LU can skip them. At the
    kinks (clamps, |ζw|) the one-sided derivative of the branch selected by the state is used,
    matching ``jax.jacfwd``; with ``lookahead=None`` so are the valves. Checked against
    forward-mode AD in the tests.

    ``lookahead`` (a state increment, the step's explicit predictor h·f): a valve's conductance
    also enters when the valve is open at y + lookahead (pressures extrapolated linearly). This
    is the W-method freedom of ROS2 (order 2 for any matrix): a step that opens a valve then
    treats the stiff valve flow implicitly instead of chattering across the switch. The matrix
    keeps wᵀJ = 0, so the closed-loop volume stays conserved.
    """
    c, b, s, w, zs, zw, v, p_c, p_at_state = (y[i] for i in range(N_STATES))
    cp, lo, circ = p.cell, p.lo, p.circ
    closed = circ.closed_loop
    m1 = lo.mu1 / p.v0
    lam = coupling.stretch(v, p.v0, lo)
    below_cap = lam < 1.2
    lam_c = jnp.minimum(lam, 1.2)
    # active tension Ta = K h(λ) X and its partials
    b0 = cell.beta0(cp.n0)
    h_raw = 1.0 + b0 * (lam_c + jnp.minimum(lam_c, 0.87) - 1.87)
    h = jnp.maximum(0.0, h_raw)
    dh_dv = jnp.where((h_raw > 0.0) & below_cap, b0 * jnp.where(lam_c < 0.87, 2.0, 1.0), 0.0) * m1
    kt = cp.Sa * cp.Tref / cp.rs
    x_bridges = s * (zs + 1.0) + w * zw
    # P_lv = μ2 Ta + Ppass(V)
    x = v / p.v0 - 1.0
    dppass = jnp.where(
        x <= 0.0,
        lo.alpha * lo.beta * lo.gamma * jnp.exp(-lo.beta * lo.gamma * jnp.minimum(x, 0.0)),
        (3.0 * lo.a * x + 2.0 * lo.b) * x + lo.c,
    ) / p.v0
    dp = {
        2: lo.mu2 * kt * h * (zs + 1.0),
        3: lo.mu2 * kt * h * zw,
        4: lo.mu2 * kt * h * s,
        5: lo.mu2 * kt * h * w,
        6: lo.mu2 * kt * x_bridges * dh_dv + dppass,
    }
    p_lv = lo.mu2 * kt * h * x_bridges + coupling.passive_pressure(v, p.v0, lo)
    p_at = circulation.atrial_pressure(p_at_state, circ)
    open_mv, open_ao = p_at - p_lv > 0.0, p_lv - p_c > 0.0
    if lookahead is not None:
        dp_lv = sum(dpj * lookahead[j] for j, dpj in dp.items())
        dp_at = closed * lookahead[IDX_PAT]
        open_mv |= (p_at + dp_at) - (p_lv + dp_lv) > 0.0
        open_ao |= (p_lv + dp_lv) - (p_c + lookahead[IDX_PC]) > 0.0
    g_mv = jnp.where(open_mv, 1.0 / circ.Rmv, 0.0)
    g_ao = jnp.where(open_ao, 1.0 / (circ.R1 + circ.R2), 0.0)
    # circulation rows: dV, dP_c, dP_at
    row_v = [0.0] * N_STATES
    row_pc = [0.0] * N_STATES
    row_pat = [0.0] * N_STATES
    for j, dpj in dp.items():
        row_v[j] = -(g_mv + g_ao) * dpj
        row_pc[j] = g_ao * dpj / circ.C
        row_pat[j] = closed * g_mv * dpj / circ.Cat
    row_v[IDX_PC] = g_ao
    row_v[IDX_PAT] = closed * g_mv
    row_pc[IDX_PC] = -(g_ao + 1.0 / circ.R3) / circ.C
    row_pc[IDX_PAT] = closed / (circ.R3 * circ.C)
    row_pat[IDX_PC] = closed / (circ.R3 * circ.Cat)
    row_pat[IDX_PAT] = -closed * (closed / circ.R3 + g_mv) / circ.Cat
    # distortion rows: dζ = a_eff μ1/V0 dV − c ζ
    row_zs = [k.a_eff * m1 * e for e in row_v]
    row_zw = [k.a_eff * m1 * e for e in row_v]
    row_zs[4] = row_zs[4] - k.cs
    row_zw[5] = row_zw[5] - k.cw
    # cell rows
    ca50 = cell.ca50(lam, cp)
    ratio_n = (ca / ca50) ** cp.nTRPN
    row_c = [0.0] * N_STATES
    row_c[0] = -cp.kTRPN * (ratio_n + 1.0)
    row_c[IDX_V] = cp.kTRPN * (1.0 - c) * ratio_n * (-cp.nTRPN / ca50) * jnp.where(below_cap, cp.beta1, 0.0) * m1
    half = 0.5 * cp.nA
    c_pos = jnp.maximum(c, 1e-12)
    c_pow = jnp.exp(half * jnp.log(c_pos))
    inv_pow = 1.0 / c_pow
    capped = inv_pow >= 100.0
    unblock = k.kb * jnp.minimum(inv_pow, 100.0)
    u = 1.0 - b - s - w
    row_b = [0.0] * N_STATES
    row_b[0] = jnp.where(c > 1e-12, jnp.where(capped, 0.0, -half * k.kb * inv_pow / c_pos * u) - half * cp.ku * c_pow / c_pos * b, 0.0)
    row_b[1] = -unblock - cp.ku * c_pow
    row_b[2] = -unblock
    row_b[3] = -unblock
    gamma_wu = cp.gamma_w * jnp.abs(zw)
    row_w = [0.0] * N_STATES
    row_w[1] = -k.kuw
    row_w[2] = -k.kuw
    row_w[3] = -k.kuw - (k.kwu + k.kws + gamma_wu)
    row_w[5] = -cp.gamma_w * jnp.sign(zw) * w
    gamma_su = cp.gamma_s * jnp.where(zs > 0.0, zs, jnp.where(zs < -1.0, -zs - 1.0, 0.0))
    row_s = [0.0] * N_STATES
    row_s[2] = -(k.ksu + gamma_su)
    row_s[3] = k.kws
    row_s[4] = -cp.gamma_s * jnp.where(zs > 0.0, 1.0, jnp.where(zs < -1.0, -1.0, 0.0)) * s
    return [row_c, row_b, row_s, row_w, row_zs, row_zw, row_v, row_pc, row_pat]
