"""Patient records: a heart (geometry or LO parameters, fixed physiology) and weighted targets.

Built-in records ``normal`` and ``heart_failure`` use the N and HF presets (DESIGN §1.3, Table 3)
with **illustrative** targets at 60 bpm built from the paper's reported relative differences
(HF: EF −19 %, ET +21 %). The MRI data of the paper are not bundled.

======================  ======  ========  ==========  =================
record                  EF      ET (s)    IVRT (s)    pulse P (mmHg)
======================  ======  ========  ==========  =================
normal                  0.60    0.300     0.080       45
heart_failure           0.486   0.363     0.100       45
======================  ======  ========  ==========  =================

Records round-trip through JSON (:meth:`Patient.to_json`, :meth:`Patient.from_json`); a malformed
record raises ``ValueError`` naming the field.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
from typing import Any

from lvenv import presets
from lvenv.geometry import Geometry
from lvenv.params import CellParams, Circulation, Heart, LOParams, validate
from lvenv.units import mmhg_to_kpa

__all__ = ["OBS_NAMES", "Patient", "builtin", "BUILTIN", "resolve"]

#: Observation vector of the environment (internal units: 1, s, ml, kPa).
OBS_NAMES = ("EF", "IVCT", "ET", "IVRT", "filling_time", "EDV", "ESV", "P_ao_sys", "P_ao_dia", "P_ao_pulse", "P_ao_mean")


@dataclasses.dataclass(frozen=True)
class Patient:
    """A patient: the heart to identify around, target observations and their weights.

    ``targets`` and ``weights`` are keyed by :data:`OBS_NAMES` (internal units). A target
    without a weight gets weight 1.
    """

    name: str
    heart: Heart
    targets: dict[str, float]
    weights: dict[str, float] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"patient.name must be a non-empty string, got {self.name!r}")
        if not isinstance(self.heart, Heart):
            raise ValueError(f"patient.heart must be an lvenv.Heart, got {type(self.heart).__name__}")
        try:
            validate(self.heart)
        except ValueError as err:
            raise ValueError(f"patient.heart: {err}") from None
        if not self.targets:
            raise ValueError("patient.targets must name at least one observation")
        for group in ("targets", "weights"):
            for key, value in getattr(self, group).items():
                if key not in OBS_NAMES:
                    raise ValueError(f"patient.{group}[{key!r}] is not an observation; choose from {OBS_NAMES}")
                if not isinstance(value, (int, float)) or not math.isfinite(value):
                    raise ValueError(f"patient.{group}[{key!r}] = {value!r} must be a finite number")
        for key, value in self.targets.items():
            if value == 0.0:
                raise ValueError(f"patient.targets[{key!r}] = 0: targets enter as relative errors and must be non-zero")
        for key, value in self.weights.items():
            if value < 0.0:
                raise ValueError(f"patient.weights[{key!r}] = {value} must be ≥ 0")
            if key not in self.targets:
                raise ValueError(f"patient.weights[{key!r}] has no matching target")

    def weight(self, key: str) -> float:
        return float(self.weights.get(key, 1.0)) if key in self.targets else 0.0

    def to_dict(self) -> dict[str, Any]:
        h = self.heart
        return {
            "name": self.name,
            "geometry": dataclasses.asdict(h.geometry),
            "lo": dataclasses.asdict(h.lo),
            "cell": dataclasses.asdict(h.cell),
            "circulation": dataclasses.asdict(h.circulation),
            "targets": dict(self.targets),
            "weights": dict(self.weights),
        }

    def to_json(self, path: str | pathlib.Path | None = None) -> str:
        text = json.dumps(self.to_dict(), indent=2)
        if path is not None:
            pathlib.Path(path).write_text(text)
        return text

    @classmethod
    def from_dict(cls, record: dict[str, Any]) -> "Patient":
        if not isinstance(record, dict):
            raise ValueError(f"a patient record must be a JSON object, got {type(record).__name__}")
        for key in ("name", "geometry", "targets"):
            if key not in record:
                raise ValueError(f"patient record is missing the field {key!r}")
        known = {"name", "geometry", "lo", "cell", "circulation", "targets", "weights"}
        if extra := set(record) - known:
            raise ValueError(f"patient record has unknown field(s) {sorted(extra)}; known: {sorted(known)}")
        parts = {}
        for key, part_cls in (("geometry", Geometry), ("lo", LOParams), ("cell", CellParams), ("circulation", Circulation)):
            if key not in record:
                continue
            value = record[key]
            if not isinstance(value, dict):
                raise ValueError(f"patient.{key} must be an object of named numbers")
            names = {f.name for f in dataclasses.fields(part_cls)}
            if extra := set(value) - names:
                raise ValueError(f"patient.{key} has unknown field(s) {sorted(extra)}; known: {sorted(names)}")
            try:
                parts[key] = part_cls(**{k: float(v) for k, v in value.items()})
            except (TypeError, ValueError) as err:
                raise ValueError(f"patient.{key}: {err}") from None
        return cls(
            name=record["name"],
            heart=Heart(**parts),
            targets={k: _number(v, f"targets[{k!r}]") for k, v in dict(record["targets"]).items()},
            weights={k: _number(v, f"weights[{k!r}]") for k, v in dict(record.get("weights", {})).items()},
        )

    @classmethod
    def from_json(cls, text_or_path: str | pathlib.Path) -> "Patient":
        path = pathlib.Path(text_or_path) if not str(text_or_path).lstrip().startswith("{") else None
        text = path.read_text() if path is not None else str(text_or_path)
        try:
            record = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(f"patient record is not valid JSON: {err}") from None
        return cls.from_dict(record)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"patient.{where} = {value!r} must be a number")
    return float(value)


def builtin(name: str) -> Patient:
    """The built-in record ``"normal"`` or ``"heart_failure"`` (illustrative targets)."""
    if name == "normal":
        return Patient("normal", presets.normal(), {"EF": 0.60, "ET": 0.300, "IVRT": 0.080, "P_ao_pulse": mmhg_to_kpa(45.0)})
    if name == "heart_failure":
        return Patient("heart_failure", presets.heart_failure(), {"EF": 0.486, "ET": 0.363, "IVRT": 0.100, "P_ao_pulse": mmhg_to_kpa(45.0)})
    raise ValueError(f"unknown built-in patient {name!r}; choose from {BUILTIN}")


BUILTIN = ("normal", "heart_failure")


def resolve(patient: str | Patient | dict | list, num_envs: int) -> list[Patient]:
    """One Patient per member from a name, a record, a dict, or a list with one entry per member."""
    if isinstance(patient, (list, tuple)):
        if len(patient) != num_envs:
            raise ValueError(f"patient list has {len(patient)} records for num_envs = {num_envs}")
        return [resolve(p, 1)[0] for p in patient]
    if isinstance(patient, str):
        record = builtin(patient)
    elif isinstance(patient, dict):
        record = Patient.from_dict(patient)
    elif isinstance(patient, Patient):
        record = patient
    else:
        raise ValueError(f"patient must be a built-in name, a Patient, a dict or a list of them, got {type(patient).__name__}")
    return [record] * num_envs
