"""Trained LO maps as a record: what congruency training (:mod:`optim.congruency`) produces and
what the presets load (package data ``lvenv/data/trained_<name>.json``).

A record holds the nine LO parameters (DESIGN §1 plus the activation delay of §3), the cell
unit it was trained with, the LO heart model they were trained for (``elements``: ``None`` for
the single cell, else the multi-element :class:`~lvenv.params.Arrangement`), C per training
beat, the passive fit's residual and the provenance (oracle backend, mesh size, time step, the
oracle runs' cache keys, code versions). It saves to and loads from JSON;
:meth:`TrainedLO.heart` builds a :class:`~lvenv.params.Heart` of that model.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
from collections.abc import Mapping
from typing import Any

from lvenv import archive
from lvenv.geometry import Geometry
from lvenv.params import Arrangement, CellParams, Circulation, Heart, LOParams, validate
from lvenv.validation import InputError, real

__all__ = ["TrainedLO", "DATA", "builtin"]

#: Folder of the shipped records.
DATA = pathlib.Path(__file__).resolve().parent / "data"


@dataclasses.dataclass(frozen=True)
class TrainedLO:
    """Trained LO maps of one geometry, their congruency and where they came from.

    ``congruency``: C per training beat ("1", "2", "3") and overall ("C"), a fraction;
    ``congruency_without_delay``: the same for the fit with the delay fixed at 0, when the
    delay was tried; ``passive_rmse_ml``: RMS volume residual of the passive fit; ``elements``:
    the LO heart model the maps belong to (``Heart.elements``; optional in a record, ``null``
    by default: the single cell).
    """

    geometry: Geometry
    lo: LOParams
    cell: CellParams
    congruency: dict[str, float]
    congruency_without_delay: dict[str, float] | None
    passive_rmse_ml: float
    provenance: dict[str, Any]
    elements: Arrangement | None = None

    def heart(self, circulation: Circulation | None = None, cell: CellParams | None = None) -> Heart:
        """A Heart with these maps and model (default circulation and the training cell unless given)."""
        return Heart(geometry=self.geometry, lo=self.lo, cell=self.cell if cell is None else cell,
                     circulation=Circulation() if circulation is None else circulation, elements=self.elements)

    def to_dict(self) -> dict[str, Any]:
        return {
            "geometry": dataclasses.asdict(self.geometry), "lo": dataclasses.asdict(self.lo), "cell": dataclasses.asdict(self.cell),
            "congruency": self.congruency, "congruency_without_delay": self.congruency_without_delay,
            "passive_rmse_ml": self.passive_rmse_ml, "provenance": self.provenance,
            "elements": None if self.elements is None else self.elements.to_dict(),
        }

    def to_json(self, path: str | pathlib.Path | None = None) -> str:
        text = json.dumps(self.to_dict(), indent=2)
        if path is not None:
            archive.write_text(path, text + "\n")
        return text

    @classmethod
    def from_dict(cls, record: Mapping[str, Any]) -> TrainedLO:
        """A record from its dict (:meth:`to_dict`), checked field by field: a missing, unknown,
        mistyped or list-valued field, or a parameter out of its range, raises
        :class:`~lvenv.validation.InputError` naming it; nothing falls back to a default, but
        ``elements`` (the single cell's records may leave it out)."""
        if not isinstance(record, Mapping):
            raise InputError(f"a trained-LO record is a JSON object, not {type(record).__name__}")
        _known("record", record, _FIELDS, optional=("elements",))
        geometry, lo, cell = (_parameters(part, record, kind) for part, kind in (("geometry", Geometry), ("lo", LOParams), ("cell", CellParams)))
        elements = None if record.get("elements") is None else Arrangement.from_dict(record["elements"])
        validate(Heart(geometry=geometry, lo=lo, cell=cell, elements=elements))
        without = record["congruency_without_delay"]
        provenance = record["provenance"]
        if not isinstance(provenance, Mapping):
            raise InputError(f"provenance = {provenance!r} must be an object")
        return cls(
            geometry=geometry, lo=lo, cell=cell, congruency=_fractions("congruency", record["congruency"]),
            congruency_without_delay=None if without is None else _fractions("congruency_without_delay", without),
            passive_rmse_ml=_rmse(record["passive_rmse_ml"]), provenance=dict(provenance), elements=elements,
        )

    @classmethod
    def from_json(cls, path: str | pathlib.Path) -> TrainedLO:
        path = pathlib.Path(path)
        try:
            record = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise InputError(f"cannot read the trained-LO record {str(path)!r}: {err}") from None
        try:
            return cls.from_dict(record)
        except InputError as err:
            raise InputError(f"trained-LO record {str(path)!r}: {err}") from None


#: The fields of a record (:meth:`TrainedLO.to_dict`), every one required but ``elements``.
_FIELDS = tuple(f.name for f in dataclasses.fields(TrainedLO))


def _known(where: str, value: Mapping[str, Any], names: tuple[str, ...], optional: tuple[str, ...] = ()) -> None:
    """InputError naming the first missing or unknown key of ``value`` (the object ``where``);
    the ``optional`` names may be missing."""
    if missing := [n for n in names if n not in value and n not in optional]:
        raise InputError(f"{where} lacks the field(s) {missing}; required: {[n for n in names if n not in optional]}")
    if unknown := sorted(str(k) for k in value if k not in names):
        raise InputError(f"{where} has the unknown field(s) {unknown}; known: {list(names)}")


def _parameters(part: str, record: Mapping[str, Any], kind: type) -> Any:
    """``record[part]`` as a ``kind`` (Geometry, LOParams, CellParams): every field present, each
    one finite real number (a list would make a batch)."""
    value = record[part]
    if not isinstance(value, Mapping):
        raise InputError(f"{part} = {value!r} must be an object of {kind.__name__} fields")
    names = tuple(f.name for f in dataclasses.fields(kind))
    _known(part, value, names)
    return kind(**{n: real(f"{part}.{n}", value[n]) for n in names})


def _rmse(value: Any) -> float:
    """The passive fit's RMS residual (ml, ≥ 0), or NaN for a record without a passive fit
    (one predicted rather than trained, :mod:`lvenv.anatomy`)."""
    if isinstance(value, float) and math.isnan(value):
        return value
    return real("passive_rmse_ml", value, 0.0)


def _fractions(name: str, value: Any) -> dict[str, float]:
    """A congruency table: run name → relative RMS difference (a fraction, ≥ 0)."""
    if not isinstance(value, Mapping):
        raise InputError(f"{name} = {value!r} must be an object of run name → fraction ≥ 0")
    return {str(k): real(f"{name}[{k!r}]", v, 0.0) for k, v in value.items()}


def builtin(name: str) -> TrainedLO:
    """A shipped record, trained against the 3-D oracle: ``"normal"`` or ``"heart_failure"``
    (the single cell), ``"normal_series3"`` or ``"heart_failure_series3"`` (the 3-cell series
    heart, :data:`lvenv.presets.LO_MODELS`)."""
    path = DATA / f"trained_{name}.json"
    if not path.is_file():
        raise InputError(f"no trained LO record {name!r} in {DATA}; known: {sorted(p.stem[len('trained_'):] for p in DATA.glob('trained_*.json'))}")
    return TrainedLO.from_json(path)
