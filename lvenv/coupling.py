"""LO coupling: the trained linear maps and the passive pressure–volume law (DESIGN §1).

::

    λ(V)    = μ1 (V/V0 − 1) + 1                   fibre stretch (1)
    dλ/dt   = μ1 / V0 · dV/dt                       (1/s)
    P_lv    = μ2 Ta + Ppass(V)                      (kPa)

    x = V/V0 − 1
    Ppass = α (1 − exp(−β γ x))      x ≤ 0          (compression; γ acts only here)
    Ppass = a x³ + b x² + c x        x > 0          (tension)

The LO cell's calcium input (ours, DESIGN §3): the 3-D wall activates over ~80 ms from four
endocardial foci while the paper's single cell starts at once. With the activation delay
d = ``lo.delay`` the cell's transient (:func:`lvenv.cell.calcium`) starts d after the beat's
onset::

    Ca_d(t) = Cdia for t < d,   Ca(t − d) for t ≥ d

d = 0 is the single cell of the paper. (A uniform spread of onsets over [0, s], averaging the
transients, was tried too: against our FE oracle it left C twice as large as the delay.)
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from lvenv import cell
from lvenv.params import CellParams, LOParams

__all__ = ["stretch", "stretch_rate", "passive_pressure", "passive_pressure_slope", "lv_pressure", "passive_volume", "calcium", "calcium_rate"]


def calcium(t, lo: LOParams, p: CellParams, norm=None):
    """LO calcium input (µM) at time ``t`` ≥ 0 since the beat's onset: the cell's transient delayed
    by ``lo.delay`` (s). ``norm``: :func:`lvenv.cell.transient_norm`, if already computed."""
    return jnp.where(t >= lo.delay, cell.calcium(jnp.maximum(t - lo.delay, 0.0), p, norm), p.Cdia)


def calcium_rate(t, lo: LOParams, p: CellParams, norm=None):
    """d/dt of :func:`calcium` (µM/s)."""
    return jnp.where(t >= lo.delay, cell.calcium_rate(jnp.maximum(t - lo.delay, 0.0), p, norm), 0.0)


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


def passive_pressure_slope(v, v0, lo: LOParams):
    """dPpass/dV (kPa/ml): α β γ exp(−β γ x) / V0 for x ≤ 0, (3a x² + 2b x + c) / V0 for x > 0."""
    x = v / v0 - 1.0
    compression = lo.alpha * lo.beta * lo.gamma * jnp.exp(-lo.beta * lo.gamma * jnp.minimum(x, 0.0))
    return jnp.where(x <= 0.0, compression, (3.0 * lo.a * x + 2.0 * lo.b) * x + lo.c) / v0


def lv_pressure(ta, v, v0, lo: LOParams):
    """P_lv = μ2 Ta + Ppass(V) (kPa)."""
    return lo.mu2 * ta + passive_pressure(v, v0, lo)


def passive_volume(p, v0, lo: LOParams) -> np.ndarray:
    """Volume (ml) at which Ppass(V) = p (kPa): the LV's passive equilibrium with pressure p.

    Host-side NumPy helper for initial states, vectorised over stacked batches. Ppass is monotone
    increasing, so the root is unique: closed form for p ≤ 0, safeguarded Newton on the cubic for p > 0,
    iterated per member until its own step is below round-off (so a member's volume is the same
    in any batch).
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
    done = np.zeros(p.shape, bool)
    for _ in range(100):  # safeguarded Newton: bisect whenever Newton leaves the bracket
        fx = cubic(x) - p
        lo_x, hi_x = np.where(fx < 0.0, x, lo_x), np.where(fx < 0.0, hi_x, x)
        newton = x - fx / ((3.0 * a * x + 2.0 * b) * x + c)
        x_new = np.where((newton > lo_x) & (newton < hi_x), newton, 0.5 * (lo_x + hi_x))
        # each member stops on its own test, so its root never depends on the other members
        x, done = np.where(done, x, x_new), done | (np.abs(x_new - x) <= 1e-15 * np.maximum(1.0, np.abs(x)))
        if np.all(done):
            break
    x = np.where(p > 0.0, x, np.where(p < 0.0, x_neg, 0.0))
    return v0 * (1.0 + x)
