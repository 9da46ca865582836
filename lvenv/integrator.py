"""ROS2: a two-stage, second-order, L-stable Rosenbrock method with an exact Jacobian.

Verwer, Spee, Blom & Hundsdorfer (1999), SIAM J Sci Comput 20:1456, with γ = 1 + 1/√2::

    (I − γ h J) k1 = f(t_n, y_n)                + γ h f_t
    (I − γ h J) k2 = f(t_n + h, y_n + h k1) − 2 k1 − γ h f_t
    y_{n+1}        = y_n + 3/2 h k1 + 1/2 h k2

with J = ∂f/∂y and f_t = ∂f/∂t at (t_n, y_n). The f_t terms follow from writing the method in
Hairer & Wanner's form (b = (1/2, 1/2), α21 = 1, γ21 = −2γ, γ22 = γ, so γ_1 = γ, γ_2 = −γ);
without them the method loses an order on stiff, time-forced problems.

It is linearly implicit: one Jacobian (forward-mode AD), one LU factorisation and two
triangular solves per step, no Newton iteration. Order 2 holds for any matrix in place of J
(a W-method), L-stability needs the exact one. Linear invariants with wᵀf ≡ 0 (the closed-loop
blood volume) are conserved to round-off because wᵀJ = 0.

States are laid out batch-last, ``y.shape == (n, *batch)``: every state, every Jacobian entry
and every LU entry is a contiguous array over the batch, so each scalar operation of the step is
one vectorised loop over members. The Jacobian is analytic where the model supplies one (the LO
heart does, with its sparsity), else ``n`` forward-mode JVPs with the unit tangent of one state
for all members at once (members are independent). The LU is written out
for the small fixed n without pivoting: I − γhJ of this model has a dominant positive diagonal
(every state decays or is dissipatively coupled).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

__all__ = ["GAMMA", "ORDER", "ros2_step", "ad_jacobian", "is_zero", "lu_factor", "lu_solve"]

GAMMA = 1.0 + 1.0 / 2.0**0.5
ORDER = 2


def is_zero(x) -> bool:
    """A structural zero: the Python literal 0.0 (arrays are never treated as zero)."""
    return isinstance(x, float) and x == 0.0


def lu_factor(a: list[list]) -> list[list]:
    """Doolittle LU (unit lower) on a list of lists of arrays, skipping structural zeros."""
    n = len(a)
    a = [row[:] for row in a]
    for k in range(n):
        inv_pivot = 1.0 / a[k][k]
        for i in range(k + 1, n):
            if is_zero(a[i][k]):
                continue
            a[i][k] = a[i][k] * inv_pivot
            for j in range(k + 1, n):
                if not is_zero(a[k][j]):
                    a[i][j] = a[i][j] - a[i][k] * a[k][j]
    return a


def lu_solve(lu: list[list], b: list) -> list:
    """Solve with the factors of :func:`lu_factor` (forward then back substitution)."""
    n = len(b)
    y = b[:]
    for i in range(n):
        for j in range(i):
            if not is_zero(lu[i][j]):
                y[i] = y[i] - lu[i][j] * y[j]
    for i in reversed(range(n)):
        for j in range(i + 1, n):
            if not is_zero(lu[i][j]):
                y[i] = y[i] - lu[i][j] * y[j]
        y[i] = y[i] / lu[i][i]
    return y


def ad_jacobian(f: Callable, u, y: jax.Array) -> tuple[jax.Array, list[list]]:
    """``(f(u, y), ∂f/∂y)`` by n forward-mode JVPs, one unit tangent per state for all members."""
    n = y.shape[0]
    f0, jvp = jax.linearize(lambda yy: f(u, yy), y)
    unit = jnp.broadcast_to(jnp.eye(n, dtype=y.dtype).reshape((n, n) + (1,) * (y.ndim - 1)), (n,) + y.shape)
    columns = jax.vmap(jvp)(unit)  # columns[j, i] = ∂f_i/∂y_j
    return f0, [[columns[j, i] for j in range(n)] for i in range(n)]


def ros2_step(f: Callable, y: jax.Array, h: jax.Array, u0, u1, du0=None, jacobian: Callable | None = None, error: bool = False):
    """One ROS2 step of ``dy/dt = f(u(t), y)``, ``y`` of shape ``(n, *batch)``, ``h`` per member.

    ``u0`` and ``u1`` are the exogenous input (for the LO heart, [Ca]) at the start and the end
    of the step, ``du0`` its time derivative at the start (so f_t = ∂f/∂u · du0, by one JVP);
    for a plain non-autonomous f(t, y) pass ``u0 = t_n``, ``u1 = t_n + h``, ``du0 = 1``.
    ``du0=None`` drops the f_t terms. ``jacobian(u, y)``: analytic ∂f/∂y as a list of lists
    whose structural zeros are the Python float 0.0 (skipped by the LU); it also receives the
    explicit predictor increment h·f(u0, y) as ``lookahead`` (any matrix keeps order 2).
    Default: forward-mode AD (:func:`ad_jacobian`).

    ``error=True`` returns ``(y_{n+1}, e)`` with the embedded local error estimate
    e = y_{n+1} − (y_n + h k1) = h/2 (k1 + k2): the difference to the first-order solution
    y_n + h k1 (linearly implicit Euler), O(h²), what step-size control (:mod:`lvenv.simulation`) uses.
    """
    n = y.shape[0]
    if jacobian is None:
        f0, jac = ad_jacobian(f, u0, y)
    else:
        f0 = f(u0, y)
        jac = jacobian(u0, y, h * f0)
    gh = GAMMA * h
    if du0 is None:
        forcing = jnp.zeros_like(y)
    else:
        forcing = gh * jax.jvp(lambda uu: f(uu, y), (u0,), (du0,))[1]
    m = [[(1.0 if i == j else 0.0) - (gh * jac[i][j] if not is_zero(jac[i][j]) else 0.0) for j in range(n)] for i in range(n)]
    lu = lu_factor(m)
    k1 = jnp.stack(lu_solve(lu, [f0[i] + forcing[i] for i in range(n)]))
    f1 = f(u1, y + h * k1)
    k2 = jnp.stack(lu_solve(lu, [f1[i] - 2.0 * k1[i] - forcing[i] for i in range(n)]))
    y1 = y + (1.5 * h) * k1 + (0.5 * h) * k2
    return (y1, (0.5 * h) * (k1 + k2)) if error else y1
