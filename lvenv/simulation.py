"""Batched beat-by-beat simulation of the LO heart to steady state (or for a fixed number of beats).

The core, :func:`run_beats`, is a pure function of stacked :class:`~lvenv.model.ModelParams`
and initial states: members are laid out batch-last (state shape ``(9, B)``) so every operation
is vectorised over members, and ``lax.while_loop`` runs the beats. A member stops (its state and
metrics freeze) as soon as it has converged or failed; the loop ends when no member is active.
Failure is reported as a status code, never raised inside jitted code, and never leaks into
other members.

Two integration schemes (``scheme``), both ROS2 (:mod:`lvenv.integrator`):

* ``"fixed"`` (:func:`beat`): ``lax.scan`` over steps_per_beat equal steps, h = T / steps_per_beat
  per member (heart rate may differ per member); records traces. ``simulate``'s default.
* ``"adaptive"`` (:func:`beat_adaptive`): per-member step-size control from the embedded error
  estimate, the last step landing on the end of the beat, all members in lock-step; after a
  member's first beat it replays its last beat's steps while they stay accurate, so a beat is a
  smooth function of its start. At the default ``step_tol`` it takes about 2.7× fewer steps than
  1000 per beat at better accuracy against Radau (EF, phase durations, pressures; README,
  Performance). The environment's default; no traces.

Steady state: the relative beat-to-beat change of EDV, ESV (both relative to EDV) and peak
P_lv falls below ``rtol``; ``acceleration="anderson"`` reaches it in fewer beats by
extrapolating the beat map's fixed point every second beat (:func:`run_beats`).

:func:`run_beats_parallel` runs the core over a padded batch's layout (:func:`lvenv.devices.layout`):
each device its own loops, and on the CPU blocks of at most :data:`lvenv.devices.CPU_BLOCK`
members one after the other, so that a block's working set stays in cache, or, for the adaptive
scheme to steady state, the device's members queued through :func:`lvenv.devices.queue_lanes`
lanes (:func:`run_beats_queued`). :data:`run_beats_jit` is its jitted form; ``max_beats`` is an
argument of its program, not a setting it is compiled for, so calls that differ only in their
number of beats share one compiled program.

A multi-element heart (:class:`lvenv.multielement.ElementParams`, ``Heart.elements``) runs
through the same loops with its flat state of 7 n + 4 rows: :func:`beat` calls
:func:`lvenv.multielement.beat` for it (the fixed scheme only), and a member whose series Newton
misses its tolerance is ``diverged``.

Status (:mod:`lvenv.status`): a member whose state turns non-finite or leaves its physical range
is ``nonfinite`` / ``diverged``; a last beat without the full valve cycle is ``no_valve_cycle``;
one with a full cycle but a non-physical beat (:func:`lvenv.status.is_physical`: ESV ≤ 0, EF > 1,
EF < :data:`lvenv.status.EF_MIN`, or a negative filling or diastolic aortic pressure) is
``non_physical``. Only ``ok`` and ``not_converged`` members report metrics; the others' are NaN.

Why one module of about 660 lines (above the project's guide of about 600): it is one algorithm.
The one-beat integrators and the beat loop share the adaptive scheme's internals: the replay
grid that :func:`beat_adaptive` records and :func:`run_beats` carries to the next beat
(:data:`GRID_STEPS`), the per-state error scale that sets both the step control and the
Anderson jump limit, and the masked update of finished members. Splitting the integrators off
would make these internals the public interface between two modules. The host-side rest
(:func:`simulate`, :class:`SimulationResult`, :func:`check_settings`, about 160 lines) cannot
take its natural module name, ``lvenv.simulate``, which is the public function's.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

from lvenv import cell, coupling, events, lo_model, model, multielement
from lvenv.circulation import beat_period
from lvenv.devices import layout, member_mesh, queue_lanes, shard_members
from lvenv.integrator import ros2_step
from lvenv.metrics import METRIC_NAMES, SUMMARY_NAMES
from lvenv.model import IDX_PC, IDX_V, ModelParams
from lvenv.params import Heart, as_batch
from lvenv.status import DIVERGED, NO_VALVE_CYCLE, NON_PHYSICAL, NONFINITE, NOT_CONVERGED, OK, STATUS, is_physical, is_usable, names
from lvenv.validation import InputError, choice, integer, real, real_array

__all__ = ["STATUS", "SimulationResult", "Traces", "simulate", "run_beats", "run_beats_parallel", "run_beats_queued", "run_beats_jit", "check_settings", "MIN_STEPS_PER_BEAT", "MAX_STEPS_PER_BEAT", "MAX_BEATS", "SCHEMES", "DEFAULT_STEP_TOL", "ACCELERATIONS"]

_MAX_VOLUME_FACTOR = 20.0  # V > 20 V0 is treated as divergence
_MAX_PRESSURE = 200.0  # kPa; |P| beyond this is treated as divergence
#: Fewest ROS2 steps per beat: below this the valve events cannot be resolved.
MIN_STEPS_PER_BEAT = 10
#: Most ROS2 steps per beat (h = 12 µs at 60 bpm, 80× finer than the default): more only costs
#: time and memory (a recorded trace holds 4 floats per step and member).
MAX_STEPS_PER_BEAT = 50_000
#: Most beats of one call (``beats`` or ``max_beats``): about a minute of one heart at the
#: default 1000 steps per beat on a 2-core CPU; a heart not steady after it never will be.
MAX_BEATS = 10_000
#: Adaptive scheme: most trial steps per beat before a member is given up as ``nonfinite``.
MAX_ADAPTIVE_STEPS = 5000
#: Integration schemes: ``"fixed"`` (``steps_per_beat`` equal ROS2 steps) and ``"adaptive"``
#: (per-member step-size control at ``step_tol``, :func:`beat_adaptive`).
SCHEMES = ("fixed", "adaptive")
#: Default ``step_tol`` of the adaptive scheme: the accuracy specification against Radau with
#: margin (the hearts of ``scripts/bench_lo.py``, 32 of seed 1: EF within 0.14 points, phase
#: durations 0.83 ms, pressures 0.08 %; 1000 fixed steps: 0.03, 0.73 ms, 0.07 %).
DEFAULT_STEP_TOL = 2e-3
#: Steady-state iterations: ``"none"`` (each beat starts where the last ended) and ``"anderson"``
#: (every second beat starts from an Anderson-extrapolated state, :func:`run_beats`).
ACCELERATIONS = ("none", "anderson")


def _scan_unroll() -> int:
    """ROS2 steps per scan iteration: 4 on GPU (fewer loop round-trips, measured +10 %), 1 on CPU."""
    default = "4" if jax.default_backend() == "gpu" else "1"
    return int(os.environ.get("LVENV_SCAN_UNROLL", default))


def _beat_system(p: ModelParams):
    """What both schemes integrate: the period T (s), f(ca, y), its analytic Jacobian for
    :func:`lvenv.integrator.ros2_step`, and the samples the event detector folds (V, P_lv, P_at,
    P_c, P_ao of a state)."""
    k = cell.rates(p.cell)
    f = lambda ca, y: model.rhs_at_calcium(ca, y, p, k)
    jac = lambda ca, y, lookahead: model.jacobian(ca, y, p, k, lookahead)

    def sample(y):
        obs = model.observe(y, p)
        return y[IDX_V], obs.p_lv, obs.p_at, y[IDX_PC], obs.p_ao

    return beat_period(p.circ), f, jac, sample


def beat(p: ModelParams, y0: jax.Array, steps: int, record: bool, volume_trace: bool = True):
    """Simulate one beat of B members from states ``y0`` (9, B; a multi-element heart's flat
    state for :class:`lvenv.multielement.ElementParams`), Ca onset at t = 0.

    Returns ``(y_end, metrics, valid, traces)``; traces are ``(V, P_lv, P_ao)`` of shape
    ``(steps + 1, B)`` when ``record`` else ``None``.
    """
    return _checked_beat(p, y0, steps, record, volume_trace)[:4]


def _checked_beat(p: ModelParams, y0: jax.Array, steps: int, record: bool, volume_trace: bool):
    """:func:`beat` and whether each member stayed on its constraint manifold (always, for the
    single cell; :func:`lvenv.multielement.beat`)."""
    if lo_model.is_multielement(p):
        return multielement.beat(p, y0, steps, record, volume_trace)
    return (*_cell_beat(p, y0, steps, record, volume_trace), True)


def _cell_beat(p: ModelParams, y0: jax.Array, steps: int, record: bool, volume_trace: bool):
    """:func:`beat` of the single-cell heart."""
    period, f, jac, sample = _beat_system(p)
    h = period / steps
    norm = cell.transient_norm(p.cell)

    acc0 = events.start(jnp.zeros_like(h), *sample(y0), period, volume_trace)

    def step(carry, n):
        y, acc = carry
        # [Ca] per member inside the loop, as in the adaptive scheme. Precomputed as (steps + 1, B)
        # arrays, or carried from the step before, its last bits depended on how XLA compiled the
        # program (one device or sharded over two; the block width), and so did every member's
        t0, t1 = n * h, (n + 1) * h
        ca0, ca1 = coupling.calcium(t0, p.lo, p.cell, norm), coupling.calcium(t1, p.lo, p.cell, norm)
        y1 = ros2_step(f, y, h, ca0, ca1, coupling.calcium_rate(t0, p.lo, p.cell, norm), jac)
        s = sample(y1)
        acc1 = events.update(acc, t1, *s)
        return (y1, acc1), ((s[0], s[1], s[4]) if record else None)

    (y_end, acc), samples = jax.lax.scan(step, (y0, acc0), jnp.arange(steps, dtype=y0.dtype), unroll=_scan_unroll())
    metrics, valid = events.finish(acc, period)
    traces = None
    if record:
        first = sample(y0)
        traces = tuple(jnp.concatenate([first[i][None], s]) for i, s in zip((0, 1, 4), samples))
    return y_end, metrics, valid, traces


#: Adaptive scheme: error scale added to abs(y) per state, for CaTRPN, B, S, W, ζs, ζw (dimensionless),
#: V (in units of the member's V0) and P_c, P_at (kPa).
_ERROR_SCALE = (1.0, 1.0, 0.01, 0.01, 0.01, 0.01, 1.0, 1.0, 1.0)
#: Adaptive scheme: first step of a beat as a fraction of the period (the calcium transient starts at once).
_FIRST_STEP = 1e-3
#: Adaptive scheme: bounds on the step-size ratio of one step to the next, and the safety factor.
_GROW, _SHRINK, _SAFETY = 5.0, 0.2, 0.9
#: Adaptive scheme: a replayed step (:func:`beat_adaptive`) is kept while its scaled error is at most this.
_REPLAY_ERROR = 2.0
#: Adaptive scheme: most trial steps a member's replay grid holds (the default tolerance takes about 370 per beat).
GRID_STEPS = 1024
#: Anderson acceleration: largest move of an extrapolated start from the beat end it replaces,
#: per state, in units of the state's error scale (:data:`_ERROR_SCALE`; V in units of V0).
_MAX_JUMP = 0.5
#: Anderson acceleration: extrapolate only while a plain beat's relative change exceeds this many
#: times the steady-state tolerance (closer in, plain beats finish sooner than an extra pair would).
_MIN_CHANGE = 10.0


def _state_scale(p: ModelParams, dtype) -> jax.Array:
    """:data:`_ERROR_SCALE` per member, shape (9, B), V's entry in ml (the member's V0). A
    multi-element state (:func:`lvenv.multielement.flatten`) takes the cell entries for every
    element, the member's V0 for V and each V_ξ, and 1 kPa for P_c, P_at and P_lv."""
    if not lo_model.is_multielement(p):
        return jnp.stack([p.v0 if i == IDX_V else jnp.full_like(p.v0, s) for i, s in enumerate(_ERROR_SCALE)]).astype(dtype)
    n = p.n_elements
    cells = np.repeat(_ERROR_SCALE[: cell.N_STATES], n)
    scale = [jnp.full_like(p.v0, s) for s in cells] + [p.v0, jnp.ones_like(p.v0), jnp.ones_like(p.v0)] + [p.v0] * n + [jnp.ones_like(p.v0)]
    return jnp.stack(scale).astype(dtype)


