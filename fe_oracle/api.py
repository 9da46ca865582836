"""``fe_oracle.run``: one oracle evaluation, cached by content hash (pure Python front end)."""

from __future__ import annotations

import importlib
import pathlib
import sys
import time

import lvenv  # noqa: F401
from lvenv.geometry import Geometry
from lvenv.params import CellParams, Circulation

from fe_oracle import cache
from fe_oracle.cases import Passive, resolve_case
from fe_oracle.material import Guccione
from fe_oracle.result import OracleResult

__all__ = ["BACKENDS", "INSTALL_HINT", "run", "load_backend"]

BACKENDS = ("dolfinx",)
INSTALL_HINT = "pip install -e '.[fe]'"


def load_backend():
    """Import the DOLFINx backend, or raise ImportError saying exactly how to install it."""
    try:
        importlib.import_module("dolfinx_solver")
        return importlib.import_module("fe_oracle.dolfinx_backend")
    except ImportError as err:
        raise ImportError(f"the FE oracle's dolfinx backend needs DOLFINx and gmsh (missing: {err.name}); install them with: {INSTALL_HINT}") from err


def run(
    geometry: Geometry,
    case="passive",
    backend: str = "dolfinx",
    *,
    mesh_size: float = 6.0,
    dt: float = 0.005,
    beats: int = 1,
    duration: float | None = None,
    cell: CellParams | None = None,
    material: Guccione | None = None,
    max_cuts: int = 4,
    newton_max_it: int = 25,
    cache_dir: str | pathlib.Path | None = None,
    use_cache: bool = True,
    progress: bool | None = None,
) -> OracleResult:
    """Run the FE oracle on ``geometry`` (unloaded, mm) for ``case``.

    ``case``: ``"passive"`` (inflation 0 → 4 kPa), a :class:`~fe_oracle.cases.Passive`, a
    training condition 1–3 (Table 2) or any :class:`~lvenv.params.Circulation` (open or closed
    loop). ``mesh_size`` is the target edge length h (mm), ``dt`` the time step (s), ``beats``
    the number of beats from the documented initial state (LV at passive equilibrium with Pat,
    P_c(0) = Pc0, cells at rest); ``duration`` (s), if given, ends the run earlier. ``max_cuts`` bounds the halvings of a failing step (load or
    time), ``newton_max_it`` the Newton iterations per solve.

    Returns an :class:`~fe_oracle.result.OracleResult`; raises
    :class:`~fe_oracle.result.OracleDidNotConverge` if a step fails after all cuts. Results are
    cached under ``cache_dir`` (``use_cache=False`` neither reads nor writes the cache).
    ``progress``: a tqdm bar over simulated time (passive: over the load); ``None`` shows it only
    on a terminal, and only on MPI rank 0.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if not isinstance(geometry, Geometry):
        raise TypeError(f"geometry must be an lvenv.geometry.Geometry, got {type(geometry).__name__}")
    if not mesh_size > 0:
        raise ValueError(f"mesh_size = {mesh_size!r} mm must be positive")
    if not dt > 0:
        raise ValueError(f"dt = {dt!r} s must be positive")
    if int(beats) != beats or beats < 1:
        raise ValueError(f"beats = {beats!r} must be a positive integer")
    record = resolve_case(case)
    cell = CellParams() if cell is None else cell
    material = Guccione() if material is None else material
    passive = isinstance(record, Passive)
    inputs = {
        "backend": backend,
        "geometry": geometry,
        "case": record,
        "mesh_size": float(mesh_size),
        "material": material,
        "max_cuts": int(max_cuts),
        "newton_max_it": int(newton_max_it),
    }
    if not passive:
        inputs.update(dt=float(dt), beats=int(beats), duration=duration, cell=cell)
    directory = cache.default_dir() if cache_dir is None else pathlib.Path(cache_dir)
    k = cache.key(inputs)
    if use_cache and (hit := cache.load(directory, k)) is not None:
        return hit
    be = load_backend()
    show = bool(getattr(sys.stderr, "isatty", lambda: False)()) if progress is None else bool(progress)
    t0 = time.perf_counter()
    if passive:
        traces, meta, log = be.run_passive(geometry, material, mesh_size, record.pressures(), max_cuts=max_cuts, newton_max_it=newton_max_it, progress=show)
    else:
        traces, meta, log = be.run_beat(
            geometry, record, cell, material, mesh_size, dt, int(beats), duration=duration, max_cuts=max_cuts, newton_max_it=newton_max_it, progress=show
        )
    meta = dict(meta, case="passive" if passive else "beat", key=k, code_version=cache.code_version(), mesh_size_mm=float(mesh_size), total_s=time.perf_counter() - t0)
    if not passive:
        meta.update(dt_s=float(dt), beats=int(beats))
    result = OracleResult(traces, meta, log)
    if use_cache:
        cache.store(directory, k, result)
    return result
