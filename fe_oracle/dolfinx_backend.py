"""The DOLFINx backend of :func:`fe_oracle.run`: passive inflation and coupled beats.

Coupled beat (DESIGN §1.2, §4), one time step t → t + dt:

1. Cell predictor: every quadrature point's Land state is advanced over the step with its
   stretch extrapolated at the previous rate (:func:`fe_oracle.active.advance`); the predicted
   S and W populations enter the active tension (:mod:`fe_oracle.mechanics`), in which ζ and
   h(λ) are implicit in the displacement (semi-implicit staggered scheme).
2. Cavity pressure P is the scalar unknown. For a trial P the wall is solved (Newton, MUMPS)
   giving V_FE(P), and the 0-D circulation takes an implicit (backward Euler) step with P,
   giving the target volume V_0D(P) = Vₙ + dt (Q_mv − Q_ao). A safeguarded secant (kept inside
   a sign-change bracket, bisection otherwise, slope carried between steps, a trial pressure
   whose wall solve fails is pulled back towards the last good one) drives
   r(P) = V_FE(P) − V_0D(P) below ``volume_tol``. The state carries V_0D, not V_FE, so the
   tolerance never accumulates into a drift of blood volume.
3. Corrector: the cell state is advanced again with the converged stretch λₙ₊₁.

A failed Newton solve or secant halves dt (``max_cuts`` times at most), then raises
:class:`~fe_oracle.result.OracleDidNotConverge`. Initial state: the LV at passive equilibrium
with Pat (Ta = 0), cells at diastolic rest at their local stretch, P_c = Pc0 (closed loop: the
atrial state starts at Pat too).
"""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

import dolfinx_solver  # noqa: F401  (must precede ufl / mpi4py / dolfinx)
import ufl
from mpi4py import MPI

import lvenv  # noqa: F401
from lvenv import circulation as circ_mod
from lvenv.geometry import Geometry, cavity_volume
from lvenv.params import CellParams, Circulation

from fe_oracle import active as cellq
from fe_oracle.activation import activation_times
from fe_oracle.fibres import fibre_field
from fe_oracle.material import Guccione
from fe_oracle.mechanics import ActiveTension, Solid, interpolate_at_quadrature, lv_dirichlet, quadrature_function
from fe_oracle.mesh import lv_mesh
from fe_oracle.passive import inflate
from fe_oracle.result import OracleDidNotConverge

__all__ = ["run_passive", "run_beat", "LVModel"]

_S = lvenv.cell.STATE_NAMES.index("S")
_W = lvenv.cell.STATE_NAMES.index("W")


class LVModel:
    """Mesh, fibres, activation times and the active solid of one geometry."""

    def __init__(self, geometry: Geometry, mesh_size: float, material: Guccione, cell: CellParams | None, *, newton_max_it: int = 25):
        t0 = time.perf_counter()
        self.geometry = geometry
        self.tm = lv_mesh(geometry, mesh_size)
        self.fibres = fibre_field(self.tm)
        self.active = ActiveTension(self.tm.mesh, cellq.tension_coefficients(cell)) if cell is not None else None
        self.solid = Solid(self.tm, material, lv_dirichlet, fibres=self.fibres.vectors(), active=self.active, prefix=f"lv{id(self)}")
        self.solid.set_max_iterations(newton_max_it)
        self.setup_s = time.perf_counter() - t0

    def mesh_info(self) -> dict:
        mesh = self.tm.mesh
        return {
            "cells": int(mesh.topology.index_map(3).size_global),
            "dofs": int(self.solid.space.dofmap.index_map.size_global * 3),
            "V0_analytic_ml": cavity_volume(self.geometry),
            "V0_mesh_ml": self.solid.volume(),
        }


def _bar(comm, show: bool, total: float, desc: str, unit: str):
    return tqdm(total=total, desc=desc, unit=unit, disable=not (show and comm.rank == 0), bar_format="{l_bar}{bar}| {n:.3g}/{total:.3g} {unit} [{elapsed}<{remaining}{postfix}]")


def run_passive(geometry, material, mesh_size, pressures, *, max_cuts=6, newton_max_it=25, progress=False):
    """Passive inflation (no active tension). Returns (traces, metadata, log)."""
    t0 = time.perf_counter()
    model = LVModel(geometry, mesh_size, material, None, newton_max_it=newton_max_it)
    info = model.mesh_info()
    log: list = []
    with _bar(model.solid.comm, progress, float(pressures[-1]), "FE passive inflation", "kPa") as bar:
        volumes = inflate(model.solid, pressures, max_cuts=max_cuts, log=log, bar=bar)
    n = len(pressures)
    traces = {"t": np.asarray(pressures) / pressures[-1], "V": volumes, "P_lv": np.asarray(pressures, float), "P_ao": np.full(n, np.nan)}
    meta = dict(info, wall_s=time.perf_counter() - t0, setup_s=model.setup_s, newton_iterations=sum(r["iterations"] for r in log), solves=len(log))
    return traces, meta, log


@jax.jit
def _zero_d_step(p_lv, v, p_c, p_at, dt, circ: Circulation):
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