def beat_adaptive(p: ModelParams, y0: jax.Array, step_tol, max_steps: int, grid: tuple[jax.Array, jax.Array] | None = None,
                  volume_trace: bool = True):
    """One beat like :func:`beat`, with per-member step-size control.

    Returns ``(y_end, metrics, valid, trials, grid)``. Each member has its own t and h, all step
    in lock-step (``lax.while_loop``) and a member that has reached the end of its beat waits for
    the others. A step is accepted when the RMS over the states of the embedded ROS2 error
    estimate (:func:`lvenv.integrator.ros2_step`), each scaled by ``step_tol`` · (abs(y) + s) with s
    from :data:`_ERROR_SCALE`, is at most 1; the next step is h · clip(0.9 err^(-1/2), 0.2, 5)
    (the estimate is O(h²)), and the last step lands on the end of the beat. Valve events are
    located by linear interpolation between accepted steps. A member not at the end of its beat
    after ``max_steps`` trials ends with a non-finite state (reported as ``nonfinite``).

    ``grid`` = ``(times, count)``: an earlier beat's time after each of its trial steps (a
    rejected trial leaves the time unchanged, a zero step), shape ``(GRID_STEPS, B)``, and how
    many trials each member made (0: no grid). A member with a grid replays it, trial for trial,
    while each step's error stays at most :data:`_REPLAY_ERROR`; at the first that does not, it
    goes on with step-size control. Near steady state the replayed grid makes a beat a smooth
    function of its start state, so beat-to-beat changes fall like the fixed scheme's instead of
    stalling at the size of an accept/reject flip (about 1e-4 relative at the default
    tolerance). Trial n of every member reads and writes row n, so replaying and recording are
    row operations, not per-member gathers. The returned grid is this beat's (count 0 when its
    trials did not fit).
    """
    period, f, jac, sample = _beat_system(p)
    norm = cell.transient_norm(p.cell)
    scale = _state_scale(p, y0.dtype)
    zero = jnp.zeros_like(y0[0])
    old_times, old_count = (jnp.zeros((GRID_STEPS,) + zero.shape, y0.dtype), jnp.zeros(zero.shape, jnp.int32)) if grid is None else grid

    def cond(c):
        return (c["n"] < max_steps) & ~jnp.all(c["done"])

    def body(c):
        t, y, n = c["t"], c["y"], c["n"]
        replay = c["replay"] & (n < old_count)
        planned = jax.lax.dynamic_index_in_dim(old_times, jnp.minimum(n, GRID_STEPS - 1), keepdims=False) - t
        step = jnp.where(replay, planned, c["h"])
        last = jnp.where(replay, n == old_count - 1, step >= period - t)
        h = jnp.where(last, period - t, step)
        t1 = jnp.where(last, period, t + h)
        ca0, ca1 = coupling.calcium(t, p.lo, p.cell, norm), coupling.calcium(t1, p.lo, p.cell, norm)
        y1, e = ros2_step(f, y, h, ca0, ca1, coupling.calcium_rate(t, p.lo, p.cell, norm), jac, error=True)
        err = jnp.sqrt(jnp.mean((e / (step_tol * (jnp.maximum(jnp.abs(y), jnp.abs(y1)) + scale))) ** 2, axis=0))
        good = jnp.isfinite(err) & jnp.all(jnp.isfinite(y1), axis=0)
        accept = ~c["done"] & good & (err <= jnp.where(replay, _REPLAY_ERROR, 1.0))
        factor = jnp.where(good, jnp.clip(_SAFETY / jnp.sqrt(jnp.maximum(err, 1e-10)), _SHRINK, _GROW), _SHRINK)
        t_next = jnp.where(accept, t1, t)
        return {
            "n": c["n"] + 1,
            "t": t_next,
            "y": _select(accept, y1, y),
            "h": jnp.where(c["done"], c["h"], jnp.where(replay & accept, c["h"], h * factor)),
            "acc": _select(accept, events.update(c["acc"], t1, *sample(y1)), c["acc"]),
            "done": c["done"] | (accept & last),
            "trials": c["trials"] + (~c["done"]).astype(jnp.int32),
            "replay": c["replay"] & (accept | c["done"]),
            "times": jax.lax.dynamic_update_index_in_dim(c["times"], t_next, jnp.minimum(n, GRID_STEPS - 1), 0),
        }

    carry0 = {
        "n": jnp.asarray(0), "t": zero, "y": y0, "h": _FIRST_STEP * period + zero, "acc": events.start(zero, *sample(y0), period, volume_trace),
        "done": zero > 1.0, "trials": jnp.zeros(zero.shape, jnp.int32),
        "replay": old_count > 0, "times": jnp.zeros_like(old_times),
    }
    out = jax.lax.while_loop(cond, body, carry0)
    metrics, valid = events.finish(out["acc"], period)
    y_end = jnp.where(out["done"], out["y"], jnp.nan)
    count = jnp.where(out["done"] & (out["trials"] <= GRID_STEPS), out["trials"], 0)
    return y_end, metrics, valid, out["trials"], (out["times"], count)


