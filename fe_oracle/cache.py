"""On-disk cache of oracle results, keyed by a content hash of every input (pure Python).

Key = SHA-256 of a canonical JSON of: backend, geometry, case, mesh size, dt, beats, material,
cell and circulation parameters (every field by name, so a new or renamed field changes it too),
solver options, and the backend's *code version* — a hash of the source files whose code its
results depend on (:data:`CODE`: the backend's own modules and the ``lvenv`` equations they
run). Changing the code of any of them gives a new key, so stale results are never reused, while
an edit elsewhere (the front end, another backend) or of documentation only (docstrings,
comments, layout: the version hashes the syntax trees without them) keeps the cached runs.

An entry is one ``<key>.npz`` file (traces plus the metadata and solver log as JSON), written
atomically in the safe format of :mod:`lvenv.archive`, so a killed run leaves either the
complete entry or none, and loading an entry never unpickles. A damaged entry is reported
(:class:`lvenv.archive.ArchiveError`, with its path) rather than silently recomputed.
Default directory: ``$LVENV_FE_CACHE`` or ``~/.cache/lvenv/fe_oracle``.

**Shipped runs.** The package ships some entries (:data:`SHIPPED`, written by
``scripts/ship_fe_runs.py``: the built-in hearts' training runs, unseen scenarios and points
inside the scenarios' axes, the runs the candidate studies compare against), without their
solver logs. :func:`lookup` reads a key from the cache directory, else from there, so a fresh
machine does not run them again.
Their keys hold the code version like any other: after a change to the oracle's code they are
never read, and the script writes them anew.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import hashlib
import json
import os
import pathlib

import numpy as np

from lvenv import archive

from fe_oracle.result import OracleResult

__all__ = ["SHIPPED", "default_dir", "code_text", "code_version", "key", "load", "lookup", "store"]

#: Per backend, the source files its results depend on (package-relative paths).
CODE = {
    "dolfinx": tuple(f"fe_oracle/{name}.py" for name in (
        "activation", "cases", "coupled_beat", "dolfinx_backend", "eikonal", "fibres", "material",
        "mechanics", "mesh", "passive", "quadrature_cells", "result",
    )) + ("lvenv/cell.py", "lvenv/circulation.py", "lvenv/geometry.py"),
    "multielement": ("fe_oracle/cases.py", "fe_oracle/multielement_backend.py", "fe_oracle/result.py", "lvenv/cell.py",
                     "lvenv/circulation.py", "lvenv/coupling.py", "lvenv/events.py", "lvenv/geometry.py",
                     "lvenv/integrator.py", "lvenv/multielement.py"),
}


#: Entries shipped with the package (module docstring), read-only.
SHIPPED = pathlib.Path(__file__).resolve().parent / "data" / "runs"


def default_dir() -> pathlib.Path:
    return pathlib.Path(os.environ.get("LVENV_FE_CACHE", pathlib.Path.home() / ".cache" / "lvenv" / "fe_oracle"))


def code_text(source: str) -> str:
    """The syntax tree of ``source`` without docstrings, comments or layout, as text: what a
    code version hashes, so that editing documentation keeps the cache."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body:
            first = body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree, include_attributes=False)


@functools.lru_cache(maxsize=None)
def code_version(backend: str = "dolfinx") -> str:
    """SHA-256 (first 16 hex digits) of the code of the source files of :data:`CODE` for
    ``backend``: their syntax trees without docstrings and comments (:func:`code_text`)."""
    root = pathlib.Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for name in CODE[backend]:
        digest.update(name.encode())
        digest.update(code_text((root / name).read_text(encoding="utf-8")).encode())
    return digest.hexdigest()[:16]


def _canonical(value):
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {"__type__": type(value).__name__, **{f.name: _canonical(getattr(value, f.name)) for f in dataclasses.fields(value)}}
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in sorted(value.items())}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


def key(inputs: dict) -> str:
    """Content hash of ``inputs`` (dataclasses, numbers, strings) and the code version."""
    blob = json.dumps({"inputs": _canonical(inputs), "code": code_version(inputs.get("backend", "dolfinx"))}, sort_keys=True, default=float)
    return hashlib.sha256(blob.encode()).hexdigest()


def _path(directory: pathlib.Path, k: str) -> pathlib.Path:
    return pathlib.Path(directory) / f"{k}.npz"


def load(directory, k: str) -> OracleResult | None:
    """The cached result for key ``k``, or None."""
    path = _path(directory, k)
    if not path.exists():
        return None
    arrays, extra = archive.load(path, "FE oracle cache entry")
    traces = {name[len("trace_"):]: value for name, value in arrays.items() if name.startswith("trace_")}
    return OracleResult(traces, extra["metadata"], extra["log"], from_cache=True)


def lookup(directory, k: str) -> OracleResult | None:
    """The result for key ``k`` from the cache ``directory``, else from :data:`SHIPPED`, or None."""
    hit = load(directory, k)
    return hit if hit is not None else load(SHIPPED, k)


def store(directory, k: str, result: OracleResult) -> pathlib.Path:
    """Atomically write ``result`` under key ``k``; returns the entry's path."""
    arrays = {f"trace_{name}": np.asarray(v) for name, v in result.traces.items()}
    return archive.save(_path(directory, k), arrays, {"metadata": _canonical(result.metadata), "log": _canonical(result.log)})
