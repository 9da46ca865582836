"""The DOLFINx backend of :func:`fe_oracle.run`: passive inflation Ⓟ and coupled beats.

:class:`LVModel` builds one geometry's mesh, fibres and active solid; :func:`run_passive`
inflates it, :func:`run_beat` runs the coupled wall–circulation beat of
:mod:`fe_oracle.coupled_beat` on it.
"""

from __future__ import annotations

import time

import numpy as np
from tqdm.auto import tqdm

import dolfinx_solver  # noqa: F401  (must precede ufl / mpi4py / dolfinx)

import lvenv  # noqa: F401
from lvenv.geometry import Geometry, cavity_volume
from lvenv.params import CellParams

from fe_oracle import quadrature_cells as cellq
from fe_oracle.coupled_beat import CoupledBeat
from fe_oracle.fibres import fibre_field
from fe_oracle.material import Guccione
from fe_oracle.mechanics import ActiveTension, Solid, lv_dirichlet
from fe_oracle.mesh import lv_mesh
from fe_oracle.passive import inflate
from fe_oracle.result import OracleDidNotConverge

__all__ = ["run_passive", "run_beat", "LVModel"]


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
    """Passive inflation (no active tension) through the sorted ``pressures`` (kPa): the branch
    ≥ 0 by inflation from the unloaded state, the branch < 0 (if any) by deflation from it.
    Returns (traces, metadata, log); the traces are sorted by pressure."""
    t0 = time.perf_counter()
    model = LVModel(geometry, mesh_size, material, None, newton_max_it=newton_max_it)
    info = model.mesh_info()
    log: list = []
    pressures = np.asarray(pressures, float)
    up, down = pressures[pressures >= 0.0], np.concatenate([[0.0], pressures[pressures < 0.0][::-1]])
    with _bar(model.solid.comm, progress, float(up[-1] - down[-1]), "FE passive inflation", "kPa") as bar:
        volumes_up = inflate(model.solid, up, max_cuts=max_cuts, log=log, bar=bar)
        volumes_down = np.empty(0)
        if len(down) > 1:
            model.solid.u.x.array[:] = 0.0
            volumes_down = inflate(model.solid, down, max_cuts=max_cuts, log=log, bar=bar)[1:][::-1]
    volumes = np.concatenate([volumes_down, volumes_up])
    traces = {"t": pressures / pressures[-1], "V": volumes, "P_lv": pressures, "P_ao": np.full(len(pressures), np.nan)}
    meta = dict(info, wall_s=time.perf_counter() - t0, setup_s=model.setup_s, newton_iterations=sum(r["iterations"] for r in log), solves=len(log))
    return traces, meta, log


def run_beat(geometry, circ, cell, material, mesh_size, dt, beats, *, duration=None, volume_tol=None, max_cuts=4, newton_max_it=25, n_sub=5, progress=False,
             synchronous=False, wall_quantiles=None):
    """Coupled active run over ``beats`` beats (or ``duration`` s). Returns (traces, metadata, log).
    ``synchronous``: every point activates at t = 0 instead of at its eikonal arrival time.
    ``wall_quantiles`` (fractions; serial runs only): the traces gain ``wall``, shape
    (samples, 3, len(wall_quantiles) + 1): per sample the quantiles and the mean over the
    quadrature points of :data:`fe_oracle.coupled_beat.WALL_FIELDS`, and the metadata
    ``activation_quantiles_s``, the same quantiles of the points' activation times.

    Metadata ``stretch_min``/``stretch_max``: extremes of the fibre stretch over all quadrature
    points and steps; ``stretch_p01``/``stretch_p99``: extremes over steps of its 1st and 99th
    percentiles (percentiles per rank under MPI).
    """
    t0 = time.perf_counter()
    model = LVModel(geometry, mesh_size, material, cell, newton_max_it=newton_max_it)
    info = model.mesh_info()
    log: list = []
    tol = 1e-4 * info["V0_analytic_ml"] if volume_tol is None else volume_tol
    if wall_quantiles is not None and model.solid.comm.size > 1:
        raise ValueError("wall_quantiles needs a serial run (quantiles over every rank's points are not gathered)")
    beat = CoupledBeat(model, circ, cell, dt=dt, volume_tol=tol, max_cuts=max_cuts, n_sub=n_sub, log=log, synchronous=synchronous, wall_quantiles=wall_quantiles)
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
    wall = {}
    if wall_quantiles is not None:
        traces["wall"] = np.array(beat.wall)
        wall = {"activation_quantiles_s": np.quantile(beat.t_act, wall_quantiles).tolist()}
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
        **wall,
    )
    return traces, meta, log