def _select(mask, new, old):
    return jax.tree.map(lambda a, b: jnp.where(mask, a, b), new, old)


def _relative_change(m, prev):
    edv = jnp.maximum(jnp.abs(m["EDV"]), 1e-12)
    return jnp.maximum(
        jnp.maximum(jnp.abs(m["EDV"] - prev["EDV"]) / edv, jnp.abs(m["ESV"] - prev["ESV"]) / edv),
        jnp.abs(m["P_lv_peak"] - prev["P_lv_peak"]) / jnp.maximum(jnp.abs(m["P_lv_peak"]), 1e-12),
    )


def _anderson(x, f, hist, scale):
    """Anderson-accelerated next start from the pair (x, f = F(x)) and up to two earlier pairs.

    ``hist`` holds ``(x1, f1, x2, f2, count)``, the earlier pairs (newest first) and how many of
    them are set. With residuals r = f − x weighted by 1/scale, γ minimises
    ‖r − [r − r1, r1 − r2] γ‖ (2×2 normal equations, ridge-regularised; one column while only
    one earlier pair exists) and the next start is f − [f − f1, f1 − f2] γ: an affine combination
    of beat ends, so the closed-loop blood volume (conserved by every beat) is conserved.
    """
    x1, f1, x2, f2, count = hist
    w = 1.0 / scale
    r, r1, r2 = (f - x) * w, (f1 - x1) * w, (f2 - x2) * w
    d1, d2 = r - r1, r1 - r2
    dot = lambda a, b: jnp.sum(a * b, axis=0)
    a11, a12, a22 = dot(d1, d1), dot(d1, d2), dot(d2, d2)
    b1, b2 = dot(d1, r), dot(d2, r)
    two = count >= 2
    a22 = jnp.where(two, a22, 1.0)
    a12 = jnp.where(two, a12, 0.0)
    b2 = jnp.where(two, b2, 0.0)
    ridge = 1e-10 * (a11 + a22)
    a11, a22 = a11 + ridge, a22 + ridge
    det = a11 * a22 - a12 * a12
    g1 = (b1 * a22 - b2 * a12) / det
    g2 = (a11 * b2 - a12 * b1) / det
    return f - g1 * (f - f1) - g2 * (f1 - f2)


