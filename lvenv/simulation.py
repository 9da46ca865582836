"""Batched beat-by-beat simulation of the LO heart to steady state (or for a fixed number of beats).

The core, :func:`run_beats`, is a pure function of stacked :class:`~lvenv.model.ModelParams`
and initial states: members are laid out batch-last (state shape ``(9, B)``) so every operation
is vectorised over members, ``lax.scan`` runs the ROS2 steps of a beat and ``lax.while_loop``
the beats. Each member has its own time step h = T / steps_per_beat, so heart rate may differ
per member. A member stops (its state and metrics freeze) as soon as it has
converged or failed; the loop ends when no member is active. Failure is reported as a status
code, never raised inside jitted code, and never leaks into other members.

Steady state: the relative beat-to-beat change of EDV, ESV (both relative to EDV) and peak
P_lv falls below ``rtol``.

Status (:mod:`lvenv.status`): a member whose state turns non-finite or leaves its physical range
is ``nonfinite`` / ``diverged``; a last beat without the full valve cycle is ``no_valve_cycle``;
one with a full cycle but ESV ≤ 0, EF > 1 or EF < :data:`lvenv.status.EF_MIN` is
``non_physical``. Only ``ok`` and ``not_converged`` members report metrics; the others' are NaN.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from lvenv import cell, coupling, events, model
from lvenv.circulation import beat_period
from lvenv.devices import shard_members
from lvenv.integrator import ros2_step
from lvenv.metrics import METRIC_NAMES
from lvenv.model import IDX_PC, IDX_V, ModelParams
from lvenv.params import Heart, as_batch
from lvenv.status import DIVERGED, EF_MIN, NO_VALVE_CYCLE, NON_PHYSICAL, NONFINITE, NOT_CONVERGED, OK, STATUS, is_usable, names
from lvenv.validation import InputError, choice, integer, real, real_array

__all__ = ["STATUS", "SimulationResult", "Traces", "simulate", "run_beats", "run_beats_jit", "check_settings", "MIN_STEPS_PER_BEAT"]

_MAX_VOLUME_FACTOR = 20.0  # V > 20 V0 is treated as divergence
_MAX_PRESSURE = 200.0  # kPa; |P| beyond this is treated as divergence
#: Fewest ROS2 steps per beat: below this the valve events cannot be resolved.
MIN_STEPS_PER_BEAT = 10


def _scan_unroll() -> int:
    """ROS2 steps per scan iteration: 4 on GPU (fewer loop round-trips, measured +10 %), 1 on CPU."""
    default = "4" if jax.default_backend() == "gpu" else "1"
    return int(os.environ.get("LVENV_SCAN_UNROLL", default))


def beat(p: ModelParams, y0: jax.Array, steps: int, record: bool):
    """Simulate one beat of B members from states ``y0`` (9, B), Ca onset at t = 0.

    Returns ``(y_end, metrics, valid, traces)``; traces are ``(V, P_lv, P_ao)`` of shape
    ``(steps + 1, B)`` when ``record`` else ``None``.
    """
    period = beat_period(p.circ)
    h = period / steps
    k = cell.rates(p.cell)
    f = lambda ca, y: model.rhs_at_calcium(ca, y, p, k)
    jac = lambda ca, y, lookahead: model.jacobian(ca, y, p, k, lookahead)
    t = jnp.arange(steps + 1, dtype=y0.dtype)[:, None] * h
    ca, ca_rate = coupling.calcium(t, p.lo, p.cell), coupling.calcium_rate(t, p.lo, p.cell)

    def sample(y):
        obs = model.observe(y, p)
        return y[IDX_V], obs.p_lv, obs.p_at, y[IDX_PC], obs.p_ao

    acc0 = events.start(jnp.zeros_like(h), *sample(y0))

    def step(carry, xs):
        y, acc = carry
        n, ca0, ca1, dca0 = xs
        y1 = ros2_step(f, y, h, ca0, ca1, dca0, jac)
        s = sample(y1)
        acc1 = events.update(acc, (n + 1) * h, *s)
        return (y1, acc1), ((s[0], s[1], s[4]) if record else None)

    xs = (jnp.arange(steps, dtype=y0.dtype), ca[:-1], ca[1:], ca_rate[:-1])
    (y_end, acc), samples = jax.lax.scan(step, (y0, acc0), xs, unroll=_scan_unroll())
    metrics, valid = events.finish(acc, period)
    traces = None
    if record:
        first = sample(y0)
        traces = tuple(jnp.concatenate([first[i][None], s]) for i, s in zip((0, 1, 4), samples))
    return y_end, metrics, valid, traces


def _select(mask, new, old):
    return jax.tree.map(lambda a, b: jnp.where(mask, a, b), new, old)


def _relative_change(m, prev):
    edv = jnp.maximum(jnp.abs(m["EDV"]), 1e-12)
    return jnp.maximum(
        jnp.maximum(jnp.abs(m["EDV"] - prev["EDV"]) / edv, jnp.abs(m["ESV"] - prev["ESV"]) / edv),
        jnp.abs(m["P_lv_peak"] - prev["P_lv_peak"]) / jnp.maximum(jnp.abs(m["P_lv_peak"]), 1e-12),
    )


def run_beats(p: ModelParams, y0: jax.Array, rtol, *, steps: int, max_beats: int, steady: bool, record: bool):
    """Pure batched core: leaves of ``p`` have shape ``(B,)``, ``y0`` has shape ``(9, B)``.

    ``steady=True`` stops each member at steady state (at most ``max_beats`` beats);
    ``steady=False`` runs exactly ``max_beats`` beats. Returns a dict of arrays: ``y``,
    ``metrics``, ``converged``, ``status``, ``beats`` and, when ``record``, ``traces``.
    """
    n_members = y0.shape[1]
    zeros = jnp.zeros((n_members,), y0.dtype)
    carry0 = {
        "n": jnp.asarray(0),
        "y": y0,
        "metrics": {k: zeros for k in METRIC_NAMES},
        "valid": jnp.zeros((n_members,), bool),
        "converged": jnp.zeros((n_members,), bool),
        "active": jnp.ones((n_members,), bool),
        "status": jnp.zeros((n_members,), jnp.int32),
        "beats": jnp.zeros((n_members,), jnp.int32),
    }
    if record:
        carry0["traces"] = tuple(jnp.zeros((steps + 1, n_members), y0.dtype) for _ in range(3))

    def cond(c):
        return (c["n"] < max_beats) & jnp.any(c["active"])

    def body(c):
        y1, m, valid, traces = beat(p, c["y"], steps, record)
        finite = jnp.all(jnp.isfinite(y1), axis=0)
        for value in m.values():
            finite &= jnp.isfinite(value)
        v = y1[IDX_V]
        in_range = (v > 0.0) & (v < _MAX_VOLUME_FACTOR * p.v0) & (jnp.abs(y1[IDX_PC]) < _MAX_PRESSURE) & (jnp.abs(m["P_lv_peak"]) < _MAX_PRESSURE)
        ok = finite & in_range
        accept = c["active"] & ok
        failed = c["active"] & ~ok
        converged = (c["beats"] >= 1) & valid & c["valid"] & (_relative_change(m, c["metrics"]) < rtol)
        new = {
            "n": c["n"] + 1,
            "y": _select(accept, y1, c["y"]),
            "metrics": _select(accept, m, c["metrics"]),
            "valid": jnp.where(accept, valid, c["valid"]),
            "converged": jnp.where(accept, converged, c["converged"]),
            "active": (accept & ~converged) if steady else accept,
            "status": jnp.where(failed, jnp.where(finite, DIVERGED, NONFINITE), c["status"]),
            "beats": c["beats"] + accept.astype(jnp.int32),
        }
        if record:
            new["traces"] = _select(accept, traces, c["traces"])
        return new

    out = jax.lax.while_loop(cond, body, carry0)
    m = out["metrics"]
    physical = (m["ESV"] > 0.0) & (m["EF"] <= 1.0) & (m["EF"] >= EF_MIN)
    status = jnp.where(out["status"] != OK, out["status"], jnp.where(
        ~out["valid"], NO_VALVE_CYCLE, jnp.where(~physical, NON_PHYSICAL, jnp.where(steady & ~out["converged"], NOT_CONVERGED, OK))))
    out["metrics"] = {k: jnp.where(is_usable(status), v, jnp.nan) for k, v in m.items()}
    out["status"] = status
    del out["n"], out["active"], out["valid"]
    return out


run_beats_jit = jax.jit(run_beats, static_argnames=("steps", "max_beats", "steady", "record"))


@dataclasses.dataclass(frozen=True)
class Traces:
    """Last simulated beat: time since its onset (s), V (ml), P_lv and P_ao (kPa)."""

    t: np.ndarray
    V: np.ndarray
    P_lv: np.ndarray
    P_ao: np.ndarray


@dataclasses.dataclass(frozen=True)
class SimulationResult:
    """Result of :func:`simulate`. For a batch every field has a leading batch axis.

    ``metrics`` uses internal units (ml, s, kPa, ml/s); ``status`` holds one of :data:`STATUS`
    per member (``"ok"``, ``"not_converged"``, ``"nonfinite"``, ``"diverged"``,
    ``"no_valve_cycle"``, ``"non_physical"``; :mod:`lvenv.status`); metrics of failed members
    are NaN.
    """

    metrics: dict[str, np.ndarray | float]
    traces: Traces | None
    converged: np.ndarray | bool
    status: np.ndarray | str
    status_code: np.ndarray | int
    beats: np.ndarray | int
    final_state: np.ndarray

    def __len__(self) -> int:
        return 1 if np.ndim(self.status_code) == 0 else len(self.status_code)

    def __getitem__(self, i: int) -> "SimulationResult":
        """Member ``i`` of a batched result, as a single result."""
        pick = lambda x: x[i]
        return SimulationResult(
            metrics={k: float(v[i]) for k, v in self.metrics.items()},
            traces=None if self.traces is None else Traces(*(pick(getattr(self.traces, f.name)) for f in dataclasses.fields(Traces))),
            converged=bool(self.converged[i]),
            status=str(self.status[i]),
            status_code=int(self.status_code[i]),
            beats=int(self.beats[i]),
            final_state=self.final_state[i],
        )


def check_settings(*, steps_per_beat, max_beats, rtol, beats=None) -> dict:
    """Validated integration settings (shared by :func:`simulate` and the environment).

    ``steps_per_beat`` an integer ≥ :data:`MIN_STEPS_PER_BEAT`; ``max_beats`` and ``beats``
    (``None`` allowed) integers ≥ 1; ``rtol`` a finite real number in (0, 1).
    """
    return {
        "steps_per_beat": integer("steps_per_beat", steps_per_beat, MIN_STEPS_PER_BEAT),
        "max_beats": integer("max_beats", max_beats, 1),
        "rtol": real("rtol", rtol, 0.0, 1.0, lo_open=True, hi_open=True),
        "beats": None if beats is None else integer("beats", beats, 1),
    }


def simulate(
    params: Heart | Sequence[Heart],
    *,
    beats: int | None = None,
    max_beats: int = 200,
    rtol: float = 1e-4,
    steps_per_beat: int = 1000,
    traces: bool = True,
    initial_state: np.ndarray | None = None,
    dtype=jnp.float64,
) -> SimulationResult:
    """Simulate one Heart, a sequence of Hearts or a stacked Heart batch.

    Args:
        params: the parameter set(s); every parameter may differ per member, geometry included.
        beats: run exactly this many beats (``converged`` then reports the steady-state test on
            the last two). ``None``: run each member to steady state, at most ``max_beats``.
        rtol: steady-state tolerance on the relative beat-to-beat change of EDV, ESV, peak P_lv.
        steps_per_beat: ROS2 steps per cardiac cycle (h = 60 / HR / steps_per_beat s).
        traces: record t, V, P_lv, P_ao of the last beat.
        initial_state: state(s) to start from (shape (9,) or (B, 9)); default: the training
            protocol's (LV at passive equilibrium with Pat, P_c = Pc0, cell at rest). A member
            whose state is not finite ends with status ``nonfinite``; the others are unaffected.
        dtype: ``jnp.float64`` (default) or ``jnp.float32``.

    Raises:
        ValueError: a parameter outside its documented range, a setting of the wrong type or
            range, or an initial state of the wrong shape (names field, value and what is allowed).
    """
    settings = check_settings(steps_per_beat=steps_per_beat, max_beats=max_beats, rtol=rtol, beats=beats)
    steps_per_beat, max_beats, rtol, beats = (settings[k] for k in ("steps_per_beat", "max_beats", "rtol", "beats"))
    if not isinstance(traces, (bool, np.bool_)):
        raise InputError(f"traces = {traces!r} must be True or False")
    dtype = choice("dtype", jnp.dtype(dtype) if _is_dtype(dtype) else dtype, (jnp.dtype(jnp.float64), jnp.dtype(jnp.float32)))
    heart, single = as_batch(params)
    p = model.model_params(heart)
    n_members = len(p.v0)
    y0 = model.initial_state(p).T if initial_state is None else _initial_state(initial_state, n_members)
    (p_dev, y_dev), _ = shard_members((jax.tree.map(lambda x: np.asarray(x, dtype), p), np.asarray(y0.T, dtype)), n_members)
    out = run_beats_jit(
        p_dev, y_dev, jnp.asarray(rtol, dtype),
        steps=steps_per_beat, max_beats=beats or max_beats, steady=beats is None, record=traces,
    )
    out = jax.tree.map(lambda x: np.asarray(x)[..., :n_members], jax.device_get(out))
    codes = np.asarray(out["status"])
    trace_obj = None
    if traces:
        period = 60.0 / np.asarray(p.circ.HR)
        t = period[:, None] * np.linspace(0.0, 1.0, steps_per_beat + 1)[None, :]
        trace_obj = Traces(t, *(np.asarray(x).T for x in out["traces"]))
    result = SimulationResult(
        metrics={k: np.asarray(v) for k, v in out["metrics"].items()},
        traces=trace_obj,
        converged=np.asarray(out["converged"]),
        status=names(codes),
        status_code=codes,
        beats=np.asarray(out["beats"]),
        final_state=np.asarray(out["y"]).T,
    )
    return result[0] if single else result


def _is_dtype(value) -> bool:
    try:
        jnp.dtype(value)
    except TypeError:
        return False
    return True


def _initial_state(value, n_members: int) -> np.ndarray:
    """User initial state(s) as an ``(n_members, 9)`` float array (one row for all members, or one each)."""
    y = real_array("initial_state", value)
    if y.shape not in ((model.N_STATES,), (n_members, model.N_STATES)):
        raise InputError(f"initial_state has shape {y.shape}; expected ({model.N_STATES},) or ({n_members}, {model.N_STATES}) (one row per member)")
    return np.broadcast_to(y, (n_members, model.N_STATES))
