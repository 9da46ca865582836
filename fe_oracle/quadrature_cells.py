"""The Land 2017 cell at every quadrature point, re-using :mod:`lvenv.cell` (DESIGN §1.1, §4).

Pure JAX, vectorised over points (state array shape ``(6, N)``, first axis ``lvenv.cell.STATE_NAMES``).

Each point's calcium transient starts at its activation time t_act (:mod:`fe_oracle.activation`)
and repeats with the beat period T::

    Ca(t) = Cdia                                 for t < t_act
          = lvenv.cell.calcium((t − t_act) mod T) otherwise

Over a mechanics step t → t + dt the stretch is taken linear in time (λ₀ → λ₁, rate
(λ₁ − λ₀)/dt) and the cell ODE ``lvenv.cell.derivatives`` is integrated with ``n_sub``
linearly implicit (Rosenbrock–Euler) sub-steps, (I − h ∂f/∂y) Δy = h f(y), the 6 × 6 Jacobian
taken by ``jax.jacfwd`` of ``lvenv.cell.derivatives`` at every point and the 6 × 6 systems
solved together, one vectorised sweep over the points per matrix entry (:func:`solve_unpivoted`). Explicit sub-steps were
unstable at hot spots of fast shortening, where γw|ζw| exceeds 10³/s. The distortions ζs, ζw obey the linear ODE dζ/dt = A dλ/dt − c ζ, whose exact
solution for a constant rate is then written back::

    ζ₁ = ζ₀ e^(−c dt) + A (λ₁ − λ₀) (1 − e^(−c dt)) / (c dt)

so that the mechanics (:class:`fe_oracle.mechanics.ActiveTension`, which uses the same formula
implicitly in λ₁) and the stored cell state agree exactly. A and c are read off
``lvenv.cell.derivatives`` itself (:func:`zeta_coefficients`), not re-derived.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import lvenv  # noqa: F401  (float64)
from lvenv import cell
from lvenv.params import CellParams

__all__ = ["tension_coefficients", "zeta_coefficients", "local_calcium", "advance", "rest_states", "solve_unpivoted", "tension"]

_ZS = cell.STATE_NAMES.index("zeta_s")
_ZW = cell.STATE_NAMES.index("zeta_w")


def zeta_coefficients(p: CellParams) -> tuple[float, float, float]:
    """(A, cs, cw) of dζs/dt = A dλ/dt − cs ζs, dζw/dt = A dλ/dt − cw ζw, from ``lvenv.cell``."""
    y = np.asarray(cell.rest_state(1.0, p))
    rate = np.asarray(cell.derivatives(y, p.Cdia, 1.0, 1.0, p))
    y_unit = y.copy()
    y_unit[_ZS] = y_unit[_ZW] = 1.0
    decay = np.asarray(cell.derivatives(y_unit, p.Cdia, 1.0, 0.0, p))
    a = float(rate[_ZS])
    if not np.isclose(a, rate[_ZW]):
        raise ValueError("lvenv.cell gives different stretch-rate gains for ζs and ζw")
    return a, float(-decay[_ZS]), float(-decay[_ZW])


def tension_coefficients(p: CellParams) -> dict[str, float]:
    """Constants of the UFL active tension: A, cs, cw, β0 and scale = Sa Tref / rs (kPa)."""
    a, cs, cw = zeta_coefficients(p)
    return {"A": a, "cs": cs, "cw": cw, "beta0": float(cell.beta0(p.n0)), "scale": float(p.Sa * p.Tref / p.rs)}


def local_calcium(t, t_act, period, p: CellParams):
    """[Ca] (µM) at time ``t`` (s) of points activated at ``t_act`` (s)."""
    since = t - t_act
    return jnp.where(since < 0.0, p.Cdia, cell.calcium(jnp.mod(since, period), p))


def rest_states(lam, p: CellParams) -> np.ndarray:
    """Diastolic rest state at stretches ``lam`` (N,): shape (6, N)."""
    return np.asarray(cell.rest_state(jnp.asarray(lam), p))


def solve_unpivoted(a, b):
    """x with a x = b for a batch of small systems; a: (n, n, N), b: (n, N) (point axis last).

    Gaussian elimination without pivoting, unrolled over the n × n entries so that each
    operation is one vectorised sweep over the N points (a batched ``jnp.linalg.solve`` with
    partial pivoting on (N, n, n) costs ~10 times more on a CPU). Stable for the matrices of
    :func:`advance`, I − h ∂f/∂y: their diagonal, 1 + h × (each state's own decay rate), is
    ≥ 1 and dominates the couplings of the Land kinetics.
    """
    n = len(b)
    a = [[a[i, j] for j in range(n)] for i in range(n)]
    b = [b[i] for i in range(n)]
    for k in range(n):
        for i in range(k + 1, n):
            factor = a[i][k] / a[k][k]
            for j in range(k + 1, n):
                a[i][j] = a[i][j] - factor * a[k][j]
            b[i] = b[i] - factor * b[k]
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (b[i] - sum(a[i][j] * x[j] for j in range(i + 1, n))) / a[i][i]
    return jnp.stack(x)


@functools.partial(jax.jit, static_argnames="n_sub")
def advance(y, lam0, lam1, t0, dt, t_act, period, p: CellParams, n_sub: int = 5):
    """Cell states after one mechanics step (module docstring); all point arrays shape (N,)."""
    rate = (lam1 - lam0) / dt
    h = dt / n_sub

    def f_point(y_pt, ca, lam, dlam):
        return cell.derivatives(y_pt, ca, lam, dlam, p)

    rhs = jax.vmap(f_point, in_axes=(1, 0, 0, 0), out_axes=1)
    jac = jax.vmap(jax.jacfwd(f_point), in_axes=(1, 0, 0, 0), out_axes=2)
    eye = jnp.eye(cell.N_STATES)[..., None]

    def body(i, y_s):
        s = (i + 1) * h
        lam = lam0 + (s / dt) * (lam1 - lam0)
        ca = local_calcium(t0 + s, t_act, period, p)
        return y_s + solve_unpivoted(eye - h * jac(y_s, ca, lam, rate), h * rhs(y_s, ca, lam, rate))

    y1 = jax.lax.fori_loop(0, n_sub, body, y)
    a, cs, cw = _zeta_consts(p)
    dlam = lam1 - lam0
    zs = y[_ZS] * jnp.exp(-cs * dt) + a * dlam * (1.0 - jnp.exp(-cs * dt)) / (cs * dt)
    zw = y[_ZW] * jnp.exp(-cw * dt) + a * dlam * (1.0 - jnp.exp(-cw * dt)) / (cw * dt)
    return y1.at[_ZS].set(zs).at[_ZW].set(zw)


def _zeta_consts(p: CellParams):
    """(A, cs, cw) traced through ``lvenv.cell.derivatives`` (jit-compatible)."""
    y = cell.rest_state(1.0, p)
    rate = cell.derivatives(y, p.Cdia, 1.0, 1.0, p)
    decay = cell.derivatives(y.at[_ZS].set(1.0).at[_ZW].set(1.0), p.Cdia, 1.0, 0.0, p)
    return rate[_ZS], -decay[_ZS], -decay[_ZW]


def tension(y, lam, p: CellParams) -> np.ndarray:
    """Ta (kPa) at each point: ``lvenv.cell.active_tension``."""
    return np.asarray(cell.active_tension(jnp.asarray(y), jnp.asarray(lam), p))