def run_beats(p: ModelParams, y0: jax.Array, rtol, *, steps: int, max_beats: int, steady: bool, record: bool,
              scheme: str = "fixed", step_tol: float = DEFAULT_STEP_TOL, acceleration: str = "none", volume_trace: bool = True):
    """Pure batched core: leaves of ``p`` have shape ``(B,)``, ``y0`` has shape ``(9, B)``.

    ``steady=True`` stops each member at steady state (at most ``max_beats`` beats);
    ``steady=False`` runs exactly ``max_beats`` beats. Returns a dict of arrays: ``y``,
    ``metrics``, ``converged``, ``status``, ``beats`` and, when ``record``, ``traces``.
    ``steps`` counts each member's ROS2 steps (tried, over all its beats).
    ``scheme="fixed"``: ``steps`` equal ROS2 steps per beat; ``"adaptive"``: step-size control
    at ``step_tol`` (:func:`beat_adaptive`) with at most :data:`MAX_ADAPTIVE_STEPS` trial steps
    per beat (``steps`` unused; ``record`` not available).

    ``acceleration="anderson"`` (with ``steady=True``) treats a beat as the map F from the state
    at its onset to the state at its end and seeks its fixed point: every second beat starts
    from an Anderson-extrapolated state (:func:`_anderson`) instead of the previous beat's end,
    and the beats between are plain. Steady state is tested exactly as without acceleration,
    on a plain beat against the beat before it. An extrapolated start that is not finite,
    moves a state by more than :data:`_MAX_JUMP` of its scale, or whose beat fails, is dropped:
    the member goes on from its last plain end without further acceleration, so acceleration
    never fails a member that plain beats would not.

    ``volume_trace=False`` skips the volume-trace frames (:func:`lvenv.events.start`; their
    metrics are NaN), which saves about 8 % of a step's time.
    """
    if scheme == "adaptive" and record:
        raise ValueError("traces are recorded by the fixed scheme only (scheme='fixed')")
    if scheme == "adaptive" and lo_model.is_multielement(p):
        raise ValueError("a multi-element heart runs with the fixed scheme only (scheme='fixed')")
    settings = dict(steps=steps, steady=steady, record=record, scheme=scheme, step_tol=step_tol, acceleration=acceleration,
                    volume_trace=volume_trace)
    carry0 = {"n": jnp.asarray(0), **_start_carry(y0, **settings)}
    scale = _state_scale(p, y0.dtype)

    def cond(c):
        return (c["n"] < max_beats) & jnp.any(c["active"])

    def body(c):
        return {"n": c["n"] + 1, **_advance(p, scale, c, rtol, **settings)}

    return _finish(jax.lax.while_loop(cond, body, carry0), steady)


