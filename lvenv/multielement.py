"""Multi-element LO hearts: n cell units in parallel or in series (DESIGN §1.4).

Each element ξ = 1..n is a Land cell unit (:mod:`lvenv.cell`) with its own stretch and tension,
and its own share of the LO pressure law (:mod:`lvenv.coupling`)::

    λ_ξ = μ1_ξ (V_ξ/V0 − 1) + 1
    P_ξ = w_ξ [ μ2 Ta_ξ(cell_ξ, λ_ξ) + Ppass(V_ξ) ]       element pressure law (kPa)

Scaling {α, a, b, c, μ2} by w_ξ scales Ppass and μ2 Ta as a whole (Ppass is linear in α on its
compression branch and in a, b, c on its tension branch; β, γ, μ1 are unscaled), hence the
factored form. The two arrangements close the n laws with the ventricle's V and P:

* **parallel** — all elements share the volume: V_ξ = V, w_ξ = 1, μ1_ξ linear over
  ``spread`` (default [0.01, 0.179]) and P = mean_ξ P_ξ = Ppass(V) + μ2 mean_ξ Ta_ξ;
* **series** — all elements share the pressure: P_ξ = P for every ξ and V = mean_ξ V_ξ,
  μ1_ξ = μ1 and w_ξ linear over ``spread`` (default [0.6, 1.0]).

Element values are ``spread[0] + (spread[1] − spread[0]) · linspace(0, 1, n)`` (both ends
included); one element takes the midpoint. ``onsets`` (optional, s) give each element its own
calcium onset: element ξ's transient starts max(delay + onset_ξ, 0) after the beat's onset
(:func:`lvenv.coupling.calcium` with that delay), so that elements can stand for regions of the
wall that the activation front reaches at different times; by default every element starts at
the LO heart's ``delay``. With n = 1 and the single element at μ1 (parallel)
or w = 1 (series) both arrangements are the single-element LO heart of :mod:`lvenv.model`.

**Distortion in ζ̃ form.** The cells' distortion ODE dζ/dt = A dλ/dt − c ζ (A = Aeff rs /
((1 − rs) rw + rs)) is integrated for ζ̃ = ζ − A λ::

    dζ̃/dt = −c ζ = −c (ζ̃ + A λ)

(:func:`lvenv.cell.derivatives` at dλ/dt = 0 and ζ = ζ̃ + A λ). This affine change of
variables removes dλ/dt from the cell equations: a cell sees its stretch only algebraically, so
the coupled system is an ODE in the parallel arrangement and a semi-explicit index-1 DAE in
the series one.

**States** (batch-last: members on the last axis). Differential: the cells ``(6, n, B)`` in ζ̃
form and the circulation ``(V, P_c, P_at)`` ``(3, B)`` with the valve and Windkessel equations
of :mod:`lvenv.circulation` driven by P. Algebraic: ``z = (V_ξ (n, B), P (B,))``. Parallel:
V_ξ = V and P = mean P_ξ explicitly. Series: z solves

    g(y, z) = [ P_ξ(cell_ξ, V_ξ) − P   (ξ = 1..n);   mean_ξ V_ξ − V ] = 0,

whose Jacobian ∂g/∂z = [[diag d_ξ, −1], [1ᵀ/n, 0]] (d_ξ = ∂P_ξ/∂V_ξ > 0: the passive slope
plus the instantaneous cross-bridge stiffness w μ2 Tref/rs h (S + W) A μ1/V0 of the ζ̃ form) is
nonsingular: the DAE has index 1.

**Solver: ROS2 on the state-space form** (ours). The series algebraic variables are eliminated
by an inner Newton solve at every state ROS2 evaluates, so ROS2 (:mod:`lvenv.integrator`,
Verwer et al. 1999, γ = 1 + 1/√2) integrates the ODE y' = f(y, z(y)) and keeps its order 2 and
L-stability; the constraint holds to the Newton tolerance at every stage and step. Newton on
g(z) = 0 is O(n) by the arrow structure of ∂g/∂z::

    r_ξ = P_ξ − P,  r_m = mean V_ξ − V,  m = mean(1/d_ξ)
    δP  = (mean(r_ξ/d_ξ) − r_m) / m,     δV_ξ = (δP − r_ξ) / d_ξ

started from the linear prediction of the step (so it typically takes 1–2 iterations).

**Jacobian and the linear solve, O(n) per step.** Both arrangements linearise to one scalar
coupling: cell ξ sees the others only through s = V (parallel) or s = P (series), and P
through the linear functional δP = Σ_ξ ρ_ξ·δcell_ξ + ρ_V δV::

    parallel  D_ξ = J_ξ,                 e_ξ = f_λ,ξ μ1_ξ/V0,        ρ_ξ = t_ξ / n,           ρ_V = mean d_ξ
    series    D_ξ = J_ξ − e_ξ t_ξᵀ,       e_ξ = f_λ,ξ μ1/(V0 d_ξ),    ρ_ξ = t_ξ / (n m d_ξ),   ρ_V = 1/m

with J_ξ = ∂f/∂cell and f_λ,ξ = ∂f/∂λ of cell ξ in ζ̃ form, t_ξ = ∂P_ξ/∂cell_ξ and
d_ξ = ∂P_ξ/∂V_ξ. The ROS2 stage system (I − γ h J) k = r becomes, per element and globally,

    (I − γh D_ξ) k_ξ − γh e_ξ s = r_ξ,   (I − γh E) k_g − γh c_P p = r_g,   p = Σ ρ_ξ·k_ξ + ρ_V k_V

(E, c_P: :func:`lvenv.circulation.jacobian` at fixed P). Block elimination (a Schur complement
of the arrow matrix): k_ξ = u_ξ + s v_ξ with u_ξ = (I − γh D_ξ)⁻¹ r_ξ, v_ξ = γh (I − γh D_ξ)⁻¹ e_ξ;
then p = a0 + a1 k_V, a 3 × 3 solve for k_g, and back-substitution. Each element's 6 × 6 LU
is unrolled and vectorised over elements and members. As in the single-element heart a valve
also conducts in the matrix when it is open at the linear prediction y + h f (a W-method
choice, order 2 for any matrix), and f_t comes from the calcium rate.

Valve events and beat metrics use the LO heart's detector (:mod:`lvenv.events`). Status codes
are :mod:`lvenv.status`'s.

**A first-class LO heart.** A :class:`~lvenv.params.Heart` whose ``elements`` is an
:class:`~lvenv.params.Arrangement` is this model everywhere a Heart goes: :func:`beat` integrates
one beat from a flat state (:func:`flatten`, ``7 n + 4`` rows), and the beat loops of
:mod:`lvenv.simulation` (steady state, Anderson acceleration, blocks and devices), and through
them :func:`lvenv.simulate`, the env and :func:`lvenv.jacobian`, call it for such a heart
(:mod:`lvenv.lo_model`). :func:`simulate` here runs a given number of beats and records every
beat's traces, the constraint residual and the stretch range, for studies of the model itself.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from lvenv import cell, circulation, coupling, events, model, status
from lvenv.integrator import GAMMA, is_zero, lu_factor, lu_solve
from lvenv.metrics import METRIC_NAMES
from lvenv.params import ARRANGEMENTS, DEFAULT_SPREAD, MAX_ELEMENTS, MAX_ONSET_S, Arrangement, Heart, LOParams, as_batch
from lvenv.validation import integer, real

__all__ = [
    "ARRANGEMENTS",
    "DEFAULT_SPREAD",
    "MAX_ELEMENTS",
    "MAX_ONSET_S",
    "Arrangement",
    "ElementParams",
    "State",
    "MultiElementResult",
    "element_params",
    "initial_state",
    "run",
    "run_jit",
    "beat",
    "flatten",
    "unflatten",
    "n_states",
    "circulation_index",
    "NEWTON_TOL",
    "simulate",
    "passive_volume",
    "zeta",
]

_ZS, _ZW = cell.STATE_NAMES.index("zeta_s"), cell.STATE_NAMES.index("zeta_w")
_NEWTON_MAX_IT = 20
_N_GLOBAL = 3  # V, P_c, P_at


@dataclasses.dataclass(frozen=True)
class ElementParams(model.ModelParams):
    """What the jitted core needs: V0 (ml) and the three parts per member ``(B,)`` (as
    :class:`lvenv.model.ModelParams`, whose ``get`` and ``replace`` it shares), per element
    ``(n, B)`` ``mu1`` (parallel: μ1_ξ; series: μ1_ξ / μ1, 1, so that the heart's μ1, which
    ``replace`` and :func:`lvenv.jacobian` reach, sets every element's), w_ξ and the calcium onset
    (s, relative to the LO delay), and the arrangement's ``kind`` (static)."""

    mu1: jax.Array
    w: jax.Array
    onset: jax.Array
    kind: str

    @property
    def n_elements(self) -> int:
        """The leading axis of the per-element arrays, n (static)."""
        return np.shape(self.mu1)[0]


jax.tree_util.register_dataclass(ElementParams, data_fields=["v0", "lo", "cell", "circ", "mu1", "w", "onset"], meta_fields=["kind"])


class State(NamedTuple):
    """Multi-element state, batch-last. ``cells`` (6, n, B) in ζ̃ form (ζ̃ = ζ − A λ: see
    :func:`zeta`); ``circ`` (3, B) = (V ml, P_c kPa, P_at kPa); algebraic ``v_el`` (n, B) element
    volumes (ml) and ``p_lv`` (B,) LV pressure (kPa)."""

    cells: jax.Array
    circ: jax.Array
    v_el: jax.Array
    p_lv: jax.Array


def element_params(heart: Heart, arrangement: Arrangement) -> ElementParams:
    """Host-side: a stacked, validated Heart batch and an arrangement → :class:`ElementParams`
    (the Heart's own ``elements`` play no part)."""
    mp = model.model_params(heart)
    n_members = np.shape(mp.v0)[0]
    values = arrangement.element_values()[:, None] * np.ones(n_members)
    if arrangement.kind == "parallel":
        mu1, w = values, np.ones_like(values)
    else:
        mu1, w = np.ones_like(values), values
    return ElementParams(v0=mp.v0, lo=mp.lo, cell=mp.cell, circ=mp.circ, mu1=mu1, w=w, onset=arrangement.member_onsets(n_members), kind=arrangement.kind)


def _element_mu1(p: ElementParams):
    """μ1_ξ, ``(n, B)``."""
    return p.mu1 if p.kind == "parallel" else p.mu1 * p.lo.mu1


def _element_lo(p: ElementParams) -> LOParams:
    return dataclasses.replace(p.lo, mu1=_element_mu1(p))


def _zeta_form(cells, lam, k: cell.Rates):
    """Cell state with ζ = ζ̃ + A λ (the form :mod:`lvenv.cell` takes)."""
    return jnp.asarray(cells).at[_ZS : _ZW + 1].add(k.a_eff * lam)


def zeta(state: State, p: ElementParams) -> jax.Array:
    """The cells of ``state`` with the distortions ζs, ζw (not ζ̃): shape (6, n, B)."""
    lam = coupling.stretch(state.v_el, p.v0, _element_lo(p))
    return _zeta_form(state.cells, lam, cell.rates(p.cell))


def initial_state(p: ElementParams) -> State:
    """Training-protocol initial state (DESIGN §1.2), host-side; its algebraic part is a guess.

    Every element at passive equilibrium with Pat — parallel: V at Ppass(V) = Pat; series: each
    V_ξ at w_ξ Ppass(V_ξ) = Pat and V = mean V_ξ —, P_c = Pc0, atrial state Pat, each cell at
    diastolic rest at its own stretch (ζ = 0). :func:`run` first solves the algebraic equations
    for (V_ξ, P) at these differential states (series: the resting tension, w_ξ μ2 Ta_rest(λ_ξ),
    shifts the V_ξ by up to ~0.1 ml from their passive equilibria; both: P = Pat + O(0.01 kPa),
    as in the single-element heart).
    """
    circ = p.circ
    if p.kind == "parallel":
        v_el = np.broadcast_to(coupling.passive_volume(circ.Pat, p.v0, p.lo), np.shape(p.mu1))
    else:
        v_el = coupling.passive_volume(np.asarray(circ.Pat) / np.asarray(p.w), p.v0, p.lo)
    v_el = np.asarray(v_el, float)
    lam = np.asarray(coupling.stretch(v_el, p.v0, _element_lo(p)))
    cells = np.array(cell.rest_state(lam, p.cell))
    cells[_ZS : _ZW + 1] -= np.asarray(cell.rates(p.cell).a_eff) * lam
    v = v_el.mean(axis=0)
    shape = v.shape
    glob = np.stack([v, np.broadcast_to(circ.Pc0, shape), np.broadcast_to(circ.Pat, shape)]).astype(float)
    return State(cells=cells, circ=glob, v_el=v_el, p_lv=np.broadcast_to(np.asarray(circ.Pat, float), shape).copy())


def _element_pressures(cells, v_el, p: ElementParams, k: cell.Rates):
    """(P_ξ, d_ξ = ∂P_ξ/∂V_ξ at fixed ζ̃, t_ξ = ∂P_ξ/∂cell_ξ as a 6-list, λ_ξ, cell in ζ form)."""
    lo_el = _element_lo(p)
    lam = coupling.stretch(v_el, p.v0, lo_el)
    y = _zeta_form(cells, lam, k)
    ta = cell.active_tension(y, lam, p.cell)
    dta_dy, dta_dlam = cell.active_tension_partials(y, lam, p.cell)
    dta_dlam = dta_dlam + k.a_eff * (dta_dy[_ZS] + dta_dy[_ZW])  # ζ = ζ̃ + A λ moves with λ
    gain = p.w * p.lo.mu2
    p_el = p.w * coupling.lv_pressure(ta, v_el, p.v0, p.lo)
    d = gain * dta_dlam * lo_el.mu1 / p.v0 + p.w * coupling.passive_pressure_slope(v_el, p.v0, p.lo)
    t = [0.0 if is_zero(x) else gain * x for x in dta_dy]
    return p_el, d, t, lam, y


def _algebraic(p: ElementParams, k: cell.Rates, cells, v, v_el, p_lv, tol):
    """(V_ξ, P, residual max_ξ abs(P_ξ − P) (B,), Newton iterations) at differential states (cells, V).

    Parallel: explicit. Series: Newton from the guess (``v_el``, ``p_lv``) until the residual is
    below ``tol`` (kPa) for every member, at most 20 iterations; a member stops at its first
    iterate below ``tol``, however many its neighbours need.
    """
    if p.kind == "parallel":
        v_el = jnp.broadcast_to(v, v_el.shape)
        p_el = _element_pressures(cells, v_el, p, k)[0]
        return v_el, jnp.mean(p_el, axis=0), jnp.zeros_like(v), jnp.zeros(v.shape, jnp.int32)

    def residual(c):
        return jnp.max(jnp.abs(c[2] - c[1]), axis=0)

    def cond(c):
        return (jnp.max(c[4]) < _NEWTON_MAX_IT) & jnp.any(residual(c) > tol)

    def body(c):
        v_el, p_lv, p_el, d, it = c
        active = residual(c) > tol  # a member that has converged stays put: its result does not depend on its neighbours
        r = p_el - p_lv
        r_m = jnp.mean(v_el, axis=0) - v
        m = jnp.mean(1.0 / d, axis=0)
        dp = (jnp.mean(r / d, axis=0) - r_m) / m
        v_new, p_new = v_el + (dp - r) / d, p_lv + dp
        p_el_new, d_new = _element_pressures(cells, v_new, p, k)[:2]
        keep = lambda new, old: jnp.where(active, new, old)
        return keep(v_new, v_el), keep(p_new, p_lv), keep(p_el_new, p_el), keep(d_new, d), it + active

    p_el, d = _element_pressures(cells, v_el, p, k)[:2]
    c = jax.lax.while_loop(cond, body, (v_el, p_lv, p_el, d, jnp.zeros(v.shape, jnp.int32)))
    return c[0], c[1], residual(c), c[4]


def _rhs(p: ElementParams, k: cell.Rates, ca, cells, glob, v_el, p_lv):
    """(d cells/dt in ζ̃ form (6, n, B), d(V, P_c, P_at)/dt (3, B)) at a consistent state."""
    lam = coupling.stretch(v_el, p.v0, _element_lo(p))
    d_cells = cell.derivatives(_zeta_form(cells, lam, k), ca, lam, 0.0, p.cell, k)
    q = circulation.flows(p_lv, glob[1], glob[2], p.circ)
    return d_cells, jnp.stack(circulation.windkessel_derivatives(q, p.circ))


class _Linearisation(NamedTuple):
    """The factorised ROS2 matrix I − γ h J of one step in arrow form (module docstring)."""

    lu: list  # LU of I − γh D_ξ, 6 × 6 entries of shape (n, B)
    v: jax.Array  # γh (I − γh D_ξ)⁻¹ e_ξ, (6, n, B)
    rho: list  # ρ_ξ, 6 entries (n, B) or structural zeros
    denom: jax.Array  # series: 1 − Σ ρ·v; parallel: 1
    a1: jax.Array  # p = a0 + a1 k_V
    c_p: list  # ∂(dV, dP_c, dP_at)/∂P, 3 entries (B,)
    g_lu: list  # LU of the 3 × 3 global matrix
    t: list  # ∂P_ξ/∂cell_ξ (series predictor)
    d: jax.Array  # ∂P_ξ/∂V_ξ (series predictor)


def _dot(rho: list, x) -> jax.Array:
    """Σ_ξ Σ_j ρ_j,ξ x_j,ξ per member."""
    return sum(jnp.sum(r * x[j], axis=0) for j, r in enumerate(rho) if not is_zero(r))


def _linearise(p: ElementParams, k: cell.Rates, ca, cells, glob, v_el, p_lv, f_cells, f_glob, h) -> _Linearisation:
    gh, kind = GAMMA * h, p.kind
    n = cells.shape[1]
    _, d, t, lam, y = _element_pressures(cells, v_el, p, k)
    j_cell, d_lam, _ = cell.jacobian(y, ca, lam, p.cell, k)
    dlam_dv = _element_mu1(p) / p.v0
    # ∂f/∂λ in ζ̃ form: the explicit λ-dependence plus ζ = ζ̃ + A λ
    shape = v_el.shape
    f_lam = [dl + k.a_eff * (j_cell[i][_ZS] + j_cell[i][_ZW]) for i, dl in enumerate(d_lam)]
    if kind == "parallel":
        e = [jnp.broadcast_to(f * dlam_dv, shape) for f in f_lam]
        jac = j_cell
        rho = [0.0 if is_zero(x) else x / n for x in t]
        rho_v = jnp.mean(d, axis=0)
    else:
        e = [jnp.broadcast_to(f * dlam_dv / d, shape) for f in f_lam]
        jac = [[a if is_zero(t[j]) else a - e[i] * t[j] for j, a in enumerate(row)] for i, row in enumerate(j_cell)]
        m = jnp.mean(1.0 / d, axis=0)
        rho = [0.0 if is_zero(x) else x / (n * m * d) for x in t]
        rho_v = 1.0 / m
    lu = lu_factor([[(1.0 if i == j else 0.0) - (0.0 if is_zero(a) else gh * a) for j, a in enumerate(row)] for i, row in enumerate(jac)])
    v = gh * jnp.stack(lu_solve(lu, e))
    sigma = _dot(rho, v)
    if kind == "parallel":
        denom, a1 = jnp.ones_like(sigma), rho_v + sigma
    else:
        denom = 1.0 - sigma
        a1 = rho_v / denom
    # valves: the fraction of the step each is open, from the state to its linear prediction y + h f (as lvenv.model.jacobian)
    p_c, p_at = glob[1], glob[2]
    ahead = h * (_dot(rho, f_cells) + rho_v * f_glob[0])
    mitral, aortic = circulation.open_fractions((p_lv, p_c, p_at), (p_lv + ahead, p_c + h * f_glob[1], p_at + h * f_glob[2]), p.circ)
    circ_jac = circulation.jacobian(mitral, aortic, p.circ)
    c_p = [row[0] for row in circ_jac]
    g = [[(1.0 if i == 0 else 0.0) - gh * c_p[i] * a1] + [(1.0 if i == j else 0.0) - gh * circ_jac[i][j] for j in (1, 2)] for i in range(_N_GLOBAL)]
    return _Linearisation(lu=lu, v=v, rho=rho, denom=denom, a1=a1, c_p=c_p, g_lu=lu_factor(g), t=t, d=d)


def _solve(kind: str, lin: _Linearisation, gh, r_cells, r_glob):
    """Solve (I − γh J) k = r: returns (k_cells (6, n, B), k_glob (3, B), p = δP of k (B,))."""
    u = jnp.stack(lu_solve(lin.lu, list(r_cells)))
    a0 = _dot(lin.rho, u) / lin.denom
    k_glob = lu_solve(lin.g_lu, [r_glob[i] + gh * lin.c_p[i] * a0 for i in range(_N_GLOBAL)])
    p_inc = a0 + lin.a1 * k_glob[0]
    s = k_glob[0] if kind == "parallel" else p_inc
    return u + s * lin.v, jnp.stack(k_glob), p_inc


def _predict(kind: str, lin: _Linearisation, v_el, p_lv, d_cells, d_glob, d_p):
    """Linear prediction of (V_ξ, P) after the state increment (d_cells, d_glob) with δP = d_p."""
    if kind == "parallel":
        return v_el + d_glob[0], p_lv + d_p
    tx = sum(t * d_cells[j] for j, t in enumerate(lin.t) if not is_zero(t))
    return v_el + (d_p - tx) / lin.d, p_lv + d_p


def _step(p: ElementParams, k, state: State, h, ca0, ca1, dca0, tol):
    """One ROS2 step (module docstring) → (state, max constraint residual (B,), Newton iterations)."""
    gh = GAMMA * h
    cells, glob, v_el, p_lv = state
    f_cells, f_glob = _rhs(p, k, ca0, cells, glob, v_el, p_lv)
    kind = p.kind  # of the arrow solve and the prediction
    lin = _linearise(p, k, ca0, cells, glob, v_el, p_lv, f_cells, f_glob, h)
    lam = coupling.stretch(v_el, p.v0, _element_lo(p))
    y = _zeta_form(cells, lam, k)
    forcing = gh * jax.jvp(lambda c: cell.derivatives(y, c, lam, 0.0, p.cell, k), (ca0,), (dca0,))[1]
    k1c, k1g, p1 = _solve(kind, lin, gh, f_cells + forcing, f_glob)
    cells1, glob1 = cells + h * k1c, glob + h * k1g
    v_el1, p_lv1 = _predict(kind, lin, v_el, p_lv, h * k1c, h * k1g, h * p1)
    v_el1, p_lv1, res1, it1 = _algebraic(p, k, cells1, glob1[0], v_el1, p_lv1, tol)
    f1_cells, f1_glob = _rhs(p, k, ca1, cells1, glob1, v_el1, p_lv1)
    k2c, k2g, p2 = _solve(kind, lin, gh, f1_cells - 2.0 * k1c - forcing, f1_glob - 2.0 * k1g)
    d_cells, d_glob, d_p = 1.5 * h * k1c + 0.5 * h * k2c, 1.5 * h * k1g + 0.5 * h * k2g, 1.5 * h * p1 + 0.5 * h * p2
    cells2, glob2 = cells + d_cells, glob + d_glob
    v_el2, p_lv2 = _predict(kind, lin, v_el, p_lv, d_cells, d_glob, d_p)
    v_el2, p_lv2, res2, it2 = _algebraic(p, k, cells2, glob2[0], v_el2, p_lv2, tol)
    return State(cells2, glob2, v_el2, p_lv2), jnp.maximum(res1, res2), it1 + it2


def _sample(p: ElementParams, state: State):
    """(V, P_lv, P_at, P_c, P_ao) as :func:`lvenv.events.update` takes them."""
    _, p_c, p_at_state = state.circ
    q = circulation.flows(state.p_lv, p_c, p_at_state, p.circ)
    return state.circ[0], state.p_lv, circulation.atrial_pressure(p_at_state, p.circ), p_c, circulation.aortic_pressure(p_c, q, p.circ)


def _stretch_range(p: ElementParams, state: State):
    """(min, max) over elements of λ_ξ, shape (2, B)."""
    lam = coupling.stretch(state.v_el, p.v0, _element_lo(p))
    return jnp.stack([jnp.min(lam, axis=0), jnp.max(lam, axis=0)])


def _beat(p: ElementParams, k: cell.Rates, carry: dict, steps: int, newton_tol, record: bool, volume_trace: bool = True):
    """One beat of ``steps`` ROS2 steps from ``carry`` (``state``, ``residual`` at its start,
    ``residual_max``, ``iterations``, ``stretch`` so far), calcium onset at its start.

    Returns ``(carry at the beat's end, metrics, valid, traces)``: the beat's metrics and whether
    the detector found its valve cycle (:mod:`lvenv.events`), and when ``record`` the samples
    V, P_lv, P_ao, P_c, P_at and the residual, each ``(steps + 1, B)``. Each step computes its
    own [Ca] per element (as :func:`lvenv.simulation.beat`), so a member's arithmetic does not
    depend on how the batch around it was compiled.
    """
    period = circulation.beat_period(p.circ)
    h = period / steps
    norm = cell.transient_norm(p.cell)
    lo_el = dataclasses.replace(p.lo, delay=jnp.maximum(p.lo.delay + p.onset, 0.0))  # each element's onset (n, B)

    def record_sample(state, res):
        v, p_lv, p_at, p_c, p_ao = _sample(p, state)
        return (v, p_lv, p_ao, p_c, p_at, res)

    def step(c, n):
        t0, t1 = n * h, (n + 1) * h
        ca0, ca1 = coupling.calcium(t0, lo_el, p.cell, norm), coupling.calcium(t1, lo_el, p.cell, norm)
        state, res, it = _step(p, k, c["state"], h, ca0, ca1, coupling.calcium_rate(t0, lo_el, p.cell, norm), newton_tol)
        acc = events.update(c["acc"], t1, *_sample(p, state))
        lam = _stretch_range(p, state)
        stretch = jnp.stack([jnp.minimum(c["stretch"][0], lam[0]), jnp.maximum(c["stretch"][1], lam[1])])
        new = {"state": state, "acc": acc, "residual": res, "residual_max": jnp.maximum(c["residual_max"], res), "iterations": c["iterations"] + it, "stretch": stretch}
        return new, (record_sample(state, res) if record else None)

    acc0 = events.start(jnp.zeros_like(h), *_sample(p, carry["state"]), period, volume_trace)
    out, samples = jax.lax.scan(step, dict(carry, acc=acc0), jnp.arange(steps, dtype=h.dtype))
    metrics, valid = events.finish(out.pop("acc"), period)
    traces = None
    if record:
        first = record_sample(carry["state"], carry["residual"])
        traces = tuple(jnp.concatenate([f[None], s]) for f, s in zip(first, samples))
    return out, metrics, valid, traces


def _start(p: ElementParams, k: cell.Rates, state0: State, newton_tol) -> dict:
    """:func:`_beat`'s carry at ``state0``, its algebraic part solved at its differential states."""
    v_el, p_lv, res0, it0 = _algebraic(p, k, state0.cells, state0.circ[0], state0.v_el, state0.p_lv, newton_tol)
    state = State(state0.cells, state0.circ, v_el, p_lv)
    return {"state": state, "residual": res0, "residual_max": res0, "iterations": it0, "stretch": _stretch_range(p, state)}


def run(p: ElementParams, state0: State, newton_tol, *, steps: int, beats: int, record: bool):
    """Pure batched core: ``beats`` beats of ``steps`` ROS2 steps from ``state0`` (members ``(B,)``).

    Returns a dict: ``state`` (final), ``metrics`` (last beat, masked to NaN unless usable),
    ``status`` (codes of :mod:`lvenv.status`; a member whose equal-pressure Newton did not
    reach ``newton_tol`` left the constraint manifold and is ``diverged``), ``residual`` (max
    over the run of max_ξ abs(P_ξ − P), kPa), ``newton_iterations`` (per member), ``stretch``
    ((min, max) of λ_ξ over elements and steps) and, when ``record``, ``traces``: V, P_lv,
    P_ao, P_c, P_at and the residual, each ``(beats, steps + 1, B)``.
    """
    k = cell.rates(p.cell)

    def one_beat(carry, _):
        out, metrics, valid, traces = _beat(p, k, carry, steps, newton_tol, record)
        return out, (metrics, valid, traces)

    carry, (metrics, valid, traces) = jax.lax.scan(one_beat, _start(p, k, state0, newton_tol), None, length=beats)
    state, res, its, stats = carry["state"], carry["residual_max"], carry["iterations"], carry["stretch"]
    metrics = {name: value[-1] for name, value in metrics.items()}
    finite = jnp.all(jnp.isfinite(state.circ), axis=0) & jnp.all(jnp.isfinite(state.cells), axis=(0, 1)) & jnp.isfinite(res)
    for value in metrics.values():
        finite &= jnp.isfinite(value)
    code = jnp.where(~finite, status.NONFINITE, jnp.where(res > newton_tol, status.DIVERGED, jnp.where(
        ~valid[-1], status.NO_VALVE_CYCLE, jnp.where(~status.is_physical(metrics), status.NON_PHYSICAL, status.OK))))
    out = {
        "state": state,
        "metrics": {name: jnp.where(status.is_usable(code), value, jnp.nan) for name, value in metrics.items()},
        "status": code,
        "residual": res,
        "newton_iterations": its,
        "stretch": stats,
    }
    if record:
        out["traces"] = traces
    return out


def n_states(n_elements: int) -> int:
    """Length of a multi-element heart's flat state (:func:`flatten`): 7 n + 4."""
    return (cell.N_STATES + 1) * n_elements + _N_GLOBAL + 1


def circulation_index(n_elements: int) -> tuple[int, int, int]:
    """Rows of V, P_c and P_at in the flat state of ``n_elements`` elements."""
    first = cell.N_STATES * n_elements
    return first, first + 1, first + 2


def flatten(state: State):
    """A :class:`State` as one array ``(7 n + 4, B)``: the cells in ζ̃ form (row c·n + ξ for cell
    state c of element ξ), then V, P_c, P_at (:func:`circulation_index`), the element volumes
    V_ξ and P_lv. With ``n = 1`` the first 9 rows are laid out as the single-cell heart's state
    (:mod:`lvenv.model`), with ζ̃ in place of ζ. The form that beat loops, the env and
    :func:`lvenv.simulate` carry."""
    cells, glob, v_el, p_lv = state
    xp = jnp if isinstance(cells, jax.Array) else np
    return xp.concatenate([xp.reshape(cells, (-1,) + cells.shape[2:]), glob, v_el, p_lv[None]])


def unflatten(y, n_elements: int) -> State:
    """The :class:`State` of a flat state ``y`` (:func:`flatten`) of ``n_elements`` elements."""
    n, c = n_elements, cell.N_STATES * n_elements
    return State(cells=y[:c].reshape((cell.N_STATES, n) + y.shape[1:]), circ=y[c : c + 3], v_el=y[c + 3 : c + 3 + n], p_lv=y[c + 3 + n])


#: Newton tolerance (kPa) on max_ξ abs(P_ξ − P) of :func:`beat`, the default of :func:`simulate`.
NEWTON_TOL = 1e-10


def beat(p: ElementParams, y0, steps: int, record: bool, volume_trace: bool = True):
    """One beat of B members from flat states ``y0`` (:func:`flatten`), calcium onset at t = 0:
    :func:`lvenv.simulation.beat` for a multi-element heart, through which every steady-state
    loop of :mod:`lvenv.simulation` (and so :func:`lvenv.simulate`, the env and
    :func:`lvenv.jacobian`) runs it.

    Returns ``(y_end, metrics, valid, traces, on_manifold)``: the first four as that function
    returns them (traces: V, P_lv, P_ao), and whether the equal-pressure Newton met
    :data:`NEWTON_TOL` at every step (where not, the member left the constraint manifold: the
    loops report it ``diverged``, as :func:`run` does).
    """
    k = cell.rates(p.cell)
    carry = _start(p, k, unflatten(y0, p.n_elements), NEWTON_TOL)
    out, metrics, valid, traces = _beat(p, k, carry, steps, NEWTON_TOL, record, volume_trace)
    return flatten(out["state"]), metrics, valid, None if traces is None else traces[:3], out["residual_max"] <= NEWTON_TOL


run_jit = jax.jit(run, static_argnames=("steps", "beats", "record"))


@dataclasses.dataclass(frozen=True)
class MultiElementResult:
    """Result of :func:`simulate`; for a batch every field has a leading batch axis.

    ``metrics``: last beat (internal units, :data:`lvenv.metrics.METRIC_NAMES`; NaN unless the
    status is usable). ``traces``: ``t`` (s, from the first beat's onset), ``V`` (ml), ``P_lv``,
    ``P_ao``, ``P_c``, ``P_at`` (kPa) and ``residual`` (max_ξ abs(P_ξ − P), kPa; 0 in parallel)
    over all beats, ``beats · steps_per_beat + 1`` samples. ``constraint_residual``: its maximum
    over the run. ``stretch``: (min, max) of λ_ξ over elements and steps. ``final``: the final :class:`State`
    (cells in ζ̃ form, member axis last).
    """

    arrangement: Arrangement
    metrics: dict[str, np.ndarray | float]
    traces: dict[str, np.ndarray] | None
    status: np.ndarray | str
    status_code: np.ndarray | int
    constraint_residual: np.ndarray | float
    newton_iterations: np.ndarray | int
    stretch: np.ndarray
    final: State


def simulate(
    params: Heart | Sequence[Heart],
    arrangement: Arrangement,
    *,
    beats: int = 1,
    steps_per_beat: int = 1000,
    traces: bool = True,
    newton_tol: float = NEWTON_TOL,
) -> MultiElementResult:
    """Simulate ``beats`` beats of the multi-element heart(s) from the training-protocol state.

    Args:
        params: a Heart, a sequence of Hearts or a stacked Heart batch (geometry, LO maps,
            cell and circulation per member); every member uses the same ``arrangement``.
        arrangement: :class:`Arrangement` (kind, number of elements, spread).
        beats: beats to run; the metrics are the last beat's.
        steps_per_beat: ROS2 steps per cardiac cycle (h = 60 / HR / steps_per_beat s).
        traces: record the traces of every beat.
        newton_tol: series only: Newton tolerance on max_ξ abs(P_ξ − P) (kPa).

    Raises:
        ValueError: a parameter or setting outside its allowed range (names field and value).
    """
    if not isinstance(arrangement, Arrangement):
        raise ValueError(f"arrangement = {arrangement!r} must be an lvenv.params.Arrangement")
    beats = integer("beats", beats, 1)
    steps_per_beat = integer("steps_per_beat", steps_per_beat, 10)
    newton_tol = real("newton_tol", newton_tol, 0.0, 1.0, lo_open=True)
    heart, single = as_batch(params)
    p = element_params(heart, arrangement)
    out = run_jit(p, initial_state(p), newton_tol, steps=steps_per_beat, beats=beats, record=bool(traces))
    out = jax.device_get(out)
    codes = np.asarray(out["status"])
    trace_dict = None
    if traces:
        period = 60.0 / np.asarray(p.circ.HR)
        t = period[:, None] * np.linspace(0.0, beats, beats * steps_per_beat + 1)[None, :]
        names = ("V", "P_lv", "P_ao", "P_c", "P_at", "residual")
        # (beats, steps + 1, B) → (B, beats · steps + 1): a beat's first sample is the last one's end
        joined = [np.concatenate([x[0]] + [x[b, 1:] for b in range(1, beats)]).T for x in out["traces"]]
        trace_dict = {"t": t, **dict(zip(names, joined))}
    result = MultiElementResult(
        arrangement=arrangement,
        metrics={name: np.asarray(out["metrics"][name]) for name in METRIC_NAMES},
        traces=trace_dict,
        status=status.names(codes),
        status_code=codes,
        constraint_residual=np.asarray(out["residual"]),
        newton_iterations=np.asarray(out["newton_iterations"]),
        stretch=np.asarray(out["stretch"]).T,
        final=State(*(np.asarray(x) for x in out["state"])),
    )
    return _member(result, 0) if single else result


def _member(r: MultiElementResult, i: int) -> MultiElementResult:
    return MultiElementResult(
        arrangement=r.arrangement,
        metrics={name: float(v[i]) for name, v in r.metrics.items()},
        traces=None if r.traces is None else {name: v[i] for name, v in r.traces.items()},
        status=str(r.status[i]),
        status_code=int(r.status_code[i]),
        constraint_residual=float(r.constraint_residual[i]),
        newton_iterations=int(r.newton_iterations[i]),
        stretch=r.stretch[i],
        final=State(*(x[..., i] for x in r.final)),
    )


def passive_volume(pressure, v0, lo: LOParams, arrangement: Arrangement) -> np.ndarray:
    """LV volume (ml) of the passive multi-element heart (Ta = 0) at cavity pressure ``pressure`` (kPa).

    Parallel: Ppass(V) = P (μ1_ξ plays no part). Series: V = mean_ξ V_ξ with w_ξ Ppass(V_ξ) = P.
    Host-side, vectorised over ``pressure``.
    """
    pressure = np.asarray(pressure, float)
    if arrangement.kind == "parallel":
        return coupling.passive_volume(pressure, v0, lo)
    w = arrangement.element_values().reshape((-1,) + (1,) * pressure.ndim)
    return np.mean(coupling.passive_volume(pressure / w, v0, lo), axis=0)
