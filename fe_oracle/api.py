"""``fe_oracle.run``: one oracle evaluation, cached by content hash (pure Python front end)."""

from __future__ import annotations

import importlib
import pathlib
import sys
import time

import lvenv  # noqa: F401
from lvenv.geometry import Geometry
from lvenv.params import CellParams, Circulation, Heart, LOParams, batch_size, validate
from lvenv.validation import InputError, choice, integer, real

from fe_oracle import cache
from fe_oracle.cases import Passive, resolve_case
from fe_oracle.material import Guccione
from fe_oracle.result import OracleResult

__all__ = ["ACTIVATIONS", "BACKENDS", "DEFAULT_DT", "DEFAULT_MESH_SIZE", "MAX_BEATS", "MAX_DURATION_S", "INSTALL_HINT", "run", "load_backend"]

BACKENDS = ("dolfinx", "multielement")
#: How the dolfinx backend's wall activates: from the eikonal solve (DESIGN §4, the default) or
#: everywhere at the beat's onset, like the single LO cell (a diagnostic: it separates the spread
#: of activation from the rest of the congruency gap).
ACTIVATIONS = ("eikonal", "synchronous")
#: Default time step (s) per backend.
DEFAULT_DT = {"dolfinx": 0.005, "multielement": 0.001}
#: Default mesh size h (mm) of the dolfinx backend: the size the LO maps are trained at.
DEFAULT_MESH_SIZE = 6.0
#: Most beats one oracle run may cover (an FE beat costs minutes; a steady state needs a few),
#: and the longest ``duration`` (s): that many beats at the slowest heart rate, 20/min.
MAX_BEATS = 100
MAX_DURATION_S = MAX_BEATS * 3.0
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
    mesh_size: float = DEFAULT_MESH_SIZE,
    dt: float | None = None,
    beats: int = 1,
    duration: float | None = None,
    cell: CellParams | None = None,
    material: Guccione | None = None,
    max_cuts: int = 4,
    newton_max_it: int = 25,
    cache_dir: str | pathlib.Path | None = None,
    use_cache: bool = True,
    progress: bool | None = None,
    arrangement: str | None = None,
    n_elements: int | None = None,
    lo: LOParams | None = None,
    activation: str = "eikonal",
) -> OracleResult:
    """Run the FE oracle on ``geometry`` (unloaded, mm) for ``case``.

    ``case``: ``"passive"`` (inflation 0 → 4 kPa), a :class:`~fe_oracle.cases.Passive`, a
    training condition 1–3 (Table 2) or any :class:`~lvenv.params.Circulation` (open or closed
    loop). ``mesh_size`` is the target edge length h (mm), ``dt`` the time step (s; default
    :data:`DEFAULT_DT` of the backend: 5 ms for dolfinx, 1 ms for multielement, whose valve
    timings need it), ``beats``
    the number of beats (at most :data:`MAX_BEATS`) from the documented initial state (LV at passive equilibrium with Pat,
    P_c(0) = Pc0, cells at rest); ``duration`` (s), if given, ends the run earlier. ``max_cuts`` bounds the halvings of a failing step (load or
    time), ``newton_max_it`` the Newton iterations per solve. ``activation``: one of
    :data:`ACTIVATIONS` (beats of the dolfinx backend only; ``"synchronous"`` sets every
    activation time to 0 s).

    Returns an :class:`~fe_oracle.result.OracleResult`; raises
    :class:`~fe_oracle.result.OracleDidNotConverge` if a step fails after all cuts. Results are
    cached under ``cache_dir``, and the runs the package ships are read too
    (:func:`fe_oracle.cache.lookup`; ``use_cache=False`` neither reads nor writes either).
    ``progress``: a tqdm bar over simulated time (passive: over the load); ``None`` shows it only
    on a terminal, and only on MPI rank 0.

    ``backend="multielement"``: the §1.4 multi-element LO heart (:mod:`fe_oracle.multielement_backend`,
    no DOLFINx, seconds): ``arrangement`` ``"parallel"`` (default) or ``"series"``, ``n_elements``
    (default 256), ``lo`` the LO parameters (default: the paper's trained values for the N and HF
    geometries). ``mesh_size``, ``material``, ``max_cuts``, ``newton_max_it`` and ``progress``
    do not apply to it; ``arrangement``, ``n_elements`` and ``lo`` apply to it only.
    """
    choice("backend", backend, BACKENDS)
    choice("activation", activation, ACTIVATIONS)
    if not isinstance(geometry, Geometry):
        raise InputError(f"geometry must be an lvenv.geometry.Geometry, got {type(geometry).__name__}")
    mesh_size = real("mesh_size", mesh_size, 0.0, lo_open=True)
    dt = real("dt", DEFAULT_DT[backend] if dt is None else dt, 0.0, 1.0, lo_open=True)
    beats = integer("beats", beats, 1, MAX_BEATS)
    if duration is not None:
        duration = real("duration", duration, 0.0, MAX_DURATION_S, lo_open=True)
    record = resolve_case(case)
    cell = CellParams() if cell is None else cell
    _check_heart(geometry, record, cell, lo)
    passive = isinstance(record, Passive)
    if backend == "multielement":
        if activation != "eikonal":
            raise InputError(f"activation = {activation!r} applies to backend 'dolfinx' only; the multielement backend has no activation sequence")
        return _run_multielement(geometry, record, cell, arrangement, n_elements, lo, dt=dt, beats=int(beats), duration=duration, cache_dir=cache_dir, use_cache=use_cache)
    if (arrangement, n_elements, lo) != (None, None, None):
        raise InputError(f"arrangement, n_elements and lo apply to backend 'multielement' only, not {backend!r}")
    material = Guccione() if material is None else material
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
        if activation != "eikonal":  # the default stays out of the key: earlier entries keep theirs
            inputs.update(activation=activation)

    def compute():
        be = load_backend()
        show = bool(getattr(sys.stderr, "isatty", lambda: False)()) if progress is None else bool(progress)
        if passive:
            return be.run_passive(geometry, material, mesh_size, record.pressures(), max_cuts=max_cuts, newton_max_it=newton_max_it, progress=show)
        return be.run_beat(geometry, record, cell, material, mesh_size, dt, int(beats), duration=duration, max_cuts=max_cuts, newton_max_it=newton_max_it, progress=show,
                           synchronous=activation == "synchronous")

    return _cached(inputs, compute, cache_dir, use_cache, mesh_size=float(mesh_size))