def _result_start(y0: jax.Array) -> dict:
    """The loop state's fields that :func:`run_beats` returns (through :func:`_finish`), before
    the first beat of members starting at ``y0`` (9, B)."""
    n_members = y0.shape[1]
    zeros = jnp.zeros((n_members,), y0.dtype)
    count = jnp.zeros((n_members,), jnp.int32)
    return {"y": y0, "metrics": {k: zeros for k in METRIC_NAMES}, "valid": jnp.zeros((n_members,), bool),
            "converged": jnp.zeros((n_members,), bool), "status": count, "beats": count, "steps": count}


def _start_carry(y0: jax.Array, *, steps: int, steady: bool, record: bool, scheme: str, acceleration: str, **_) -> dict:
    """Loop state of :func:`run_beats` for members starting at ``y0`` (9, B)."""
    n_members = y0.shape[1]
    carry = {
        **_result_start(y0),
        "active": jnp.ones((n_members,), bool),
        "start": y0,
        "plain": jnp.ones((n_members,), bool),
        "change": jnp.full((n_members,), jnp.inf, y0.dtype),
        "accelerate": jnp.full((n_members,), acceleration == "anderson" and steady),
        "hist": (y0, y0, y0, y0, jnp.zeros((n_members,), jnp.int32)),
    }
    if scheme == "adaptive":
        carry["grid"] = (jnp.zeros((GRID_STEPS, n_members), y0.dtype), jnp.zeros((n_members,), jnp.int32))
    if record:
        carry["traces"] = tuple(jnp.zeros((steps + 1, n_members), y0.dtype) for _ in range(3))
    return carry


