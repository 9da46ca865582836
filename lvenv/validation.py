"""Checks of user-supplied settings at the Python boundary, with one wording for every error.

Every check raises :class:`InputError` (a ``ValueError``) naming the field, the value given and what is allowed, e.g.
``rtol = nan must be a finite real number in (0, 1)``. Booleans and strings are rejected where
numbers belong (``True`` is not the integer 1 here), and a float is an integer only when it is
integral (``beats=2.0`` passes, ``beats=1.5`` does not). Pure Python and NumPy: the geometry and
the FE front end use it too.
"""

from __future__ import annotations

import math
import numbers
import os
import pathlib
from collections.abc import Collection
from typing import Any

import numpy as np

__all__ = ["InputError", "integer", "real", "choice", "real_array", "writable"]


class InputError(ValueError):
    """Bad input from a user: names the field, the value and what is allowed.

    Every check of lvenv's public entry points raises it, so a caller (the CLI) can tell bad
    input (exit code 2) from a failure of the code itself.
    """


def _number(x: float) -> str:
    """A bound as written in messages: integers in full, other numbers in %g."""
    return str(x) if isinstance(x, numbers.Integral) else f"{x:g}"


def _interval(lo: float, hi: float, lo_open: bool, hi_open: bool) -> str:
    """The allowed interval in words (``in [0, 1)``, ``≥ 1``); empty when unbounded."""
    if math.isinf(hi) and not math.isinf(lo):
        return f"{'>' if lo_open else '≥'} {_number(lo)}"
    if math.isinf(lo) and not math.isinf(hi):
        return f"{'<' if hi_open else '≤'} {_number(hi)}"
    if math.isinf(lo) and math.isinf(hi):
        return ""
    return f"in {'(' if lo_open else '['}{_number(lo)}, {_number(hi)}{')' if hi_open else ']'}"


def real(name: str, value: Any, lo: float = -math.inf, hi: float = math.inf, *, lo_open: bool = False, hi_open: bool = False) -> float:
    """``value`` as a finite float inside the interval, else ``ValueError`` naming ``name``."""
    allowed = f"a finite real number {_interval(lo, hi, lo_open, hi_open)}".rstrip()
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise InputError(f"{name} = {value!r} must be {allowed}")
    x = float(value)
    inside = math.isfinite(x) and (x > lo if lo_open else x >= lo) and (x < hi if hi_open else x <= hi)
    if not inside:
        raise InputError(f"{name} = {value!r} must be {allowed}")
    return x


def integer(name: str, value: Any, minimum: int | None = None, maximum: int | None = None) -> int:
    """``value`` as an int within [minimum, maximum]; integral floats are accepted, bools are not."""
    lo = -math.inf if minimum is None else minimum
    hi = math.inf if maximum is None else maximum
    allowed = f"an integer {_interval(lo, hi, False, False)}".rstrip()
    integral = isinstance(value, numbers.Integral) or (isinstance(value, numbers.Real) and math.isfinite(float(value)) and float(value).is_integer())
    if isinstance(value, (bool, np.bool_)) or not integral:
        raise InputError(f"{name} = {value!r} must be {allowed}")
    n = int(value)
    if not lo <= n <= hi:
        raise InputError(f"{name} = {value!r} must be {allowed}")
    return n


def choice(name: str, value: Any, choices: Collection[Any]) -> Any:
    """``value`` if it is one of ``choices``, else ``ValueError`` listing them."""
    boolean = isinstance(value, (bool, np.bool_)) and not any(isinstance(c, bool) for c in choices)
    if boolean or isinstance(value, (list, dict, set, np.ndarray)) or value not in choices:
        raise InputError(f"{name} = {value!r} is not one of {', '.join(map(repr, choices))}")
    return value


def real_array(name: str, value: Any) -> np.ndarray:
    """``value`` (number, sequence or array) as a float64 array; booleans, strings, complex and
    ragged input raise ``ValueError`` naming ``name``."""
    try:
        arr = np.asarray(value)
    except ValueError as err:
        raise InputError(f"{name} = {value!r} is not a real number or an array of them ({err})") from None
    if arr.dtype.kind not in "iuf":
        raise InputError(f"{name} = {value!r} must be a real number or an array of real numbers (got dtype {arr.dtype})")
    return arr.astype(np.float64)


def writable(name: str, path: str | os.PathLike[str], *, folder: bool = False) -> pathlib.Path:
    """``path`` as a Path that can be written (a file, or with ``folder`` a folder): it exists and
    is writable, or its nearest existing parent is a writable folder (missing folders are made
    when written). Else :class:`InputError` naming ``name``, the path and why. Creates nothing:
    call it before a long computation whose result goes there."""
    target = pathlib.Path(path).expanduser()
    kind = "a folder" if folder else "a file"
    if target.exists():
        if target.is_dir() != folder:
            raise InputError(f"{name} = {str(path)!r} must be {kind}, and it is {'a folder' if target.is_dir() else 'a file'}")
        if not os.access(target, os.W_OK):
            raise InputError(f"{name} = {str(path)!r} is not writable")
        return target
    parent = target.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{name} = {str(path)!r} cannot be made: {str(parent)!r} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{name} = {str(path)!r} cannot be written: the folder {str(parent)!r} is not writable")
    return target