class _Beat:
    """Mutable state of a coupled run (kept out of the public API)."""

    def __init__(self, model: LVModel, circ: Circulation, cell: CellParams, *, dt, volume_tol, max_cuts, n_sub, log):
        self.m, self.circ, self.cell = model, circ, cell
        self.dt_nominal, self.volume_tol, self.max_cuts, self.n_sub, self.log = dt, volume_tol, max_cuts, n_sub, log
        mesh = model.tm.mesh
        F = ufl.Identity(3) + ufl.grad(model.solid.u)
        f0 = model.fibres.f0
        self._lam_q = quadrature_function(mesh)
        self._lam_expr = ufl.sqrt(ufl.inner(F * f0, F * f0))
        self.period = float(circ_mod.beat_period(circ))
        self.t_act, _, self.foci = activation_times(model.tm, model.geometry, model.fibres)

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
        self.p_lv, self.p_lv_prev = p_at0, p_at0
        self.p_c, self.p_at = float(circ.Pc0), p_at0
        self.u_prev = self.m.solid.u.x.array.copy()
        self.dt_prev = self.dt_nominal
        self.slope = None
        q = circ_mod.flows(self.p_lv, self.p_c, self.p_at, circ)
        self.p_ao = float(circ_mod.aortic_pressure(self.p_c, q, circ))
        self.lam_min, self.lam_max = self._global_range(self.lam)
        self.lam_p01, self.lam_p99 = np.percentile(self.lam, [1.0, 99.0])

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
        v0d, p_c, p_at, p_ao = (float(x) for x in _zero_d_step(p, self.v0d, self.p_c, self.p_at, dt, self.circ))
        entry["volume_mismatch"] = v_fe - v0d
        return v_fe - v0d, (v_fe, v0d, p_c, p_at, p_ao)

    def _pressure_solve(self, dt, max_evals=12):
        """Safeguarded secant on r(P); returns the accepted (P, outputs) or None."""
        p = self.p_lv + (self.p_lv - self.p_lv_prev) * dt / self.dt_prev
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
            out = self._evaluate(p_new, dt)
            for _ in range(3):  # a trial pressure too far for Newton: move back towards p
                if out is not None:
                    break
                p_new = p + 0.25 * (p_new - p)
                out = self._evaluate(p_new, dt)
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
        solid.u.x.array[:] = self.u_now + (self.u_now - self.u_prev) * dt / self.dt_prev
        accepted = self._pressure_solve(dt)
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
        self.p_lv_prev, self.p_lv = self.p_lv, p
        self.v0d, self.p_c, self.p_at, self.p_ao = v0d, p_c, p_at, p_ao
        self.v_fe = v_fe
        self.u_prev = self.u_now
        self.dt_prev = dt
        return True


def run_beat(geometry, circ, cell, material, mesh_size, dt, beats, *, duration=None, volume_tol=None, max_cuts=4, newton_max_it=25, n_sub=5, progress=False):
    """Coupled active run over ``beats`` beats (or ``duration`` s). Returns (traces, metadata, log).

    Metadata ``stretch_min``/``stretch_max``: extremes of the fibre stretch over all quadrature
    points and steps; ``stretch_p01``/``stretch_p99``: extremes over steps of its 1st and 99th
    percentiles (percentiles per rank under MPI).
    """
    t0 = time.perf_counter()
    model = LVModel(geometry, mesh_size, material, cell, newton_max_it=newton_max_it)
    info = model.mesh_info()
    log: list = []
    tol = 1e-4 * info["V0_analytic_ml"] if volume_tol is None else volume_tol
    beat = _Beat(model, circ, cell, dt=dt, volume_tol=tol, max_cuts=max_cuts, n_sub=n_sub, log=log)
    beat.initialise()
    t_end = beats * beat.period if duration is None else duration
    rows = [(0.0, beat.v0d, beat.p_lv, beat.p_ao, beat.p_c, beat.p_at)]
    cuts_total = 0
    with _bar(model.solid.comm, progress, t_end, "FE beat", "s") as bar:
        while beat.t < t_end - 1e-9:
            h = min(dt, t_end - beat.t)
            cuts = 0
            while not beat.step(h):
                cuts += 1
                cuts_total += 1
                if cuts > max_cuts:
                    raise OracleDidNotConverge(
                        f"coupled step failed after {max_cuts} halvings of dt (last dt {h:.3g} s)", time=beat.t, residual=beat.last_residual, log=log
                    )
                h *= 0.5
            rows.append((beat.t, beat.v0d, beat.p_lv, beat.p_ao, beat.p_c, beat.p_at))
            bar.update(h)
            bar.set_postfix_str(f"P_lv {beat.p_lv:.2f} kPa, V {beat.v0d:.1f} ml", refresh=False)
    arr = np.array(rows)
    traces = {"t": arr[:, 0], "V": arr[:, 1], "P_lv": arr[:, 2], "P_ao": arr[:, 3], "P_c": arr[:, 4], "P_at": arr[:, 5]}
    meta = dict(
        info,
        wall_s=time.perf_counter() - t0,
        setup_s=model.setup_s,
        steps=len(rows) - 1,
        step_cuts=cuts_total,
        fe_solves=len(log),
        newton_iterations=sum(r["iterations"] for r in log),
        quadrature_points=int(model.solid.comm.allreduce(beat.lam.size)),
        stretch_min=beat.lam_min,
        stretch_max=beat.lam_max,
        stretch_p01=beat._global_range(np.array([beat.lam_p01]))[0],
        stretch_p99=beat._global_range(np.array([beat.lam_p99]))[1],
        activation_time_max_s=beat._global_range(beat.t_act)[1],
        period_s=beat.period,
        volume_tol_ml=tol,
    )
    return traces, meta, log
