"""What an oracle run returns, and how it fails (pure Python, no DOLFINx)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

__all__ = ["OracleResult", "OracleDidNotConverge", "TRACE_NAMES"]

TRACE_NAMES = ("t", "V", "P_lv", "P_ao")


@dataclasses.dataclass(frozen=True)
class OracleResult:
    """Traces and metadata of one oracle run.

    ``traces``: ``t`` (s), ``V`` (ml), ``P_lv`` and ``P_ao`` (kPa), equal-length 1-D arrays. For
    the passive case ``t`` is the load parameter P / p_max (0 → 1; negative on a deflation branch), ``P_lv`` the applied pressure and
    ``P_ao`` is NaN. Beats also carry ``P_c`` (Windkessel capacitor) and ``P_at`` (atrium), kPa;
    ``V`` is the 0-D volume state, which the FE cavity volume matches within ``volume_tol_ml``. ``metadata``: inputs, mesh size, V0, timings, stretch range (JSON-able).
    ``log``: one record per nonlinear solve (time, pressure, Newton reason and iterations,
    residual). ``from_cache`` is True when the result was read back from the cache.
    """

    traces: dict[str, np.ndarray]
    metadata: dict[str, Any]
    log: list[dict[str, Any]]
    from_cache: bool = False


class OracleDidNotConverge(RuntimeError):
    """The FE solve failed even after step cutting.

    ``time`` is the simulated time (s; for passive inflation the pressure, kPa) at which it
    failed, ``residual`` the last nonlinear residual norm, ``log`` the solver log so far.
    """

    def __init__(self, message: str, *, time: float, residual: float, log: list[dict[str, Any]]):
        super().__init__(f"{message} (at t = {time:.6g}, last residual {residual:.3e})")
        self.time = time
        self.residual = residual
        self.log = log
