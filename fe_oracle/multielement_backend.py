"""The ``multielement`` backend of :func:`fe_oracle.run`: the §1.4 multi-element LO heart (no DOLFINx).

A cheap stand-in for the 3-D oracle (DESIGN §4) for tests and the Table-4-style study: the
parallel or series arrangement of ``n_elements`` Land cell units of :mod:`lvenv.multielement`
answers the same interface and returns the same :class:`~fe_oracle.result.OracleResult` as the
DOLFINx backend:

* coupled beats: traces ``t`` (s), ``V`` (ml), ``P_lv``, ``P_ao``, ``P_c``, ``P_at`` (kPa) over
  ``beats`` beats from the training-protocol state (every element at passive equilibrium with
  Pat, P_c = Pc0, cells at rest). ``dt`` is rounded down to T / ceil(T/dt) so that every beat
  ends on a step (T = 60/HR); ``duration`` keeps the samples at t ≤ ``duration``. The default
  ``dt`` is 1 ms (1000 ROS2 steps per beat, :data:`fe_oracle.api.DEFAULT_DT`): at 5 ms EF is
  still within 0.001 but IVCT and IVRT are off by 10–17 ms (condition ②);
* passive inflation Ⓟ: ``t`` = load parameter 0 → 1, ``V``, ``P_lv`` = applied pressure,
  ``P_ao`` NaN; the passive heart (Ta = 0) is solved in closed form / by a scalar root per
  element (:func:`lvenv.multielement.passive_volume`).

Metadata: the DOLFINx keys that describe this model too — ``V0_analytic_ml``, ``wall_s``,
``period_s``, ``steps``, ``step_cuts`` (always 0), ``newton_iterations`` (the series
equal-pressure Newton; 0 in parallel and in passive inflation, whose elements are independent
scalar roots), ``stretch_min``/``stretch_max`` (over elements and steps),
``activation_time_max_s`` (0: every element starts at the onset), ``solves`` (passive load
points) and, from :func:`fe_oracle.run`, ``backend``, ``case``, ``key``, ``code_version``,
``total_s``, ``dt_s``, ``beats`` and ``mesh_size_mm`` (``None``: no mesh). The mesh and quadrature keys of
:data:`FE_ONLY_METADATA` are absent. Added: :data:`MULTIELEMENT_METADATA`.

``lo=None`` takes the paper's trained LO values for the N and HF geometries
(:data:`lvenv.presets.N_LO`, :data:`~lvenv.presets.HF_LO`), :class:`~lvenv.params.LOParams`
defaults for any other geometry. A solver failure (non-finite state, equal-pressure Newton not
converged) raises :class:`~fe_oracle.result.OracleDidNotConverge`; a beat without a full valve
cycle is returned as it is, as the DOLFINx backend does.
"""

from __future__ import annotations

import math
import time

import numpy as np

import lvenv  # noqa: F401  (float64)
from lvenv import coupling, multielement, presets
from lvenv.circulation import beat_period
from lvenv.geometry import Geometry, cavity_volume
from lvenv.params import Arrangement, CellParams, Circulation, Heart, LOParams

from fe_oracle.result import OracleDidNotConverge

__all__ = ["FE_ONLY_METADATA", "MULTIELEMENT_METADATA", "NEWTON_TOL", "arrangement", "default_lo", "run_passive", "run_beat"]

#: Metadata keys of the DOLFINx backend with no meaning here (mesh, quadrature points, FE solves).
FE_ONLY_METADATA = ("cells", "dofs", "V0_mesh_ml", "setup_s", "fe_solves", "quadrature_points", "stretch_p01", "stretch_p99", "volume_tol_ml")
#: Metadata keys only this backend has.
MULTIELEMENT_METADATA = ("arrangement", "n_elements", "spread", "lo", "constraint_residual_kPa")
#: Series equal-pressure tolerance max_ξ abs(P_ξ − P) (kPa).
NEWTON_TOL = 1e-10


