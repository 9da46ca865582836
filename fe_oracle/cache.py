"""On-disk cache of oracle results, keyed by a content hash of every input (pure Python).

Key = SHA-256 of a canonical JSON of: geometry, case, mesh size, dt, beats, material, cell and
circulation parameters, solver options, and the *code version* — a hash of the source of
``fe_oracle`` and of the ``lvenv`` modules it runs (cell, circulation, geometry, params).
Changing any of them gives a new key, so stale results are never reused.

An entry is one ``<key>.npz`` file (traces plus the metadata and solver log as JSON). It is
written to a temporary file in the same directory and ``os.replace``-d into place, so a killed
run leaves either the complete entry or none (at most a ``.tmp`` file, which is ignored).
Default directory: ``$LVENV_FE_CACHE`` or ``~/.cache/lvenv/fe_oracle``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import pathlib
import tempfile

import numpy as np

from fe_oracle.result import OracleResult

__all__ = ["default_dir", "code_version", "key", "load", "store"]

_LVENV_MODULES = ("cell.py", "circulation.py", "geometry.py", "params.py")


def default_dir() -> pathlib.Path:
    return pathlib.Path(os.environ.get("LVENV_FE_CACHE", pathlib.Path.home() / ".cache" / "lvenv" / "fe_oracle"))


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """SHA-256 (first 16 hex digits) of the oracle's source and the lvenv modules it uses."""
    here = pathlib.Path(__file__).resolve().parent
    lvenv_dir = here.parent / "lvenv"
    files = sorted(here.glob("*.py")) + [lvenv_dir / name for name in _LVENV_MODULES]
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
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
    blob = json.dumps({"inputs": _canonical(inputs), "code": code_version()}, sort_keys=True, default=float)
    return hashlib.sha256(blob.encode()).hexdigest()


def _path(directory: pathlib.Path, k: str) -> pathlib.Path:
    return pathlib.Path(directory) / f"{k}.npz"


def load(directory, k: str) -> OracleResult | None:
    """The cached result for key ``k``, or None."""
    path = _path(directory, k)
    if not path.exists():
        return None
    with np.load(path, allow_pickle=False) as data:
        traces = {name[len("trace_"):]: np.array(data[name]) for name in data.files if name.startswith("trace_")}
        extra = json.loads(str(data["json"]))
    return OracleResult(traces, extra["metadata"], extra["log"], from_cache=True)


def store(directory, k: str, result: OracleResult) -> pathlib.Path:
    """Atomically write ``result`` under key ``k``; returns the entry's path."""
    directory = pathlib.Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    final = _path(directory, k)
    payload = {f"trace_{name}": np.asarray(v) for name, v in result.traces.items()}
    payload["json"] = np.array(json.dumps({"metadata": _canonical(result.metadata), "log": _canonical(result.log)}, default=float))
    fd, tmp = tempfile.mkstemp(prefix=f".{k}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, final)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise
    return final
