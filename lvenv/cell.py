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
    "rest_state",
    "steady_state_tension",
]

STATE_NAMES = ("CaTRPN", "B", "S", "W", "zeta_s", "zeta_w")
N_STATES = len(STATE_NAMES)
_CATRPN_POW_CAP = 100.0


def beta0(n0):
    """β0 such that h(n0) = 0: 1/(1.87 − 2 n0) for n0 ≤ 0.87, else 1/(1 − n0)."""
    return jnp.where(n0 <= 0.87, 1.0 / (1.87 - 2.0 * n0), 1.0 / (1.0 - jnp.minimum(n0, 0.999)))


def calcium(t, p: CellParams):
    """[Ca](t) in µM, ``t`` the time since the beat's onset (s), bi-exponential with peak Cmax."""
    t_peak = p.tau1 * p.tau2 / (p.tau2 - p.tau1) * jnp.log(p.tau2 / p.tau1)
    norm = jnp.exp(-t_peak / p.tau2) - jnp.exp(-t_peak / p.tau1)
    shape = (jnp.exp(-t / p.tau2) - jnp.exp(-t / p.tau1)) / norm
    return p.Cdia + (p.Cmax - p.Cdia) * shape


def calcium_rate(t, p: CellParams):
    """d[Ca]/dt (µM/s) of :func:`calcium`."""
    t_peak = p.tau1 * p.tau2 / (p.tau2 - p.tau1) * jnp.log(p.tau2 / p.tau1)
    norm = jnp.exp(-t_peak / p.tau2) - jnp.exp(-t_peak / p.tau1)
    return (p.Cmax - p.Cdia) * (jnp.exp(-t / p.tau1) / p.tau1 - jnp.exp(-t / p.tau2) / p.tau2) / norm


def ca50(lam, p: CellParams):
    """Ca50 (µM) at stretch λ: Ca50ref + β1 (min(λ, 1.2) − 1)."""
    return p.Ca50ref + p.beta1 * (jnp.minimum(lam, 1.2) - 1.0)


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
    catrpn_pow = jnp.exp(0.5 * p.nA * jnp.log(jnp.maximum(catrpn, 1e-12)))
    d_catrpn = p.kTRPN * ((ca / ca50(lam, p)) ** p.nTRPN * (1.0 - catrpn) - catrpn)
    d_b = kb * jnp.minimum(1.0 / catrpn_pow, _CATRPN_POW_CAP) * u - p.ku * catrpn_pow * b
    gamma_wu = p.gamma_w * jnp.abs(zw)
    gamma_su = p.gamma_s * jnp.where(zs > 0.0, zs, jnp.where(zs < -1.0, -zs - 1.0, 0.0))
    d_w = kuw * u - (kwu + kws + gamma_wu) * w
    d_s = kws * w - (ksu + gamma_su) * s
    d_zw = a_eff * dlam - cw * zw
    d_zs = a_eff * dlam - cs * zs
    return jnp.stack([d_catrpn, d_b, d_s, d_w, d_zs, d_zw])


def _length_dependence(lam, p: CellParams):
    lam_c = jnp.minimum(lam, 1.2)
    return jnp.maximum(0.0, 1.0 + beta0(p.n0) * (lam_c + jnp.minimum(lam_c, 0.87) - 1.87))


def active_tension(y, lam, p: CellParams):
    """Ta (kPa) = Sa h(λ) (Tref/rs) [S (ζs + 1) + W ζw]."""
    s, w, zs, zw = y[2], y[3], y[4], y[5]
    return p.Sa * _length_dependence(lam, p) * (p.Tref / p.rs) * (s * (zs + 1.0) + w * zw)


def _bound_fractions(catrpn, p: CellParams):
    """Steady-state (B, S, W) at fixed CaTRPN, isometric (ζ = 0)."""
    kuw, kws, kwu, ksu, kb, *_ = rates(p)
    catrpn_pos = jnp.maximum(catrpn, 1e-12)
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
    return p.Sa * _length_dependence(lam, p) * (p.Tref / p.rs) * s
