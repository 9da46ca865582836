"""The coupled wall–circulation time step of an FE beat (kept apart from the LO heart's :mod:`lvenv.coupling`).

Coupled beat (DESIGN §1.2, §4), one time step t → t + dt:

1. Cell predictor: every quadrature point's Land state is advanced over the step with its
   stretch extrapolated at the previous rate (:func:`fe_oracle.quadrature_cells.advance`); the predicted
   S and W populations enter the active tension (:mod:`fe_oracle.mechanics`), in which ζ and
   h(λ) are implicit in the displacement (semi-implicit staggered scheme).
2. Cavity pressure P is the scalar unknown. For a trial P the wall is solved (Newton, MUMPS)
   giving V_FE(P), and the 0-D circulation takes an implicit (backward Euler) step with P,
   giving the target volume V_0D(P) = Vₙ + dt (Q_mv − Q_ao). A safeguarded secant (kept inside
   a sign-change bracket, bisection otherwise, slope carried between steps, a trial pressure
   whose wall solve fails is pulled back towards the last good one; the first trial's P and
   the displacement its Newton solve starts from are extrapolated, quadratically in t, from
   the last :data:`PREDICTOR_POINTS` accepted steps; each later trial starts from the last
   one's displacement moved along the tangent du/dP of
   :meth:`~fe_oracle.mechanics.Solid.pressure_tangent`) drives
   r(P) = V_FE(P) − V_0D(P) below ``volume_tol``. The state carries V_0D, not V_FE, so the
   tolerance never accumulates into a drift of blood volume.
3. Corrector: the cell state is advanced again with the converged stretch λₙ₊₁.

With ``wall_quantiles`` (fractions in [0, 1]) every accepted step also records the
distribution over the wall's quadrature points of the fibre stretch λ, its rate dλ/dt (1/s)
and the active tension Ta (kPa): those quantiles and the mean of each (:meth:`CoupledBeat.wall_sample`),
for comparing the wall with a single LO cell (`scripts/wall_diagnosis.py`).

A failed Newton solve or secant halves dt (``max_cuts`` times at most), then raises
:class:`~fe_oracle.result.OracleDidNotConverge`. Initial state: the LV at passive equilibrium
with Pat (Ta = 0), cells at diastolic rest at their local stretch, P_c = Pc0 (closed loop: the
atrial state starts at Pat too).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

import dolfinx_solver  # noqa: F401  (must precede ufl / mpi4py / dolfinx)
import ufl
from mpi4py import MPI

import lvenv  # noqa: F401
from lvenv import circulation as circ_mod
from lvenv.params import CellParams, Circulation

from fe_oracle import quadrature_cells as cellq
from fe_oracle.activation import activation_times
from fe_oracle.mechanics import interpolate_at_quadrature, quadrature_function
from fe_oracle.passive import inflate

__all__ = ["PREDICTOR_POINTS", "WALL_FIELDS", "CoupledBeat", "zero_d_step"]

#: How many accepted steps (time, pressure and displacement of each) the first trial of a step
#: extrapolates from: 3, quadratic in time. On the N beat ② (h = 10 mm, dt = 5 ms) that takes
#: 21 % fewer Newton iterations than linear (2 points); cubic (4) takes more than quadratic.
PREDICTOR_POINTS = 3
#: The wall quantities :meth:`CoupledBeat.wall_sample` records: fibre stretch λ, its rate dλ/dt
#: (1/s) and the active tension Ta (kPa).
WALL_FIELDS = ("lam", "rate", "Ta")
_S = lvenv.cell.STATE_NAMES.index("S")
_W = lvenv.cell.STATE_NAMES.index("W")


@jax.jit
def zero_d_step(p_lv, v, p_c, p_at, dt, circ: Circulation):
    """Backward-Euler step of the circulation for a given LV pressure: (V_0D, P_c, P_at, P_ao)."""

    def unknowns_residual(x):
        q = circ_mod.flows(p_lv, x[0], x[1], circ)
        _, d_pc, d_pat = circ_mod.windkessel_derivatives(q, circ)
        return jnp.stack([x[0] - p_c - dt * d_pc, x[1] - p_at - dt * d_pat])

    def newton(_, x):
        r = unknowns_residual(x)
        jac = jax.jacfwd(unknowns_residual)(x)
        return x - jnp.linalg.solve(jac, r)

    x = jax.lax.fori_loop(0, 12, newton, jnp.stack([p_c, p_at]))
    q = circ_mod.flows(p_lv, x[0], x[1], circ)
    d_v, _, _ = circ_mod.windkessel_derivatives(q, circ)
    return v + dt * d_v, x[0], x[1], circ_mod.aortic_pressure(x[0], q, circ)


class CoupledBeat:
    """Mutable state of one coupled FE run on an :class:`~fe_oracle.dolfinx_backend.LVModel`."""

    def __init__(self, model, circ: Circulation, cell: CellParams, *, dt, volume_tol, max_cuts, n_sub, log, synchronous=False, wall_quantiles=None):
        self.m, self.circ, self.cell = model, circ, cell
        self.wall_quantiles = None if wall_quantiles is None else np.asarray(wall_quantiles, float)
        self.wall: list[np.ndarray] = []
        self.dt_nominal, self.volume_tol, self.max_cuts, self.n_sub, self.log = dt, volume_tol, max_cuts, n_sub, log
        mesh = model.tm.mesh
        F = ufl.Identity(3) + ufl.grad(model.solid.u)
        f0 = model.fibres.f0
        self._lam_q = quadrature_function(mesh)
        self._lam_expr = ufl.sqrt(ufl.inner(F * f0, F * f0))
        self.period = float(circ_mod.beat_period(circ))
        self.t_act, _, self.foci = activation_times(model.tm, model.geometry, model.fibres)
        if synchronous:
            self.t_act = np.zeros_like(self.t_act)

    def stretch(self) -> np.ndarray:
        return interpolate_at_quadrature(self._lam_q, self._lam_expr).copy()

    def set_cell_inputs(self, y, lam_prev, dt):
        a = self.m.active
        a.S.x.array[:] = y[_S]
        a.W.x.array[:] = y[_W]
        a.zeta_s.x.array[:] = self.y[lvenv.cell.STATE_NAMES.index("zeta_s")]
        a.zeta_w.x.array[:] = self.y[lvenv.cell.STATE_NAMES.index("zeta_w")]
        a.lam_prev.x.array[:] = lam_prev
        a.dt.value = dt

    def initialise(self):
        circ = self.circ
        p_at0 = float(circ.Pat)
        a = self.m.active
        a.S.x.array[:] = 0.0
        a.W.x.array[:] = 0.0
        inflate(self.m.solid, np.array([0.0, p_at0]) if p_at0 > 0 else np.array([0.0]), log=self.log)
        self.lam = self.stretch()
        self.y = np.asarray(cellq.rest_states(self.lam, self.cell))
        self.rate = np.zeros_like(self.lam)
        self.t = 0.0
        self.v0d = self.m.solid.volume()
        self.p_lv = p_at0
        self.history = [(0.0, p_at0, self.m.solid.u.x.array.copy())]
        self.p_c, self.p_at = float(circ.Pc0), p_at0
        self.slope = None
        q = circ_mod.flows(self.p_lv, self.p_c, self.p_at, circ)
        self.p_ao = float(circ_mod.aortic_pressure(self.p_c, q, circ))
        self.lam_min, self.lam_max = self._global_range(self.lam)
        self.lam_p01, self.lam_p99 = np.percentile(self.lam, [1.0, 99.0])
        self._record_wall()

    def wall_sample(self) -> np.ndarray:
        """The wall now: for each of :data:`WALL_FIELDS`, its quantiles at ``wall_quantiles``
        over the quadrature points and then its mean; shape (3, len(wall_quantiles) + 1).
        Serial only (a rank sees its own points)."""
        fields = (self.lam, self.rate, cellq.tension(self.y, self.lam, self.cell))
        return np.array([np.concatenate([np.quantile(f, self.wall_quantiles), [f.mean()]]) for f in fields])

    def _record_wall(self):
        if self.wall_quantiles is not None:
            self.wall.append(self.wall_sample())

    def _global_range(self, values) -> tuple[float, float]:
        comm = self.m.solid.comm
        lo = float(values.min()) if values.size else math.inf
        hi = float(values.max()) if values.size else -math.inf
        return comm.allreduce(lo, op=MPI.MIN), comm.allreduce(hi, op=MPI.MAX)

    def _advance_cells(self, lam1, dt):
        return np.asarray(cellq.advance(self.y, self.lam, lam1, self.t, dt, self.t_act, self.period, self.cell, n_sub=self.n_sub))

    def _evaluate(self, p, dt):
        """r(P) = V_FE(P) − V_0D(P), or None if the wall solve failed."""
        report = self.m.solid.solve(p)
        entry = {"t": self.t + dt, "dt": dt, "pressure": p, "converged": report.converged, "reason": report.reason, "iterations": report.iterations, "residual": report.residual}
        self.log.append(entry)
        self.last_residual = report.residual
        if not report.converged:
            return None
        v_fe = self.m.solid.volume()
        v0d, p_c, p_at, p_ao = (float(x) for x in zero_d_step(p, self.v0d, self.p_c, self.p_at, dt, self.circ))
        entry["volume_mismatch"] = v_fe - v0d
        return v_fe - v0d, (v_fe, v0d, p_c, p_at, p_ao)

    def _evaluate_from(self, u_guess, p, dt):
        """:meth:`_evaluate` with the wall solve started from ``u_guess``."""
        self.m.solid.u.x.array[:] = u_guess
        return self._evaluate(p, dt)

    def _extrapolated(self, dt):
        """(P in kPa, u in mm) at t + dt on the polynomial in t through the accepted steps of
        ``history`` (Lagrange form)."""
        times = [t for t, _, _ in self.history]
        t1 = self.t + dt
        weights = [math.prod((t1 - tk) / (tj - tk) for k, tk in enumerate(times) if k != j) for j, tj in enumerate(times)]
        p = sum(w * p for w, (_, p, _) in zip(weights, self.history))
        u = sum(w * u for w, (_, _, u) in zip(weights, self.history))
        return float(p), u

    def _pressure_solve(self, p, dt, max_evals=12):
        """Safeguarded secant on r(P) from the trial pressure ``p``; returns the accepted (P, outputs) or None."""
        out = self._evaluate(p, dt)
        if out is None:
            p = self.p_lv
            self.m.solid.u.x.array[:] = self.u_now
            out = self._evaluate(p, dt)
            if out is None:
                return None
        r, data = out
        lo, hi = -math.inf, math.inf
        slope = self.slope
        if slope is None:
            dp = 0.01
            out2 = self._evaluate(p + dp, dt)
            if out2 is None:
                return None
            slope = max((out2[0] - r) / dp, 1e-3)
            p, (r, data) = p + dp, out2
        for _ in range(max_evals):
            if abs(r) < self.volume_tol:
                self.slope = slope
                return p, data
            if r > 0:
                hi = min(hi, p)
            else:
                lo = max(lo, p)
            step = -r / slope
            step = max(min(step, 5.0), -5.0)
            p_new = p + step
            if not (lo < p_new < hi):
                p_new = 0.5 * (lo + hi) if math.isfinite(lo) and math.isfinite(hi) else (p + step * 0.5)
            tangent = self.m.solid.pressure_tangent()
            u_p = self.m.solid.u.x.array.copy()
            out = self._evaluate_from(u_p + tangent * (p_new - p), p_new, dt)
            for _ in range(3):  # a trial pressure too far for Newton: move back towards p
                if out is not None:
                    break
                p_new = p + 0.25 * (p_new - p)
                out = self._evaluate_from(u_p + tangent * (p_new - p), p_new, dt)
            if out is None:
                return None
            r_new, data_new = out
            if p_new != p:
                secant = (r_new - r) / (p_new - p)
                if secant > 1e-6:
                    slope = secant
            p, r, data = p_new, r_new, data_new
        return None

    def step(self, dt) -> bool:
        """Try one step of size dt; on success update the state and return True."""
        solid = self.m.solid
        self.u_now = solid.u.x.array.copy()
        y_pred = self._advance_cells(self.lam + self.rate * dt, dt)
        self.set_cell_inputs(y_pred, self.lam, dt)
        p_guess, solid.u.x.array[:] = self._extrapolated(dt)
        accepted = self._pressure_solve(p_guess, dt)
        if accepted is None:
            solid.u.x.array[:] = self.u_now
            return False
        p, (v_fe, v0d, p_c, p_at, p_ao) = accepted
        lam1 = self.stretch()
        self.y = self._advance_cells(lam1, dt)
        self.rate = (lam1 - self.lam) / dt
        self.lam = lam1
        lo, hi = self._global_range(lam1)
        self.lam_min, self.lam_max = min(self.lam_min, lo), max(self.lam_max, hi)
        p01, p99 = np.percentile(lam1, [1.0, 99.0])
        self.lam_p01, self.lam_p99 = min(self.lam_p01, p01), max(self.lam_p99, p99)
        self.t += dt
        self.p_lv = p
        self.history = (self.history + [(self.t, p, solid.u.x.array.copy())])[-PREDICTOR_POINTS:]
        self.v0d, self.p_c, self.p_at, self.p_ao = v0d, p_c, p_at, p_ao
        self.v_fe = v_fe
        self._record_wall()
        return True