def arrangement(kind, n_elements) -> Arrangement:
    """Validated :class:`~lvenv.params.Arrangement` (``None``: parallel, 256 elements)."""
    return Arrangement("parallel" if kind is None else kind, 256 if n_elements is None else n_elements)


def default_lo(geometry: Geometry) -> LOParams:
    """The paper's trained LO parameters of a preset geometry (N, HF), else the defaults."""
    trained = {presets.N_UNLOADED: presets.N_LO, presets.HF_UNLOADED: presets.HF_LO}
    return trained.get(geometry, LOParams())


def _metadata(geometry: Geometry, arr: Arrangement, lo: LOParams, t0: float, **extra) -> dict:
    return dict(
        V0_analytic_ml=cavity_volume(geometry),
        arrangement=arr.kind,
        n_elements=arr.n_elements,
        spread=list(arr.spread),
        lo={name: float(getattr(lo, name)) for name in LOParams.__dataclass_fields__},
        wall_s=time.perf_counter() - t0,
        **extra,
    )


def run_passive(geometry: Geometry, arr: Arrangement, lo: LOParams, pressures):
    """Passive inflation through ``pressures`` (kPa, increasing from 0). Returns (traces, metadata, log)."""
    t0 = time.perf_counter()
    pressures = np.asarray(pressures, float)
    v0 = cavity_volume(geometry)
    volumes = multielement.passive_volume(pressures, v0, lo, arr)
    w = np.ones(arr.n_elements) if arr.kind == "parallel" else arr.element_values()
    log = []
    for p, v in zip(pressures, volumes):
        v_el = np.full(arr.n_elements, v) if arr.kind == "parallel" else coupling.passive_volume(p / w, v0, lo)
        residual = float(np.max(np.abs(w * np.asarray(coupling.passive_pressure(v_el, v0, lo)) - p)))
        log.append({"pressure": float(p), "converged": True, "residual": residual})
    traces = {"t": pressures / pressures[-1], "V": volumes, "P_lv": pressures, "P_ao": np.full(len(pressures), np.nan)}
    return traces, _metadata(geometry, arr, lo, t0, solves=len(pressures), newton_iterations=0), log


def run_beat(geometry: Geometry, circ: Circulation, cell: CellParams, arr: Arrangement, lo: LOParams, dt: float, beats: int, *, duration: float | None = None):
    """Coupled run over ``beats`` beats (or ``duration`` s). Returns (traces, metadata, log)."""
    t0 = time.perf_counter()
    period = float(beat_period(circ))
    steps = max(10, math.ceil(period / dt - 1e-9))
    n_beats = beats if duration is None else max(1, math.ceil(duration / period - 1e-9))
    heart = Heart(geometry=geometry, lo=lo, cell=cell, circulation=circ)
    res = multielement.simulate(heart, arr, beats=n_beats, steps_per_beat=steps, newton_tol=NEWTON_TOL)
    tr = res.traces
    keep = slice(None) if duration is None else tr["t"] <= duration + 1e-9
    traces = {name: np.asarray(tr[name][keep]) for name in ("t", "V", "P_lv", "P_ao", "P_c", "P_at")}
    log = [{"t": float(traces["t"][-1]), "converged": res.status not in ("nonfinite", "diverged"),
            "status": res.status, "iterations": res.newton_iterations, "residual": res.constraint_residual}]
    if not log[0]["converged"]:
        raise OracleDidNotConverge(f"multielement {arr.kind} run failed (status {res.status}, equal-pressure residual {res.constraint_residual:.3g} kPa)",
                                   time=float(traces["t"][-1]), residual=res.constraint_residual, log=log)
    meta = _metadata(
        geometry, arr, lo, t0,
        period_s=period,
        steps=len(traces["t"]) - 1,
        step_cuts=0,
        newton_iterations=res.newton_iterations,
        stretch_min=float(res.stretch[0]),
        stretch_max=float(res.stretch[1]),
        activation_time_max_s=0.0,
        constraint_residual_kPa=res.constraint_residual,
    )
    return traces, meta, log
