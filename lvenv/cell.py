"""Cell unit: Land et al. 2017 human myofilament model (J Physiol 595:6167), DESIGN §1.1.

States ``(CaTRPN, B, S, W, ζs, ζw)``; inputs [Ca] (µM), fibre stretch λ and its rate dλ/dt (1/s).
With λc = min(λ, 1.2) and U = 1 − B − S − W::

    Ca50     = Ca50ref + β1 (λc − 1)
    dCaTRPN  = kTRPN [ (Ca/Ca50)^nTRPN (1 − CaTRPN) − CaTRPN ]
    kb       = ku TRPN50^nTm / (1 − rs − (1 − rs) rw)
    dB       = kb min(CaTRPN^(−nTm/2), 100) U − ku CaTRPN^(nTm/2) B
    kwu      = kuw (1/rw − 1) − kws ;   ksu = kws rw (1/rs − 1)
    γwu      = γw |ζw| ;   γsu = γs ζs (ζs > 0),  γs (−ζs − 1) (ζs < −1),  0 otherwise
    dW       = kuw U − (kwu + kws + γwu) W
    dS       = kws W − (ksu + γsu) S
    Aw = As  = Aeff rs / ((1 − rs) rw + rs)
    cw = φ kuw (1 − rw)/rw ;   cs = φ kws (1 − rs) rw / rs
    dζw      = Aw dλ/dt − cw ζw ;   dζs = As dλ/dt − cs ζs
    h(λ)     = max(0, 1 + β0 (λc + min(λc, 0.87) − 1.87))
    Ta       = Sa h(λ) (Tref/rs) [ S (ζs + 1) + W ζw ]            (kPa)

Paper parameters: Sa multiplies Tref; the Vmax factor multiplies kuw and kws; nA is nTm; n0 sets
β0 so that h(n0) = 0; τ1, τ2 shape the calcium transient

    Ca(t') = Cdia + (Cmax − Cdia) (exp(−t'/τ2) − exp(−t'/τ1)) / norm,   t' = t mod T,

with ``norm`` the peak of the bi-exponential so that max Ca = Cmax.

All functions are pure and elementwise: they vectorise over any number of cells by broadcasting
(the FE oracle calls them at every quadrature point). A cell state has the six states on its
*first* axis, shape ``(6, ...)``, so each state is a contiguous array over cells.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from lvenv.params import CellParams

__all__ = [
    "N_STATES",
    "STATE_NAMES",
    "beta0",
    "calcium",
    "calcium_rate",
    "ca50",
    "rates",
    "Rates",
    "derivatives",
    "active_tension",
    "active_tension_partials",
    "length_dependence",
    "length_dependence_slope",
    "jacobian",
    "rest_state",
    "steady_state_tension",
    "LAMBDA_CAP",
    "H_KNEE",
]

STATE_NAMES = ("CaTRPN", "B", "S", "W", "zeta_s", "zeta_w")
N_STATES = len(STATE_NAMES)
_CATRPN_POW_CAP = 100.0
_CATRPN_FLOOR = 1e-12

#: λc = min(λ, LAMBDA_CAP): Ca50 and h stop depending on stretch above it (Land 2017).
LAMBDA_CAP = 1.2
#: Knee of the length dependence h(λ) (Land 2017): its slope halves above it.
H_KNEE = 0.87
_H_SHIFT = 1.0 + H_KNEE


def beta0(n0):
    """β0 such that h(n0) = 0: 1/(1.87 − 2 n0) for n0 ≤ 0.87, else 1/(1 − n0)."""
    return jnp.where(n0 <= H_KNEE, 1.0 / (_H_SHIFT - 2.0 * n0), 1.0 / (1.0 - jnp.minimum(n0, 0.999)))


def transient_norm(p: CellParams):
    """Peak value of the unnormalised bi-exponential exp(−t/τ2) − exp(−t/τ1) (dimensionless)."""
    t_peak = p.tau1 * p.tau2 / (p.tau2 - p.tau1) * jnp.log(p.tau2 / p.tau1)
    return jnp.exp(-t_peak / p.tau2) - jnp.exp(-t_peak / p.tau1)


def calcium(t, p: CellParams, norm=None):
    """[Ca](t) in µM, ``t`` the time since the beat's onset (s), bi-exponential with peak Cmax.

    ``norm``: :func:`transient_norm` of ``p``, if already computed (hoisted out of step loops).
    """
    norm = transient_norm(p) if norm is None else norm
    shape = (jnp.exp(-t / p.tau2) - jnp.exp(-t / p.tau1)) / norm
    return p.Cdia + (p.Cmax - p.Cdia) * shape


def calcium_rate(t, p: CellParams, norm=None):
    """d[Ca]/dt (µM/s) of :func:`calcium`."""
    norm = transient_norm(p) if norm is None else norm
    return (p.Cmax - p.Cdia) * (jnp.exp(-t / p.tau1) / p.tau1 - jnp.exp(-t / p.tau2) / p.tau2) / norm


def ca50(lam, p: CellParams):
    """Ca50 (µM) at stretch λ: Ca50ref + β1 (min(λ, 1.2) − 1)."""
    return p.Ca50ref + p.beta1 * (jnp.minimum(lam, LAMBDA_CAP) - 1.0)


class Rates(NamedTuple):
    """Derived rate constants (1/s) and distortion gain of the cell model."""

    kuw: jax.Array
    kws: jax.Array
    kwu: jax.Array
    ksu: jax.Array
    kb: jax.Array
    a_eff: jax.Array
    cw: jax.Array
    cs: jax.Array


def rates(p: CellParams) -> Rates:
    """Rate constants of :func:`derivatives`; compute once per member, outside time loops."""
    kuw = p.kuw * p.vmax_factor
    kws = p.kws * p.vmax_factor
    return Rates(
        kuw=kuw,
        kws=kws,
        kwu=kuw * (1.0 / p.rw - 1.0) - kws,
        ksu=kws * p.rw * (1.0 / p.rs - 1.0),
        kb=p.ku * p.TRPN50**p.nA / (1.0 - p.rs - (1.0 - p.rs) * p.rw),
        a_eff=p.Aeff * p.rs / ((1.0 - p.rs) * p.rw + p.rs),
        cw=p.phi * kuw * (1.0 - p.rw) / p.rw,
        cs=p.phi * kws * (1.0 - p.rs) * p.rw / p.rs,
    )


def derivatives(y, ca, lam, dlam, p: CellParams, k: Rates | None = None):
    """d/dt of the cell state ``y`` (first axis: the six states), 1/s.

    ``k``: precomputed :func:`rates` (computed here when omitted).
    """
    catrpn, b, s, w, zs, zw = (y[i] for i in range(N_STATES))
    kuw, kws, kwu, ksu, kb, a_eff, cw, cs = rates(p) if k is None else k
    u = 1.0 - b - s - w
    catrpn_pow = jnp.exp(0.5 * p.nA * jnp.log(jnp.maximum(catrpn, _CATRPN_FLOOR)))
    d_catrpn = p.kTRPN * ((ca / ca50(lam, p)) ** p.nTRPN * (1.0 - catrpn) - catrpn)
    d_b = kb * jnp.minimum(1.0 / catrpn_pow, _CATRPN_POW_CAP) * u - p.ku * catrpn_pow * b
    gamma_wu = p.gamma_w * jnp.abs(zw)
    gamma_su = p.gamma_s * jnp.where(zs > 0.0, zs, jnp.where(zs < -1.0, -zs - 1.0, 0.0))
    d_w = kuw * u - (kwu + kws + gamma_wu) * w
    d_s = kws * w - (ksu + gamma_su) * s
    d_zw = a_eff * dlam - cw * zw
    d_zs = a_eff * dlam - cs * zs
    return jnp.stack([d_catrpn, d_b, d_s, d_w, d_zs, d_zw])


def length_dependence(lam, b0, minimum=jnp.minimum, maximum=jnp.maximum):
    """h(λ) = max(0, 1 + β0 (λc + min(λc, 0.87) − 1.87)), λc = min(λ, 1.2) (Land 2017).

    ``minimum`` / ``maximum`` let the FE oracle evaluate this same formula in UFL.
    """
    lam_c = minimum(lam, LAMBDA_CAP)
    return maximum(0.0, 1.0 + b0 * (lam_c + minimum(lam_c, H_KNEE) - _H_SHIFT))


def length_dependence_slope(lam, b0):
    """dh/dλ, one-sided at the kinks (the branch the state selects, as forward-mode AD does)."""
    lam_c = jnp.minimum(lam, LAMBDA_CAP)
    h_raw = 1.0 + b0 * (lam_c + jnp.minimum(lam_c, H_KNEE) - _H_SHIFT)
    return jnp.where((h_raw > 0.0) & (lam < LAMBDA_CAP), b0 * jnp.where(lam_c < H_KNEE, 2.0, 1.0), 0.0)


def active_tension(y, lam, p: CellParams):
    """Ta (kPa) = Sa h(λ) (Tref/rs) [S (ζs + 1) + W ζw]."""
    s, w, zs, zw = y[2], y[3], y[4], y[5]
    return p.Sa * length_dependence(lam, beta0(p.n0)) * (p.Tref / p.rs) * (s * (zs + 1.0) + w * zw)


def active_tension_partials(y, lam, p: CellParams) -> tuple[list, jax.Array]:
    """(∂Ta/∂y as a list over the six states, ∂Ta/∂λ) in kPa per unit; CaTRPN and B are the
    structural zeros ``0.0``."""
    s, w, zs, zw = y[2], y[3], y[4], y[5]
    b0 = beta0(p.n0)
    scale = p.Sa * p.Tref / p.rs
    kh = scale * length_dependence(lam, b0)
    return [0.0, 0.0, kh * (zs + 1.0), kh * zw, kh * s, kh * w], scale * (s * (zs + 1.0) + w * zw) * length_dependence_slope(lam, b0)


def jacobian(y, ca, lam, p: CellParams, k: Rates) -> tuple[list[list], list, list]:
    """Partials of :func:`derivatives` at fixed inputs: (∂f/∂y as 6 × 6 rows, ∂f/∂λ, ∂f/∂(dλ/dt)).

    Structural zeros are the Python float ``0.0`` (the ROS2 LU skips them). At the clamps and
    abs(ζw) the one-sided derivative of the branch the state selects is used, as ``jax.jacfwd`` does.
    """
    c, b, s, w, zs, zw = (y[i] for i in range(N_STATES))
    zero = [0.0] * N_STATES
    c50 = ca50(lam, p)
    ratio_n = (ca / c50) ** p.nTRPN
    row_c = zero[:]
    row_c[0] = -p.kTRPN * (ratio_n + 1.0)
    d_c_dlam = p.kTRPN * (1.0 - c) * ratio_n * (-p.nTRPN / c50) * jnp.where(lam < LAMBDA_CAP, p.beta1, 0.0)
    half = 0.5 * p.nA
    c_pos = jnp.maximum(c, _CATRPN_FLOOR)
    c_pow = jnp.exp(half * jnp.log(c_pos))
    inv_pow = 1.0 / c_pow
    unblock = k.kb * jnp.minimum(inv_pow, _CATRPN_POW_CAP)
    u = 1.0 - b - s - w
    row_b = zero[:]
    row_b[0] = jnp.where(c > _CATRPN_FLOOR, jnp.where(inv_pow >= _CATRPN_POW_CAP, 0.0, -half * k.kb * inv_pow / c_pos * u) - half * p.ku * c_pow / c_pos * b, 0.0)
    row_b[1] = -unblock - p.ku * c_pow
    row_b[2] = -unblock
    row_b[3] = -unblock
    row_s = zero[:]
    row_s[2] = -(k.ksu + p.gamma_s * jnp.where(zs > 0.0, zs, jnp.where(zs < -1.0, -zs - 1.0, 0.0)))
    row_s[3] = k.kws
    row_s[4] = -p.gamma_s * jnp.where(zs > 0.0, 1.0, jnp.where(zs < -1.0, -1.0, 0.0)) * s
    row_w = zero[:]
    row_w[1] = -k.kuw
    row_w[2] = -k.kuw
    row_w[3] = -k.kuw - (k.kwu + k.kws + p.gamma_w * jnp.abs(zw))
    row_w[5] = -p.gamma_w * jnp.sign(zw) * w
    row_zs = zero[:]
    row_zs[4] = -k.cs
    row_zw = zero[:]
    row_zw[5] = -k.cw
    d_dlam = [d_c_dlam, 0.0, 0.0, 0.0, 0.0, 0.0]
    d_dlam_rate = [0.0, 0.0, 0.0, 0.0, k.a_eff, k.a_eff]
    return [row_c, row_b, row_s, row_w, row_zs, row_zw], d_dlam, d_dlam_rate


def _bound_fractions(catrpn, p: CellParams):
    """Steady-state (B, S, W) at fixed CaTRPN, isometric (ζ = 0)."""
    kuw, kws, kwu, ksu, kb, *_ = rates(p)
    catrpn_pos = jnp.maximum(catrpn, _CATRPN_FLOOR)
    half = 0.5 * p.nA
    b_per_u = kb * jnp.minimum(catrpn_pos ** (-half), _CATRPN_POW_CAP) / (p.ku * catrpn_pos**half)
    w_per_u = kuw / (kwu + kws)
    s_per_u = kws / ksu * w_per_u
    u = 1.0 / (1.0 + b_per_u + w_per_u + s_per_u)
    return b_per_u * u, s_per_u * u, w_per_u * u


def rest_state(lam, p: CellParams):
    """Isometric steady state at diastolic [Ca] = Cdia and stretch λ: shape ``(6, ...)``."""
    x = (p.Cdia / ca50(lam, p)) ** p.nTRPN
    catrpn = x / (1.0 + x)
    b, s, w = _bound_fractions(catrpn, p)
    zero = jnp.zeros_like(catrpn)
    return jnp.stack([catrpn, b, s, w, zero, zero])


def steady_state_tension(ca, lam, p: CellParams):
    """Isometric steady-state Ta (kPa) at constant [Ca] and λ (force–calcium relation)."""
    x = (ca / ca50(lam, p)) ** p.nTRPN
    catrpn = x / (1.0 + x)
    _, s, _ = _bound_fractions(catrpn, p)
    return p.Sa * length_dependence(lam, beta0(p.n0)) * (p.Tref / p.rs) * s
