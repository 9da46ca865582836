"""LO coupling: the trained linear maps and the passive pressure–volume law (DESIGN §1).

::

    λ(V)    = μ1 (V/V0 − 1) + 1                   fibre stretch (1)
    dλ/dt   = μ1 / V0 · dV/dt                       (1/s)
    P_lv    = μ2 Ta + Ppass(V)                      (kPa)

    x = V/V0 − 1
    Ppass = α (1 − exp(−β γ x))      x ≤ 0          (compression; γ acts only here)
    Ppass = a x³ + b x² + c x        x > 0          (tension)
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from lvenv.params import LOParams

__all__ = ["stretch", "stretch_rate", "passive_pressure", "lv_pressure", "passive_volume"]


def stretch(v, v0, lo: LOParams):
    """Fibre stretch λ = μ1 (V/V0 − 1) + 1."""
    return lo.mu1 * (v / v0 - 1.0) + 1.0


def stretch_rate(dv, v0, lo: LOParams):
    """dλ/dt = μ1/V0 · dV/dt (1/s), ``dv`` in ml/s."""
    return lo.mu1 / v0 * dv


def passive_pressure(v, v0, lo: LOParams):
    """Ppass(V) in kPa (module docstring)."""
    x = v / v0 - 1.0
    compression = lo.alpha * (1.0 - jnp.exp(-lo.beta * lo.gamma * jnp.minimum(x, 0.0)))
    xp = jnp.maximum(x, 0.0)
    tension = ((lo.a * xp + lo.b) * xp + lo.c) * xp
    return jnp.where(x <= 0.0, compression, tension)


def lv_pressure(ta, v, v0, lo: LOParams):
    """P_lv = μ2 Ta + Ppass(V) (kPa)."""
    return lo.mu2 * ta + passive_pressure(v, v0, lo)


def passive_volume(p, v0, lo: LOParams) -> np.ndarray:
    """Volume (ml) at which Ppass(V) = p (kPa): the LV's passive equilibrium with pressure p.

    Host-side NumPy helper for initial states, vectorised over stacked batches. Ppass is monotone
    increasing, so the root is unique: closed form for p ≤ 0, safeguarded Newton on the cubic for p > 0.
    """
    p, v0 = np.broadcast_arrays(np.asarray(p, float), np.asarray(v0, float))
    a, b, c, alpha, beta, gamma = (np.broadcast_to(np.asarray(getattr(lo, k), float), p.shape) for k in ("a", "b", "c", "alpha", "beta", "gamma"))
    with np.errstate(divide="ignore", invalid="ignore"):
        x_neg = -np.log1p(-np.minimum(p, 0.0) / alpha) / (beta * gamma)
    cubic = lambda x: ((a * x + b) * x + c) * x
    lo_x, hi_x = np.zeros(p.shape), np.ones(p.shape)
    while np.any(grow := cubic(hi_x) < p):
        hi_x = np.where(grow, 2.0 * hi_x, hi_x)
    x = 0.5 * (lo_x + hi_x)
    for _ in range(60):  # safeguarded Newton: bisect whenever Newton leaves the bracket
        fx = cubic(x) - p
        lo_x, hi_x = np.where(fx < 0.0, x, lo_x), np.where(fx < 0.0, hi_x, x)
        newton = x - fx / ((3.0 * a * x + 2.0 * b) * x + c)
        x_new = np.where((newton > lo_x) & (newton < hi_x), newton, 0.5 * (lo_x + hi_x))
        if np.all(np.abs(x_new - x) <= 1e-15 * np.maximum(1.0, np.abs(x))):
            x = x_new
            break
        x = x_new
    x = np.where(p > 0.0, x, np.where(p < 0.0, x_neg, 0.0))
    return v0 * (1.0 + x)
