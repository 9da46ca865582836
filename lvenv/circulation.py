"""Circulation: diode valves, three-element Windkessel and atrium (DESIGN §1.2).

::

    LV ──mitral Rmv── atrium (P_at)        Q_mv = max(P_at − P_lv, 0) / Rmv
    LV ──aortic R1── P_ao ──R2── C (P_c)   Q_ao = max(P_lv − P_c, 0) / (R1 + R2)
    C ──R3── venous side                   Q_per = (P_c − P_ven) / R3

    dV/dt    = Q_mv − Q_ao                                     (ml/s)
    dP_c/dt  = (Q_ao − Q_per) / C                              (kPa/s)
    dP_at/dt = closed · (Q_per − Q_mv) / Cat                   (kPa/s)
    P_ven    = closed · P_at ;   P_ao = P_c + R2 Q_ao          (kPa)

Open loop (``closed_loop = 0``): the atrium holds the constant ``Pat`` and the venous side is at
0 kPa (training runs, Table 2). Closed loop (``closed_loop = 1``, ours): R3 drains into the atrial
capacitor Cat, which fills the LV; total volume V + C P_c + Cat P_at is conserved.

Valves are ideal diodes with resistance: no backflow. Both the LO heart and the FE oracle call
these functions, so the two see exactly the same circulation.
"""

from __future__ import annotations

import jax.numpy as jnp

from lvenv.params import Circulation

__all__ = ["Flows", "flows", "valves_open", "open_fractions", "windkessel_derivatives", "jacobian", "aortic_pressure", "total_volume", "beat_period"]


class Flows(tuple):
    """``(Q_mv, Q_ao, Q_per)`` in ml/s."""

    __slots__ = ()

    @property
    def mitral(self):
        return self[0]

    @property
    def aortic(self):
        return self[1]

    @property
    def peripheral(self):
        return self[2]


def beat_period(circ: Circulation):
    """Cardiac cycle length T = 60 / HR (s)."""
    return 60.0 / circ.HR


def atrial_pressure(p_at_state, circ: Circulation):
    """Atrial pressure (kPa): the state in a closed loop, the constant ``Pat`` in an open one."""
    return jnp.where(circ.closed_loop > 0.5, p_at_state, circ.Pat)


def _valve_drops(p_lv, p_c, p_at_state, circ: Circulation):
    """(P_at − P_lv, P_lv − P_c) in kPa: positive where the mitral, the aortic valve is open."""
    return atrial_pressure(p_at_state, circ) - p_lv, p_lv - p_c


def valves_open(p_lv, p_c, p_at_state, circ: Circulation):
    """(mitral open, aortic open): P_at > P_lv and P_lv > P_c."""
    g_mv, g_ao = _valve_drops(p_lv, p_c, p_at_state, circ)
    return g_mv > 0.0, g_ao > 0.0


def open_fractions(start, end, circ: Circulation):
    """(mitral, aortic): the fraction of a step each valve is open, given the pressures
    (P_lv, P_c, P_at state; kPa) at the step's start and predicted at its end, linear in between.

    1 open throughout, 0 shut throughout; for a valve that opens or shuts within the step, the
    part of the step on the open side of the pressure line's zero. Continuous in both ends.
    """
    def fraction(g0, g1):
        span = jnp.abs(g0) + jnp.abs(g1)
        return (jnp.maximum(g0, 0.0) + jnp.maximum(g1, 0.0)) / jnp.where(span > 0.0, span, 1.0)

    return tuple(fraction(g0, g1) for g0, g1 in zip(_valve_drops(*start, circ), _valve_drops(*end, circ)))


def flows(p_lv, p_c, p_at_state, circ: Circulation) -> Flows:
    """Mitral, aortic and peripheral flows (ml/s) for LV, capacitor and atrial-state pressures (kPa)."""
    p_at = atrial_pressure(p_at_state, circ)
    q_mv = jnp.maximum(p_at - p_lv, 0.0) / circ.Rmv
    q_ao = jnp.maximum(p_lv - p_c, 0.0) / (circ.R1 + circ.R2)
    p_ven = circ.closed_loop * p_at
    q_per = (p_c - p_ven) / circ.R3
    return Flows((q_mv, q_ao, q_per))


def windkessel_derivatives(q: Flows, circ: Circulation):
    """``(dV/dt, dP_c/dt, dP_at/dt)`` in ml/s, kPa/s, kPa/s."""
    d_v = q.mitral - q.aortic
    d_pc = (q.aortic - q.peripheral) / circ.C
    d_pat = circ.closed_loop * (q.peripheral - q.mitral) / circ.Cat
    return d_v, d_pc, d_pat


def jacobian(mitral_open, aortic_open, circ: Circulation) -> list[list]:
    """∂(dV/dt, dP_c/dt, dP_at/dt) / ∂(P_lv, P_c, P_at state) for the given valve states (3 × 3).

    An open valve conducts g_mv = 1/Rmv, g_ao = 1/(R1 + R2); a shut one not at all. The states may
    also be fractions in [0, 1] (:func:`open_fractions`), which scale the conductances. Units:
    ml/(s·kPa) in the first row, 1/s in the others.
    """
    g_mv = mitral_open * (1.0 / circ.Rmv)
    g_ao = aortic_open * (1.0 / (circ.R1 + circ.R2))
    closed = circ.closed_loop
    return [
        [-(g_mv + g_ao), g_ao, closed * g_mv],
        [g_ao / circ.C, -(g_ao + 1.0 / circ.R3) / circ.C, closed / (circ.R3 * circ.C)],
        [closed * g_mv / circ.Cat, closed / (circ.R3 * circ.Cat), -closed * (closed / circ.R3 + g_mv) / circ.Cat],
    ]


def aortic_pressure(p_c, q: Flows, circ: Circulation):
    """Central aortic pressure P_ao = P_c + R2 Q_ao (kPa)."""
    return p_c + circ.R2 * q.aortic


def total_volume(v, p_c, p_at_state, circ: Circulation):
    """Stressed blood volume V + C P_c + Cat P_at (ml), conserved in the closed loop."""
    return v + circ.C * p_c + circ.Cat * p_at_state