def _advance(p: ModelParams, scale: jax.Array, c: dict, rtol, *, steps: int, steady: bool, record: bool, scheme: str, step_tol: float,
             acceleration: str, volume_trace: bool) -> dict:
    """One beat of every active member of the loop state ``c`` (:func:`_start_carry`): the new loop state."""
    n_members = c["y"].shape[1]
    x = c["start"]
    if scheme == "adaptive":
        y1, m, valid, trials, grid = beat_adaptive(p, x, step_tol, MAX_ADAPTIVE_STEPS, c["grid"], volume_trace)
        traces, on_manifold = None, True
    else:
        y1, m, valid, traces, on_manifold = _checked_beat(p, x, steps, record, volume_trace)
        trials = jnp.full(n_members, steps, jnp.int32)
    finite = jnp.all(jnp.isfinite(y1), axis=0)
    for key in SUMMARY_NAMES:  # the frames are NaN without volume_trace
        finite &= jnp.isfinite(m[key])
    i_v, i_pc, _ = lo_model.circulation_index(p)
    v = y1[i_v]
    in_range = (v > 0.0) & (v < _MAX_VOLUME_FACTOR * p.v0) & (jnp.abs(y1[i_pc]) < _MAX_PRESSURE) & (jnp.abs(m["P_lv_peak"]) < _MAX_PRESSURE)
    ok = finite & in_range & on_manifold
    dropped = c["active"] & ~ok & ~c["plain"]  # a failed extrapolation: back to the last plain end
    accept = c["active"] & ok
    failed = c["active"] & ~ok & c["plain"]
    change = jnp.where((c["beats"] >= 1) & valid & c["valid"], _relative_change(m, c["metrics"]), jnp.inf)
    converged = c["plain"] & (change < rtol)
    stalled = c["plain"] & jnp.isfinite(c["change"]) & (change >= c["change"])  # a plain beat's change did not fall since the last one
    x1, f1, x2, _, count = c["hist"]
    hist = _select(accept, (x, y1, x1, f1, jnp.minimum(count + 1, 2)), c["hist"])
    if acceleration == "anderson":
        jump = _anderson(x, y1, c["hist"], scale)
        usable = jnp.all(jnp.isfinite(jump), axis=0) & jnp.all(jnp.abs(jump - y1) <= _MAX_JUMP * scale, axis=0)
        extrapolate = accept & c["accelerate"] & ~stalled & c["plain"] & (count >= 1) & usable & (change > _MIN_CHANGE * rtol)
    else:  # no extrapolation to compute per beat
        jump, extrapolate = y1, jnp.zeros_like(accept)
    new = {
        "y": _select(accept, y1, c["y"]),
        "metrics": _select(accept, m, c["metrics"]),
        "valid": jnp.where(accept, valid, c["valid"]),
        "converged": jnp.where(accept, converged, c["converged"]),
        "active": ((accept | dropped) & ~converged) if steady else accept,
        "status": jnp.where(failed, jnp.where(finite, DIVERGED, NONFINITE), c["status"]),
        "beats": c["beats"] + (accept | dropped).astype(jnp.int32),
        "steps": c["steps"] + jnp.where(c["active"], trials, 0),
        "start": jnp.where(extrapolate, jump, jnp.where(accept, y1, c["y"])),
        "plain": ~extrapolate,
        "accelerate": c["accelerate"] & ~dropped & ~(accept & stalled),
        "change": jnp.where(accept & c["plain"], change, c["change"]),
        "hist": hist,
    }
    if record:
        new["traces"] = _select(accept, traces, c["traces"])
    if scheme == "adaptive":
        new["grid"] = _select(accept, grid, c["grid"])
    return new


def _finish(out: dict, steady: bool) -> dict:
    """:func:`run_beats`'s result from its final loop state: status codes, NaN metrics where unusable."""
    m = out["metrics"]
    status = jnp.where(out["status"] != OK, out["status"], jnp.where(
        ~out["valid"], NO_VALVE_CYCLE, jnp.where(~is_physical(m), NON_PHYSICAL, jnp.where(steady & ~out["converged"], NOT_CONVERGED, OK))))
    result = {k: out[k] for k in ("y", "converged", "beats", "steps", "traces") if k in out}
    return {**result, "metrics": {k: jnp.where(is_usable(status), v, jnp.nan) for k, v in m.items()}, "status": status}


def run_beats_queued(p: ModelParams, y0: jax.Array, rtol, *, lanes: int, max_beats: int, **settings):
    """:func:`run_beats` to steady state (``steady=True``, no traces) with the members queued
    through ``lanes`` lanes: the first ``lanes`` members start, and a lane whose member has
    finished (converged, failed or out of beats) takes the next waiting member at once, with
    its own fresh loop state. Lock-step blocks make every member of a block wait for the block's
    slowest; here a lane waits only at the end of the queue. A member's computation is the same
    elementwise sequence in any lane, so its result is bit-identical to :func:`run_beats`'s.
    Same arguments (``max_beats`` counts each member's own beats) and result.
    """
    if not settings.get("steady") or settings.get("record"):
        raise ValueError("queued lanes run to steady state without traces (steady=True, record=False)")
    settings = {"scheme": "fixed", "step_tol": DEFAULT_STEP_TOL, "acceleration": "none", "volume_trace": True, **settings}
    n_members = y0.shape[1]
    lanes = min(lanes, n_members)
    take = lambda tree, idx: jax.tree.map(lambda leaf: leaf[..., idx], tree)
    first = jnp.arange(lanes)
    lane0 = _start_carry(y0[:, :lanes], **settings)
    carry0 = {"lane": {**lane0, "n": jnp.zeros((lanes,), jnp.int32), "member": first, "p": take(p, first)},
              "next": jnp.asarray(lanes), "out": _result_start(y0)}

    def cond(c):
        return jnp.any(c["lane"]["active"])

    def body(c):
        lane, member, lane_p = c["lane"], c["lane"]["member"], c["lane"]["p"]
        state = {k: v for k, v in lane.items() if k not in ("n", "member", "p")}
        state = _advance(lane_p, _state_scale(lane_p, y0.dtype), state, rtol, **settings)
        n = lane["n"] + 1
        state["active"] = state["active"] & (n < max_beats)
        finished = ~state["active"] & (member < n_members)
        put = jnp.where(finished, member, n_members)  # out of range: dropped
        out = jax.tree.map(lambda o, v: o.at[..., put].set(v, mode="drop"), c["out"], {k: state[k] for k in c["out"]})
        rank = jnp.cumsum(finished) - 1
        incoming = jnp.where(finished, c["next"] + rank, n_members)
        refill = incoming < n_members
        source = jnp.minimum(incoming, n_members - 1)
        fresh = _start_carry(y0[:, source], **settings)
        state = _select(refill, fresh, state)
        lane_p = _select(refill, take(p, source), lane_p)
        member = jnp.where(refill, incoming, jnp.where(finished, n_members, member))
        lane = {**state, "n": jnp.where(refill, 0, n), "member": member, "p": lane_p}
        return {"lane": lane, "next": c["next"] + jnp.sum(finished), "out": out}

    out = jax.lax.while_loop(cond, body, carry0)["out"]
    return _finish(out, True)


