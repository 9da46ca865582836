"""Safe, atomic files of named arrays plus JSON metadata (``.npz``; never pickle).

One format for everything lvenv and its packages write to resume from or to cache: optimiser
and environment checkpoints (:mod:`optim.protocol`, :mod:`optim.minimize`), FE oracle
results (:mod:`fe_oracle.cache`) and the finished items of long studies (:func:`save_records`). A file is a NumPy ``.npz`` archive of numeric, boolean or
fixed-width string arrays and one ``__meta__`` entry holding JSON text; it is read with
``allow_pickle=False``, so loading a file from elsewhere cannot run code.

Writes go to a temporary file in the same folder, are flushed to disk and then
``os.replace``-d into place: a killed process leaves the old file or the new one, never half of
one (at most a stray ``.tmp`` file, which readers ignore).
"""

from __future__ import annotations

import json
import os
import pathlib
import tempfile
import zipfile
from collections.abc import Callable
from typing import IO, Any

import numpy as np

from lvenv.validation import InputError

__all__ = ["ArchiveError", "save", "load", "META", "save_records", "load_records", "write_text"]

META = "__meta__"


class ArchiveError(InputError):
    """A file that cannot be read back: missing, damaged, truncated or not ours. Names the path."""


def save(path: str | os.PathLike[str], arrays: dict[str, Any], meta: dict[str, Any]) -> pathlib.Path:
    """Atomically write ``arrays`` (name → array) and ``meta`` (JSON-able) to ``path``."""
    target = pathlib.Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    payload = {name: np.asarray(value) for name, value in arrays.items()}
    for name, value in payload.items():
        if value.dtype.kind not in "biufU":
            raise TypeError(f"archive entry {name!r} has dtype {value.dtype}; only numbers, booleans and strings are stored")
    payload[META] = np.array(json.dumps(meta, allow_nan=True))
    return _replace(target, lambda fh: np.savez(fh, **payload), binary=True)


def write_text(path: str | os.PathLike[str], text: str) -> pathlib.Path:
    """Atomically write UTF-8 ``text`` to ``path`` (a JSON record, a CSV rewritten on resume),
    the same way as :func:`save`: the old file or the new one, never half of one."""
    return _replace(pathlib.Path(path), lambda fh: fh.write(text), binary=False)


def _replace(target: pathlib.Path, write: Callable[[IO], Any], *, binary: bool) -> pathlib.Path:
    """``write`` into a temporary file beside ``target``, flush it to disk, then ``os.replace`` it
    into place (module docstring); the temporary file is removed if anything fails."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise
    return target


def load(path: str | os.PathLike[str], what: str = "file") -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``(arrays, meta)`` of an archive; :class:`ArchiveError` (naming ``what`` and the path, and
    saying what to do) if it is missing, damaged or not an archive of this format."""
    path = pathlib.Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.array(data[name]) for name in data.files if name != META}
            meta = json.loads(str(data[META]))
    except FileNotFoundError:
        raise ArchiveError(f"{what} {str(path)!r} does not exist") from None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as err:
        raise ArchiveError(
            f"{what} {str(path)!r} is damaged or not an lvenv archive ({type(err).__name__}: {err}); "
            "delete it or move it away to start afresh"
        ) from None
    if not isinstance(meta, dict):
        raise ArchiveError(f"{what} {str(path)!r} has no metadata object; delete it or move it away to start afresh")
    return arrays, meta


def save_records(path: str | os.PathLike[str], records: list[dict[str, Any]], settings: dict[str, Any]) -> pathlib.Path:
    """Atomically write a long study's finished ``records`` (JSON-able) with the ``settings``
    that produced them, for :func:`load_records` to resume from."""
    return save(path, {}, {"settings": settings, "records": records})


def load_records(path: str | os.PathLike[str], settings: dict[str, Any]) -> list[dict[str, Any]]:
    """The records :func:`save_records` wrote to ``path`` under equal ``settings``; ``[]`` when
    there is no file. :class:`ArchiveError` if the file is damaged or its settings differ
    (naming both), since mixing the records of two settings would be wrong."""
    if not pathlib.Path(path).exists():
        return []
    _, meta = load(path, "study checkpoint")
    settings = json.loads(json.dumps(settings))
    if meta.get("settings") != settings or not isinstance(meta.get("records"), list):
        raise ArchiveError(f"study checkpoint {str(path)!r} was written with settings {meta.get('settings')}, not {settings}; "
                           "delete it or move it away to start afresh")
    return meta["records"]