def _check_heart(geometry: Geometry, record: Passive | Circulation, cell: CellParams, lo: LOParams | None) -> None:
    """The run's parameters, checked as :func:`lvenv.simulate` checks a Heart (the same
    :class:`~lvenv.validation.InputError`, naming field, value and range): one parameter set, no batch."""
    if not isinstance(cell, CellParams):
        raise InputError(f"cell must be an lvenv.params.CellParams or None, got {type(cell).__name__}")
    heart = Heart(geometry=geometry, lo=lo if isinstance(lo, LOParams) else LOParams(), cell=cell,
                  circulation=record if isinstance(record, Circulation) else Circulation())
    validate(heart)
    if batch_size(heart) is not None:
        raise InputError("an oracle run takes one parameter set: cell, circulation and lo must hold numbers, not a batch of arrays")


def _cached(inputs: dict, compute, cache_dir, use_cache: bool, *, mesh_size: float | None) -> OracleResult:
    """The cached result for ``inputs``, else ``compute()`` → (traces, metadata, log) with the
    metadata every backend shares added, stored in the cache unless ``use_cache`` is False."""
    directory = cache.default_dir() if cache_dir is None else pathlib.Path(cache_dir)
    k = cache.key(inputs)
    if use_cache and (hit := cache.lookup(directory, k)) is not None:
        return hit
    t0 = time.perf_counter()
    traces, meta, log = compute()
    passive = isinstance(inputs["case"], Passive)
    meta = dict(meta, backend=inputs["backend"], case="passive" if passive else "beat", key=k, code_version=cache.code_version(inputs["backend"]),
                mesh_size_mm=mesh_size, total_s=time.perf_counter() - t0)
    if not passive:
        meta.update(dt_s=inputs["dt"], beats=inputs["beats"])
    result = OracleResult(traces, meta, log)
    if use_cache:
        cache.store(directory, k, result)
    return result


def _run_multielement(geometry, record, cell, arrangement, n_elements, lo, *, dt, beats, duration, cache_dir, use_cache) -> OracleResult:
    """``run`` with ``backend="multielement"`` (:mod:`fe_oracle.multielement_backend`)."""
    from fe_oracle import multielement_backend as be

    arr = be.arrangement(arrangement, n_elements)
    lo = be.default_lo(geometry) if lo is None else lo
    if not isinstance(lo, LOParams):
        raise InputError(f"lo = {lo!r} must be an lvenv.params.LOParams or None")
    passive = isinstance(record, Passive)
    inputs = {"backend": "multielement", "geometry": geometry, "case": record, "arrangement": arr, "lo": lo}
    if not passive:
        inputs.update(dt=float(dt), beats=beats, duration=duration, cell=cell)

    def compute():
        if passive:
            return be.run_passive(geometry, arr, lo, record.pressures())
        return be.run_beat(geometry, record, cell, arr, lo, dt, beats, duration=duration)

    return _cached(inputs, compute, cache_dir, use_cache, mesh_size=None)