def run_beats_parallel(p: ModelParams, y0: jax.Array, rtol, **settings):
    """:func:`run_beats` laid out over a padded batch (:func:`lvenv.devices.layout`): each device
    runs its own loops on its members (``shard_map``: no device waits for another's beats or
    steps), and on the CPU in blocks of at most :data:`lvenv.devices.CPU_BLOCK` members, one block
    after the other (``lax.map``), each with its own loops. The adaptive scheme to steady state
    on the CPU instead queues a device's members through :func:`lvenv.devices.queue_lanes` lanes
    (:func:`run_beats_queued`) when they fill more than one block, so that no member waits for
    its block's slowest. (The fixed scheme keeps the blocks: queued, its metrics differed from a
    lone run's in the last bits, about 1e-15 relative, which would break bit-identity across
    batch sizes.) A member's result does not depend on its block, lane or device. A batch whose size is not a padded size (e.g. one member under
    ``jax.vmap``) runs as one block. Same arguments and result as :func:`run_beats`.
    """
    n_members = y0.shape[-1]
    used, blocks, block = layout(n_members)
    limit = jnp.asarray(settings.pop("max_beats"))  # an argument of the loops, not a setting to compile for
    run = functools.partial(run_beats, **settings)
    if used * blocks * block != n_members:
        return run(p, y0, rtol, max_beats=limit)

    lanes = queue_lanes(blocks * block) if settings["steady"] and settings.get("scheme") == "adaptive" else None
    queued = lanes is not None and blocks > 1

    def local(p, y0, rtol, limit):
        if queued:
            return run_beats_queued(p, y0, rtol, lanes=lanes, max_beats=limit, **settings)
        if blocks == 1:
            return run(p, y0, rtol, max_beats=limit)
        split = lambda x: jnp.moveaxis(x.reshape(x.shape[:-1] + (blocks, block)), -2, 0)
        out = jax.lax.map(lambda args: run(*args, rtol, max_beats=limit), (jax.tree.map(split, p), split(y0)))
        return jax.tree.map(lambda x: jnp.moveaxis(x, 0, -2).reshape(x.shape[1:-1] + (blocks * block,)), out)

    if used == 1:
        return local(p, y0, rtol, limit)
    last = lambda tree: jax.tree.map(lambda x: PartitionSpec(*([None] * (x.ndim - 1)), "members"), tree)
    out_specs = last(jax.eval_shape(functools.partial(run, max_beats=limit), p, y0, rtol))
    return jax.shard_map(local, mesh=member_mesh(), in_specs=(last(p), last(y0), PartitionSpec(), PartitionSpec()), out_specs=out_specs,
                         check_vma=False)(p, y0, rtol, limit)


run_beats_jit = jax.jit(run_beats_parallel, static_argnames=("steps", "steady", "record", "scheme", "step_tol", "acceleration", "volume_trace"))


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

    ``beats`` counts the beats simulated and ``steps`` the ROS2 steps tried (all beats, rejected
    adaptive steps included). ``metrics`` uses internal units (ml, s, kPa, ml/s); ``status`` holds one of :data:`STATUS`
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
    steps: np.ndarray | int

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
            steps=int(self.steps[i]),
        )


