"""Valve-event detector and per-beat metrics (DESIGN §1.5), accumulated on the fly in ``lax.scan``.

Valve conditions (kPa): mitral open while g_mv = P_at − P_lv > 0, aortic open while
g_ao = P_lv − P_c > 0. An event is a sign change of g between two steps; its time and the volume
there are found by linear interpolation between the steps (error O(h²), sub-step accurate).
Within one beat (onset of the calcium transient at t = 0) the events are taken in cycle order:

    t_mvc  last mitral closing before ejection (t = 0 if closed at onset)   EDV = V(t_mvc)
    t_avo  first aortic opening after t_mvc
    t_avc  last aortic closing before filling                               ESV = V(t_avc)
    t_mvo  first mitral opening after t_avc

i.e. a state machine in which a mitral re-opening before ejection, or an aortic re-opening
before filling, undoes the preceding closing. Two events within one step keep their order.

    IVCT = t_avo − t_mvc,  ET = t_avc − t_avo,  IVRT = t_mvo − t_avc,
    filling_time = T − (t_mvo − t_mvc),  SV = EDV − ESV,  EF = SV / EDV,  CO = SV / T.

Aortic pressures over the beat: systolic max, diastolic min, mean (trapezoidal time average),
pulse = sys − dia; peak P_lv is the beat maximum. Filling pressures: EDP = P_lv(t_mvc), taken
as the interpolated P_at (equal where the mitral valve closes, and smooth there while P_lv rises
steeply; P_lv at the onset if the valve is already closed), and the mean atrial pressure P_at_mean (trapezoidal time
average; the constant ``Pat`` in an open loop). Volume trace: V at the K = :data:`~lvenv.metrics.N_FRAMES`
frame times t_j = j T / K after the onset (``V_frame_00`` …), linearly interpolated between
steps, as a retrospectively ECG-gated cine MRI samples the cycle from the R wave (the onset of
the calcium transient is the electrical activation). A beat without the full event sequence, or
whose "ejection" does not reduce the volume (SV < 0: both valves open at once, which happens
only in degenerate circulations such as R3 → 0 with P_c < P_at), is marked invalid and its
metrics are masked by the caller.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from lvenv.metrics import FRAME_NAMES, N_FRAMES

__all__ = ["Accumulator", "start", "update", "finish", "beat_metrics"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Accumulator:
    """Running record of one beat (per member). Times in s, volumes in ml, pressures in kPa."""

    t: jax.Array
    g_mv: jax.Array
    g_ao: jax.Array
    v: jax.Array
    p_at: jax.Array
    p_ao: jax.Array
    t_mvc: jax.Array
    v_mvc: jax.Array
    p_mvc: jax.Array
    t_avo: jax.Array
    t_avc: jax.Array
    v_avc: jax.Array
    t_mvo: jax.Array
    found: jax.Array  # number of events found so far, 0..4, in cycle order
    p_lv_max: jax.Array
    p_ao_max: jax.Array
    p_ao_min: jax.Array
    p_ao_integral: jax.Array
    p_at_integral: jax.Array
    t0: jax.Array  # the onset
    frame: jax.Array  # T / K, the time between frames
    v_frames: jax.Array  # (K, ...) V at the frame times passed so far (V at the onset before)


def _frame_index(v, frames: int):
    """0, 1, …, frames − 1 along a new leading axis, broadcasting against the members ``v``."""
    return jnp.arange(frames, dtype=v.dtype).reshape((frames,) + (1,) * jnp.ndim(v))


def start(t, v, p_lv, p_at, p_c, p_ao, period, volume_trace: bool = True) -> Accumulator:
    """Open the record at the beat's onset ``t`` of a beat of ``period`` s. A mitral valve
    already closed there closes at t. ``volume_trace`` (static): record the frames; without,
    their metrics are NaN and a step costs no work per frame (the env's fast path)."""
    frames = N_FRAMES if volume_trace else 0
    zero = jnp.zeros_like(v)
    closed = p_at - p_lv < 0.0
    return Accumulator(
        t=t + zero, g_mv=p_at - p_lv, g_ao=p_lv - p_c, v=v, p_at=p_at + zero, p_ao=p_ao,
        t_mvc=t + zero, v_mvc=jnp.where(closed, v, zero), p_mvc=jnp.where(closed, p_lv, zero), t_avo=zero, t_avc=zero, v_avc=zero, t_mvo=zero,
        found=jnp.where(closed, 1, 0).astype(jnp.int32),
        p_lv_max=p_lv, p_ao_max=p_ao, p_ao_min=p_ao, p_ao_integral=zero, p_at_integral=zero,
        t0=t + zero, frame=period / N_FRAMES + zero, v_frames=jnp.broadcast_to(v, (frames, *jnp.shape(v))),
    )


def _crossing(t0, t1, g0, g1, closing: bool):
    """Whether g crosses zero downwards (closing) or upwards (opening), and the fraction of the step."""
    hit = (g0 >= 0.0) & (g1 < 0.0) if closing else (g0 <= 0.0) & (g1 > 0.0)
    denom = jnp.where(hit, g0 - g1, 1.0)
    frac = jnp.clip(jnp.where(hit, g0 / denom, 0.0), 0.0, 1.0)
    return hit, frac


def update(acc: Accumulator, t, v, p_lv, p_at, p_c, p_ao) -> Accumulator:
    """Fold the next step's sample into the beat record."""
    g_mv, g_ao = p_at - p_lv, p_lv - p_c
    dt = t - acc.t
    lerp = lambda a, b, s: a + (b - a) * s

    mvc, f_mvc = _crossing(acc.t, t, acc.g_mv, g_mv, closing=True)
    avo, f_avo = _crossing(acc.t, t, acc.g_ao, g_ao, closing=False)
    avc, f_avc = _crossing(acc.t, t, acc.g_ao, g_ao, closing=True)
    mvo, f_mvo = _crossing(acc.t, t, acc.g_mv, g_mv, closing=False)

    # a valve re-opening before the cycle moves on undoes its closing (chatter, weak beats)
    found = jnp.where(mvo & (acc.found == 1), 0, acc.found)
    found = jnp.where(avo & (found == 3), 2, found)
    take_mvc = mvc & (found == 0)
    found = jnp.where(take_mvc, 1, found)
    take_avo = avo & (found == 1)
    found = jnp.where(take_avo, 2, found)
    take_avc = avc & (found == 2)
    found = jnp.where(take_avc, 3, found)
    take_mvo = mvo & (found == 3)
    found = jnp.where(take_mvo, 4, found)

    # two events inside one step keep their cycle order (interpolation alone need not)
    t_mvc = jnp.where(take_mvc, acc.t + f_mvc * dt, acc.t_mvc)
    t_avo = jnp.where(take_avo, jnp.maximum(acc.t + f_avo * dt, t_mvc), acc.t_avo)
    t_avc = jnp.where(take_avc, jnp.maximum(acc.t + f_avc * dt, t_avo), acc.t_avc)
    t_mvo = jnp.where(take_mvo, jnp.maximum(acc.t + f_mvo * dt, t_avc), acc.t_mvo)

    # K × members work per step, so multiplications only (one division per member)
    t_frames = acc.t0 + acc.frame * _frame_index(v, acc.v_frames.shape[0])
    passed = (acc.t < t_frames) & (t_frames <= t)
    f_frames = (t_frames - acc.t) * (1.0 / jnp.where(dt > 0.0, dt, 1.0))
    return Accumulator(
        t=t, g_mv=g_mv, g_ao=g_ao, v=v, p_at=p_at, p_ao=p_ao,
        t_mvc=t_mvc,
        v_mvc=jnp.where(take_mvc, lerp(acc.v, v, f_mvc), acc.v_mvc),
        p_mvc=jnp.where(take_mvc, lerp(acc.p_at, p_at, f_mvc), acc.p_mvc),  # = P_lv there; P_at is the smooth one
        t_avo=t_avo,
        t_avc=t_avc,
        v_avc=jnp.where(take_avc, lerp(acc.v, v, f_avc), acc.v_avc),
        t_mvo=t_mvo,
        found=found,
        p_lv_max=jnp.maximum(acc.p_lv_max, p_lv),
        p_ao_max=jnp.maximum(acc.p_ao_max, p_ao),
        p_ao_min=jnp.minimum(acc.p_ao_min, p_ao),
        p_ao_integral=acc.p_ao_integral + 0.5 * dt * (acc.p_ao + p_ao),
        p_at_integral=acc.p_at_integral + 0.5 * dt * (acc.p_at + p_at),
        t0=acc.t0, frame=acc.frame,
        v_frames=jnp.where(passed, lerp(acc.v, v, f_frames), acc.v_frames),
    )


def finish(acc: Accumulator, period) -> tuple[dict[str, jax.Array], jax.Array]:
    """Metrics of the beat (internal units, in the order of :data:`lvenv.metrics.METRIC_NAMES`)
    and whether the full valve cycle was found."""
    sv = acc.v_mvc - acc.v_avc
    valid = (acc.found == 4) & (sv >= 0.0)
    metrics = {
        "EF": sv / jnp.where(valid, acc.v_mvc, 1.0),
        "EDV": acc.v_mvc,
        "ESV": acc.v_avc,
        "SV": sv,
        "IVCT": acc.t_avo - acc.t_mvc,
        "ET": acc.t_avc - acc.t_avo,
        "IVRT": acc.t_mvo - acc.t_avc,
        "filling_time": period - (acc.t_mvo - acc.t_mvc),
        "P_lv_peak": acc.p_lv_max,
        "P_ao_sys": acc.p_ao_max,
        "P_ao_dia": acc.p_ao_min,
        "P_ao_pulse": acc.p_ao_max - acc.p_ao_min,
        "P_ao_mean": acc.p_ao_integral / period,
        "CO": sv / period,
        "EDP": acc.p_mvc,
        "P_at_mean": acc.p_at_integral / period,
        **dict(zip(FRAME_NAMES, acc.v_frames if acc.v_frames.shape[0] else [jnp.full_like(sv, jnp.nan)] * N_FRAMES)),
    }
    return metrics, valid


@jax.jit
def beat_metrics(t, v, p_lv, p_at, p_c, p_ao, period) -> tuple[dict[str, jax.Array], jax.Array]:
    """Metrics of one beat given as samples (1-D arrays whose first sample is the beat's onset), e.g. FE traces.

    The same event detection as the LO heart's (:func:`start`, :func:`update`, :func:`finish`)
    folded over the samples; returns the metrics and whether the full valve cycle was found.
    """

    def fold(acc, sample):
        return update(acc, *sample), None

    acc, _ = jax.lax.scan(fold, start(t[0], v[0], p_lv[0], p_at[0], p_c[0], p_ao[0], period), (t[1:], v[1:], p_lv[1:], p_at[1:], p_c[1:], p_ao[1:]))
    return finish(acc, period)
