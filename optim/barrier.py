"""Progressive barrier for MADS: Audet C, Dennis JE Jr (2009) A progressive barrier for
derivative-free nonlinear programming. SIAM J Optim 20(1):445-472.

Each point has an objective f and an aggregate constraint violation h >= 0 (h = 0: feasible).
Points with h > h_max are rejected. The feasible incumbent x^F has the least f with h = 0; the
infeasible points with 0 < h <= h_max that no other point dominates (h' <= h and f' <= f) form
the filter, and the infeasible incumbent x^I is its point of least f (= largest h).

An iteration is

* dominating when a trial point improves x^F, or dominates x^I  -> the mesh coarsens,
* improving when it is not dominating but a trial point enters the filter with h < h(x^I)
  -> the mesh stays, and h_max drops to the largest filter h below h(x^I),
* unsuccessful otherwise -> the mesh refines and h_max = h(x^I).

Polling happens around a primary and a secondary frame centre: x^I is primary when
f(x^I) < f(x^F) - rho, else x^F. (ours) Before any infeasible incumbent exists, the first
infeasible points count as improving rather than dominating, so that on problems where h is
never positive this reduces exactly to unconstrained MADS on f.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from optim.protocol import FloatArray

Status = Literal["dominating", "improving", "unsuccessful"]
_RANK = {"unsuccessful": 0, "improving": 1, "dominating": 2}


@dataclasses.dataclass(frozen=True)
class BarrierPoint:
    """A point u of the unit cube with objective f and violation h (f = inf: failed)."""

    u: FloatArray
    f: float
    h: float


def dominates(a: BarrierPoint, b: BarrierPoint) -> bool:
    """a ≺ b: no worse in both f and h, better in one."""
    return a.h <= b.h and a.f <= b.f and (a.h < b.h or a.f < b.f)


class ProgressiveBarrier:
    """Incumbents, filter and threshold h_max; see the module docstring."""

    def __init__(self, rho: float = 0.1) -> None:
        self.rho = float(rho)
        self.h_max = np.inf
        self.feasible: BarrierPoint | None = None
        self.infeasible: BarrierPoint | None = None
        self.filter: list[BarrierPoint] = []
        self.status: Status = "unsuccessful"
        self._start: BarrierPoint | None = None

    def start_iteration(self) -> None:
        self._start, self.status = self.infeasible, "unsuccessful"

    def insert(self, p: BarrierPoint) -> Status:
        """Offer one evaluated point; returns (and accumulates) the iteration status it causes."""
        status: Status = "unsuccessful"
        if not (np.isfinite(p.f) and np.isfinite(p.h) and p.h <= self.h_max):
            return status
        if p.h == 0.0:
            if self.feasible is None or p.f < self.feasible.f:
                self.feasible, status = p, "dominating"
        elif not any(q.h <= p.h and q.f <= p.f for q in self.filter):
            self.filter = [q for q in self.filter if not dominates(p, q)] + [p]
            start = self._start
            if start is not None and dominates(p, start):
                status = "dominating"
            elif start is None or p.h < start.h:
                status = "improving"
        if _RANK[status] > _RANK[self.status]:
            self.status = status
        return status

    def end_iteration(self) -> Status:
        """Update h_max, the filter and x^I from the iteration's status."""
        start = self._start
        if self.status == "improving":
            below = [q.h for q in self.filter if start is None or q.h < start.h]
            if below:
                self.h_max = max(below)
        elif start is not None:
            self.h_max = start.h
        self.filter = [q for q in self.filter if q.h <= self.h_max]
        self.infeasible = min(self.filter, key=lambda q: (q.f, q.h)) if self.filter else None
        return self.status

    def poll_centres(self) -> list[BarrierPoint]:
        """[primary, secondary] frame centres (either may be missing)."""
        f, i = self.feasible, self.infeasible
        if f is None or i is None:
            return [c for c in (f, i) if c is not None]
        return [i, f] if i.f < f.f - self.rho else [f, i]