def check_settings(*, steps_per_beat, max_beats, rtol, beats=None, scheme="fixed", step_tol=DEFAULT_STEP_TOL, acceleration="none") -> dict:
    """Validated integration settings (shared by :func:`simulate` and the environment).

    ``steps_per_beat`` an integer in [:data:`MIN_STEPS_PER_BEAT`, :data:`MAX_STEPS_PER_BEAT`];
    ``max_beats`` and ``beats`` (``None`` allowed) integers in [1, :data:`MAX_BEATS`]; ``rtol`` a finite real number in (0, 1); ``scheme`` one of
    :data:`SCHEMES`; ``step_tol`` a real number in [1e-8, 0.1]; ``acceleration`` one of
    :data:`ACCELERATIONS`.
    """
    return {
        "steps_per_beat": integer("steps_per_beat", steps_per_beat, MIN_STEPS_PER_BEAT, MAX_STEPS_PER_BEAT),
        "max_beats": integer("max_beats", max_beats, 1, MAX_BEATS),
        "rtol": real("rtol", rtol, 0.0, 1.0, lo_open=True, hi_open=True),
        "beats": None if beats is None else integer("beats", beats, 1, MAX_BEATS),
        "scheme": choice("scheme", scheme, SCHEMES),
        "step_tol": real("step_tol", step_tol, 1e-8, 0.1),
        "acceleration": choice("acceleration", acceleration, ACCELERATIONS),
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
    scheme: str = "fixed",
    step_tol: float = DEFAULT_STEP_TOL,
    acceleration: str = "none",
    volume_trace: bool = True,
) -> SimulationResult:
    """Simulate one Heart, a sequence of Hearts or a stacked Heart batch.

    Args:
        params: the parameter set(s); every parameter may differ per member, geometry included.
            The members share one LO heart model (``Heart.elements``): the single cell, or a
            multi-element heart (:mod:`lvenv.multielement`; fixed scheme only).
        beats: run exactly this many beats (``converged`` then reports the steady-state test on
            the last two). ``None``: run each member to steady state, at most ``max_beats``.
            Both at most :data:`MAX_BEATS`.
        rtol: steady-state tolerance on the relative beat-to-beat change of EDV, ESV, peak P_lv.
        steps_per_beat: ROS2 steps per cardiac cycle (h = 60 / HR / steps_per_beat s), in
            [:data:`MIN_STEPS_PER_BEAT`, :data:`MAX_STEPS_PER_BEAT`].
        traces: record t, V, P_lv, P_ao of the last beat.
        initial_state: state(s) to start from (shape (9,) or (B, 9); (7 n + 4,) or (B, 7 n + 4)
            for n elements, :func:`lvenv.multielement.flatten`); default: the training
            protocol's (LV at passive equilibrium with Pat, P_c = Pc0, cell at rest). A member
            whose state is not finite ends with status ``nonfinite``; the others are unaffected.
        dtype: ``jnp.float64`` (default) or ``jnp.float32``.
        scheme: ``"fixed"`` (``steps_per_beat`` equal steps, default) or ``"adaptive"``
            (per-member step-size control at the relative tolerance ``step_tol``, about 2.7×
            fewer steps at the same accuracy against Radau; ``steps_per_beat`` unused and
            ``traces=False`` required).
        acceleration: ``"none"`` (default) or ``"anderson"``: the steady state by an accelerated
            iteration of the beat map (:func:`run_beats`); ignored with ``beats``.
        volume_trace: record the 20 volume-trace frames (``V_frame_00`` …); ``False`` leaves
            them NaN and runs about 8 % faster.

    Raises:
        ValueError: a parameter outside its documented range, a setting of the wrong type or
            range, or an initial state of the wrong shape (names field, value and what is allowed).
    """
    settings = check_settings(steps_per_beat=steps_per_beat, max_beats=max_beats, rtol=rtol, beats=beats, scheme=scheme, step_tol=step_tol,
                              acceleration=acceleration)
    steps_per_beat, max_beats, rtol, beats = (settings[k] for k in ("steps_per_beat", "max_beats", "rtol", "beats"))
    if not isinstance(traces, (bool, np.bool_)):
        raise InputError(f"traces = {traces!r} must be True or False")
    if not isinstance(volume_trace, (bool, np.bool_)):
        raise InputError(f"volume_trace = {volume_trace!r} must be True or False")
    if traces and scheme == "adaptive":
        raise InputError("traces = True needs scheme = 'fixed' (the adaptive scheme's steps differ per member); pass traces=False")
    dtype = choice("dtype", jnp.dtype(dtype) if _is_dtype(dtype) else dtype, (jnp.dtype(jnp.float64), jnp.dtype(jnp.float32)))
    heart, single = as_batch(params)
    lo_model.check_scheme(heart.elements, settings["scheme"])
    if heart.elements is not None and dtype != jnp.dtype(jnp.float64):
        raise InputError(f"dtype = {dtype}: a multi-element heart runs in float64 (its series Newton tolerance is {multielement.NEWTON_TOL:g} kPa)")
    p = lo_model.core_params(heart)
    n_members = len(p.v0)
    y0 = lo_model.initial_state(p).T if initial_state is None else _initial_state(initial_state, n_members, lo_model.n_states(p))
    (p_dev, y_dev), _ = shard_members((jax.tree.map(lambda x: np.asarray(x, dtype), p), np.asarray(y0.T, dtype)), n_members)
    out = run_beats_jit(
        p_dev, y_dev, jnp.asarray(rtol, dtype),
        steps=steps_per_beat, max_beats=beats or max_beats, steady=beats is None, record=traces,
        scheme=settings["scheme"], step_tol=settings["step_tol"], acceleration=settings["acceleration"], volume_trace=bool(volume_trace),
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
        steps=np.asarray(out["steps"]),
    )
    return result[0] if single else result


def _is_dtype(value) -> bool:
    try:
        jnp.dtype(value)
    except TypeError:
        return False
    return True


def _initial_state(value, n_members: int, n_states: int) -> np.ndarray:
    """User initial state(s) as an ``(n_members, n_states)`` float array (one row for all members, or one each)."""
    y = real_array("initial_state", value)
    if y.shape not in ((n_states,), (n_members, n_states)):
        raise InputError(f"initial_state has shape {y.shape}; expected ({n_states},) or ({n_members}, {n_states}) (one row per member)")
    return np.broadcast_to(y, (n_members, n_states))
