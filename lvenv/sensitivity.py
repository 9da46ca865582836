"""Derivatives of the steady-state beat metrics with respect to any LO, cell or circulation
parameter: :func:`jacobian`, by forward-mode autodiff through the integrator and the event
location, closed by the implicit-function theorem at the periodic steady state.

Method. Let one beat map the start-of-beat state to the end-of-beat state, ``y ↦ F(y, θ)``, and
give that beat's metrics ``M(y, θ)``. At the steady state y* = F(y*, θ), so

    (I − F_y) dy*/dθ = F_θ,        dM/dθ = M_y dy*/dθ + M_θ.

F_y (9 × 9), F_θ, M_y and M_θ come from 9 + k forward-mode JVPs of *one* beat from y*
(``jax.jvp`` through the ``lax.scan`` of ROS2 steps and the event accumulator), for all members
at once. In the closed loop the blood volume c(y, θ) = V + C P_c + Cat P_at is conserved, so
I − F_y is singular along the volume direction: each steady state belongs to one volume, the
cold start's, c(y0(θ), θ) (:func:`lvenv.model.initial_state`, the same volume the env's warm
starts keep). The volume row ∇_y c · dy* = d c(y0(θ), θ)/dθ − ∂c/∂θ closes the system, which is
solved by least squares (10 × 9, consistent). The cold-start volume's derivative is a central
difference on the host (a smooth closed form and a converged Newton root, relative step 1e-6).
Geometry enters only through V0 (computed on the host) and is not a ``wrt`` parameter.

A multi-element heart (``Heart.elements``, :mod:`lvenv.multielement`) is differentiated the same
way over its flat state of 7 n + 4 rows (:mod:`lvenv.lo_model`). Its algebraic rows (the element
volumes and P_lv) are re-solved at the start of every beat, so F_y has zero columns there (up to
the Newton tolerance) and they add no condition: their rows of I − F_y are the identity.

Where the metrics are not differentiable. Valve events are located by linear interpolation
between integrator steps (:mod:`lvenv.events`), so at a fixed ``steps_per_beat`` an event time
is a smooth function of θ *between* grid steps, and the returned derivative is that of the
interpolated crossing inside the step where it lies. When a change of θ moves an event across a
step, the interpolation's slope changes: durations (IVCT, ET, IVRT, filling time) and the
volumes read at events (EDV, ESV, EF, SV) have kinks there, with one-sided derivatives that
differ by O(h); this derivative is the one of the current step. The valves themselves are
diodes (flow ∝ max(ΔP, 0)); their switching is resolved by the steps, with the same kind of
kink. Peak and extreme pressures are maxima over the step samples (the derivative of the
maximising sample). Members whose steady state is not usable (any status but ``ok``) get NaN
rows, never numbers: ``not_converged`` included, since the derivative assumes y* = F(y*).

Checked against central finite differences of :func:`lvenv.simulate` over random hearts in
``tests/lvenv/test_sensitivity.py``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from lvenv import lo_model, model
from lvenv.devices import shard_members
from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.metrics import FRAME_NAMES, METRIC_NAMES
from lvenv.params import Heart, as_batch, field_names
from lvenv.simulation import beat, simulate
from lvenv.validation import InputError

__all__ = ["Jacobian", "jacobian"]

_VOLUME_STEP = 1e-6  # relative central-difference step of the cold-start blood volume


@dataclasses.dataclass(frozen=True)
class Jacobian:
    """d metric / d parameter at the steady state, in internal units per internal unit.

    ``values`` has shape ``(len(metrics), len(wrt))`` for one heart, with a leading batch axis
    for a batch; ``metrics_at`` holds the metric values there, ``status`` the steady state's
    status (a member that is not ``ok`` has NaN rows)."""

    wrt: tuple[str, ...]
    metrics: tuple[str, ...]
    values: np.ndarray
    metrics_at: dict[str, np.ndarray | float]
    status: np.ndarray | str

    def __getitem__(self, key: tuple[str, str]) -> np.ndarray | float:
        """``jac["EF", "tau2"]``: d EF / d τ2 (per member for a batch)."""
        metric, name = key
        if metric not in self.metrics or name not in self.wrt:
            raise KeyError(f"{key!r}: metrics are {self.metrics}, parameters {self.wrt}")
        return self.values[..., self.metrics.index(metric), self.wrt.index(name)]


def _check_names(wrt: Sequence[str], metrics: Sequence[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    if isinstance(wrt, str) or isinstance(metrics, str):
        raise InputError("wrt and metrics must be sequences of names, e.g. wrt=('tau2',), not a single string")
    wrt, metrics = tuple(wrt), tuple(metrics)
    known = field_names()
    for name in wrt:
        if name not in known:
            raise InputError(f"wrt contains {name!r}, which is not an LO, cell or circulation parameter; known: {known}")
        if name == "closed_loop":
            raise InputError("wrt = 'closed_loop' is a switch (0 or 1), not a differentiable parameter")
    for name in metrics:
        if name not in METRIC_NAMES:
            raise InputError(f"metrics contains {name!r}; choose from {METRIC_NAMES}")
    if not wrt or not metrics or len(set(wrt)) != len(wrt) or len(set(metrics)) != len(metrics):
        raise InputError(f"wrt = {wrt} and metrics = {metrics} must be non-empty and without repeats")
    return wrt, metrics


def _volume(p: model.ModelParams, y: np.ndarray) -> np.ndarray:
    """Closed-loop blood volume V + C P_c + Cat P_at (ml) of states ``y`` (n_states, B)."""
    i_v, i_pc, i_pat = lo_model.circulation_index(p)
    return y[i_v] + np.asarray(p.circ.C) * y[i_pc] + np.asarray(p.circ.Cat) * y[i_pat]


def _cold_volume_rates(heart: Heart, wrt: tuple[str, ...]) -> np.ndarray:
    """d c(y0(θ), θ) / dθ_j (k, B) by central differences on the host (module docstring)."""
    rates = []
    for name in wrt:
        value = np.asarray(heart.get(name), float)
        step = _VOLUME_STEP * np.maximum(np.abs(value), 1e-3)
        vols = []
        for sign in (1.0, -1.0):
            p = lo_model.core_params(heart.replace(**{name: value + sign * step}))
            vols.append(_volume(p, lo_model.initial_state(p)))
        rates.append((vols[0] - vols[1]) / (2.0 * step))
    return np.stack(rates)


@functools.partial(jax.jit, static_argnames=("wrt", "steps", "volume_trace"))
def _beat_tangents(p: model.ModelParams, y: jax.Array, theta: jax.Array, *, wrt: tuple[str, ...], steps: int, volume_trace: bool):
    """JVPs of one beat from ``y`` (n, S) along each state axis and each parameter of ``wrt``
    (values ``theta`` (k, S)), all members at once: (end state (n + k, n, S), metrics (n + k, m, S))
    with every metric of :data:`~lvenv.metrics.METRIC_NAMES` (the frames NaN without
    ``volume_trace``), so that one program serves any choice of metrics; n = 9 for the single
    cell (:func:`lvenv.lo_model.n_states`)."""

    def one_beat(y, th):
        pp = p.replace(**{name: th[j] for j, name in enumerate(wrt)})
        y_end, m, _, _ = beat(pp, y, steps, False, volume_trace)
        return y_end, jnp.stack([m[name] for name in METRIC_NAMES])

    k, (n, size) = len(wrt), y.shape
    eye_y = jnp.concatenate([jnp.broadcast_to(jnp.eye(n)[:, :, None], (n, n, size)), jnp.zeros((k, n, size))])
    eye_th = jnp.concatenate([jnp.zeros((n, k, size)), jnp.broadcast_to(jnp.eye(k)[:, :, None], (k, k, size))])
    return jax.vmap(lambda dy, dth: jax.jvp(one_beat, (y, theta), (dy, dth))[1])(eye_y, eye_th)


def jacobian(
    heart: Heart | Sequence[Heart],
    wrt: Sequence[str] = DEFAULT_ACTION_PARAMS,
    metrics: Sequence[str] = METRIC_NAMES,
    *,
    max_beats: int = 200,
    rtol: float = 1e-6,
    steps_per_beat: int = 1000,
) -> Jacobian:
    """d metrics / d ``wrt`` of the steady-state beat of ``heart`` (one Heart or a batch), at the
    settings :func:`lvenv.simulate` takes (module docstring for the method and its limits).

    The steady state is found by :func:`lvenv.simulate` with ``rtol`` (tighter than the default
    1e-4: the derivative assumes y* = F(y*)); a member that does not reach it has NaN rows.
    One compiled program serves every choice of ``metrics`` for given ``wrt``, ``steps_per_beat``
    and batch shape (a second one where the metrics include a volume-trace frame).
    """
    wrt, metrics = _check_names(wrt, metrics)
    batch, single = as_batch(heart)
    steady = simulate(batch, max_beats=max_beats, rtol=rtol, steps_per_beat=steps_per_beat, traces=False)
    p = lo_model.core_params(batch)
    n, k, n_y = len(p.v0), len(wrt), lo_model.n_states(p)
    theta = np.stack([np.asarray(p.get(name), float) for name in wrt])  # (k, B)
    y_star = np.asarray(steady.final_state, float).T  # (n_y, B)
    (p_dev, y_dev, theta_dev), _ = shard_members((p, y_star, theta), n)

    volume_trace = not set(metrics).isdisjoint(FRAME_NAMES)
    d_y, d_m = jax.device_get(_beat_tangents(p_dev, y_dev, theta_dev, wrt=wrt, steps=steps_per_beat, volume_trace=volume_trace))
    d_y, d_m = np.asarray(d_y)[..., :n], np.asarray(d_m)[..., :n]
    f_y, f_th = np.moveaxis(d_y[:n_y], 0, 1), np.moveaxis(d_y[n_y:], 0, 1)  # (n_y, n_y, B), (n_y, k, B)
    m_y, m_th = np.moveaxis(d_m[:n_y], 0, 1), np.moveaxis(d_m[n_y:], 0, 1)  # (M, n_y, B), (M, k, B): all M metrics

    closed = np.asarray(p.circ.closed_loop, float)
    i_v, i_pc, i_pat = lo_model.circulation_index(p)
    grad_c = np.zeros((n_y, n))
    grad_c[i_v], grad_c[i_pc], grad_c[i_pat] = 1.0, np.asarray(p.circ.C), np.asarray(p.circ.Cat)
    partial_c = np.zeros((k, n))  # ∂c/∂θ at fixed state: P_c for C, P_at for Cat
    for j, name in enumerate(wrt):
        if name == "C":
            partial_c[j] = y_star[i_pc]
        elif name == "Cat":
            partial_c[j] = y_star[i_pat]
    volume_rhs = _cold_volume_rates(batch, wrt) - partial_c  # (k, B)

    # Every metric's row is computed and the asked-for ones are taken after: a product's shape
    # fixes its rounding, so a metric's derivative does not depend on which others are asked for.
    values = np.full((n, len(METRIC_NAMES), k), np.nan)
    for b in np.flatnonzero(np.atleast_1d(steady.status) == "ok"):
        a = np.vstack([np.eye(n_y) - f_y[:, :, b], closed[b] * grad_c[:, b][None]])
        rhs = np.vstack([f_th[:, :, b], closed[b] * volume_rhs[:, b][None]])
        dy_star = np.linalg.lstsq(a, rhs, rcond=None)[0]
        values[b] = m_y[:, :, b] @ dy_star + m_th[:, :, b]
    values = values[:, [METRIC_NAMES.index(name) for name in metrics]]
    at = {name: np.asarray(steady.metrics[name]) for name in metrics}
    if single:
        return Jacobian(wrt, metrics, values[0], {name: float(v[0]) for name, v in at.items()}, str(steady.status[0]))
    return Jacobian(wrt, metrics, values, at, np.asarray(steady.status))

