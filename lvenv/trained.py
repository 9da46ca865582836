"""Trained LO maps as a record: what congruency training (:mod:`optim.congruency`) produces and
what the presets load (package data ``lvenv/data/trained_<name>.json``).

A record holds the nine LO parameters (DESIGN §1 plus the activation delay of §3), the cell
unit it was trained with, C per training beat, the passive fit's residual and the provenance
(oracle backend, mesh size, time step, the oracle runs' cache keys, code versions). It saves to
and loads from JSON; :meth:`TrainedLO.heart` builds a :class:`~lvenv.params.Heart`.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from collections.abc import Mapping
from typing import Any

from lvenv.geometry import Geometry
from lvenv.params import CellParams, Circulation, Heart, LOParams
from lvenv.validation import InputError

__all__ = ["TrainedLO", "DATA", "builtin"]

#: Folder of the shipped records.
DATA = pathlib.Path(__file__).resolve().parent / "data"


@dataclasses.dataclass(frozen=True)
class TrainedLO:
    """Trained LO maps of one geometry, their congruency and where they came from.

    ``congruency``: C per training beat ("1", "2", "3") and overall ("C"), a fraction;
    ``congruency_without_delay``: the same for the fit with the delay fixed at 0, when the
    delay was tried; ``passive_rmse_ml``: RMS volume residual of the passive fit.
    """

    geometry: Geometry
    lo: LOParams
    cell: CellParams
    congruency: dict[str, float]
    congruency_without_delay: dict[str, float] | None
    passive_rmse_ml: float
    provenance: dict[str, Any]

    def heart(self, circulation: Circulation | None = None, cell: CellParams | None = None) -> Heart:
        """A Heart with these maps (default circulation and the training cell unless given)."""
        return Heart(geometry=self.geometry, lo=self.lo, cell=self.cell if cell is None else cell,
                     circulation=Circulation() if circulation is None else circulation)

    def to_dict(self) -> dict[str, Any]:
        return {
            "geometry": dataclasses.asdict(self.geometry), "lo": dataclasses.asdict(self.lo), "cell": dataclasses.asdict(self.cell),
            "congruency": self.congruency, "congruency_without_delay": self.congruency_without_delay,
            "passive_rmse_ml": self.passive_rmse_ml, "provenance": self.provenance,
        }

    def to_json(self, path: str | pathlib.Path | None = None) -> str:
        text = json.dumps(self.to_dict(), indent=2)
        if path is not None:
            pathlib.Path(path).write_text(text + "\n")
        return text

    @classmethod
    def from_dict(cls, record: Mapping[str, Any]) -> TrainedLO:
        try:
            return cls(
                geometry=Geometry(**record["geometry"]), lo=LOParams(**record["lo"]), cell=CellParams(**record["cell"]),
                congruency=dict(record["congruency"]), congruency_without_delay=record.get("congruency_without_delay"),
                passive_rmse_ml=float(record["passive_rmse_ml"]), provenance=dict(record["provenance"]),
            )
        except (KeyError, TypeError) as err:
            raise InputError(f"not a trained-LO record: {err}") from None

    @classmethod
    def from_json(cls, path: str | pathlib.Path) -> TrainedLO:
        path = pathlib.Path(path)
        try:
            record = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise InputError(f"cannot read the trained-LO record {str(path)!r}: {err}") from None
        return cls.from_dict(record)


def builtin(name: str) -> TrainedLO:
    """The shipped record ``"normal"`` or ``"heart_failure"`` (trained against the 3-D oracle)."""
    path = DATA / f"trained_{name}.json"
    if not path.is_file():
        raise InputError(f"no trained LO record {name!r} in {DATA}; known: {sorted(p.stem[len('trained_'):] for p in DATA.glob('trained_*.json'))}")
    return TrainedLO.from_json(path)
