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

From images (DESIGN §5). A record's geometry may be the imaged, end-diastolic one: its ``unload``
field says how to unload it, ``{"strain": ε}`` (the paper's rule, `lvenv.anatomy.unload`),
``{"group": "N"}`` or ``{"group": "HF"}`` (the rule at that group's strain,
:data:`lvenv.anatomy.ED_STRAIN`) or ``{"edp": p}`` (kPa: the strain at which the predicted
passive curve reaches the imaged cavity volume at that end-diastolic pressure,
`lvenv.anatomy.unload_to_volume`). ``"lo": "regression"`` takes the LO maps the anatomy
regression predicts for the (unloaded) geometry (`lvenv.anatomy.from_geometry`: the regression of
the record's LO heart model, which also gives a multi-element heart its cells' onsets). What was done
is kept in :attr:`Patient.anatomy` (the imaged geometry, the strain, the maps' predictive sd),
which the record round-trips; the resolved record holds the unloaded geometry and the maps'
values, so reading it again does not unload twice.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from lvenv import presets
from lvenv.circulation import beat_period
from lvenv.geometry import Geometry
from lvenv.metrics import FRAME_NAMES, METRICS, N_FRAMES, OBS_NAMES
from lvenv.params import Arrangement, CellParams, Circulation, Heart, LOParams, validate
from lvenv.units import mmhg_to_kpa
from lvenv.validation import InputError, real, real_array

__all__ = ["OBS_NAMES", "Patient", "builtin", "BUILTIN", "resolve"]

_PHASES = ("IVCT", "ET", "IVRT", "filling_time")


@dataclasses.dataclass(frozen=True)
class Patient:
    """A patient: the heart to identify around, target observations and their weights.

    ``targets`` and ``weights`` are keyed by :data:`~lvenv.metrics.OBS_NAMES` (internal units).
    A target without a weight gets weight 1. Checked at construction (``ValueError`` naming the
    field, value and what is allowed):

    * every target lies in its metric's range (:attr:`lvenv.metrics.Metric.target`; e.g. EF in
      (0, 1], volumes, durations and pressures positive);
    * targets agree with each other where they must: ESV < EDV, P_ao_dia < P_ao_mean < P_ao_sys
      (of those given), P_ao_pulse < P_ao_sys, and the given phase durations fit into one beat
      at the heart's rate;
    * weights are finite and ≥ 0, and at least one target has a positive weight.
    """

    name: str
    heart: Heart
    targets: Mapping[str, float]
    weights: Mapping[str, float] = dataclasses.field(default_factory=dict)
    #: How the heart's geometry and maps came from an imaged anatomy (module docstring), else empty.
    anatomy: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"patient.name must be a non-empty string, got {self.name!r}")
        if not isinstance(self.heart, Heart):
            raise InputError(f"patient.heart must be an lvenv.Heart, got {type(self.heart).__name__}")
        try:
            validate(self.heart)
        except ValueError as err:
            raise InputError(f"patient.heart: {err}") from None
        for group in ("targets", "weights"):
            value = getattr(self, group)
            if not isinstance(value, Mapping):
                raise InputError(f"patient.{group} must map observation names to numbers, got {type(value).__name__}")
            for key in value:
                if key not in OBS_NAMES:
                    raise InputError(f"patient.{group}[{key!r}] is not an observation; choose from {OBS_NAMES}")
        if not self.targets:
            raise InputError("patient.targets must name at least one observation")
        targets = {}
        for key, value in self.targets.items():
            lo, hi = METRICS[key].target
            targets[key] = real(f"patient.targets[{key!r}]", value, lo, hi, lo_open=True)
        weights = {}
        for key, value in self.weights.items():
            if key not in targets:
                raise InputError(f"patient.weights[{key!r}] has no matching target")
            weights[key] = real(f"patient.weights[{key!r}]", value, 0.0)
        if not any(weights.get(k, 1.0) > 0.0 for k in targets):
            raise InputError(f"patient.weights = {weights} are all zero: at least one target needs a positive weight")
        object.__setattr__(self, "targets", targets)
        object.__setattr__(self, "weights", weights)
        self._check_consistency()

    def _check_consistency(self) -> None:
        t = self.targets

        def below(small: str, large: str) -> None:
            if small in t and large in t and not t[small] < t[large]:
                raise InputError(f"patient.targets[{small!r}] = {t[small]:g} must be below patient.targets[{large!r}] = {t[large]:g}")

        for small, large in (("ESV", "EDV"), ("P_ao_dia", "P_ao_sys"), ("P_ao_dia", "P_ao_mean"), ("P_ao_mean", "P_ao_sys"), ("P_ao_pulse", "P_ao_sys")):
            below(small, large)
        period = float(beat_period(self.heart.circulation))
        phases = {k: t[k] for k in _PHASES if k in t}
        if sum(phases.values()) > period:
            raise InputError(f"patient.targets {phases} (s) add up to more than one beat, {period:g} s at {float(self.heart.circulation.HR):g} bpm")

    def with_volume_trace(self, t, volumes, weight: float = 1.0) -> "Patient":
        """This patient with a volume trace among its targets: samples (``t`` s from the beat's
        onset, e.g. a cine MRI's phases after the R wave; ``volumes`` ml), at least 4, strictly
        increasing in [0, T), interpolated periodically onto the frames t_j = j T / 20 of
        :data:`lvenv.metrics.FRAME_NAMES`, each with weight ``weight``."""
        t, volumes = real_array("t", t), real_array("volumes", volumes)
        period = float(beat_period(self.heart.circulation))
        if t.ndim != 1 or t.shape != volumes.shape or len(t) < 4:
            raise InputError(f"t and volumes must be 1-D of one length ≥ 4, got shapes {t.shape} and {volumes.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0) and t[0] >= 0.0 and t[-1] < period):
            raise InputError(f"t = {t.tolist()} must increase strictly within [0, {period:g}) s (one beat at {float(self.heart.circulation.HR):g} bpm)")
        frames = np.interp(np.arange(N_FRAMES) * period / N_FRAMES, t, volumes, period=period)
        trace = {name: float(v) for name, v in zip(FRAME_NAMES, frames)}
        return dataclasses.replace(self, targets={**self.targets, **trace}, weights={**self.weights, **dict.fromkeys(trace, float(weight))})

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
            **({"elements": h.elements.to_dict()} if h.elements is not None else {}),
            **({"anatomy": dict(self.anatomy)} if self.anatomy else {}),
        }

    def to_json(self, path: str | pathlib.Path | None = None) -> str:
        text = json.dumps(self.to_dict(), indent=2)
        if path is not None:
            pathlib.Path(path).write_text(text)
        return text

    @classmethod
    def from_dict(cls, record: dict[str, Any]) -> "Patient":
        """A patient from a record: ``name``, ``geometry`` and ``targets`` required; ``lo``
        (numbers or ``"regression"``), ``unload``, ``cell``, ``circulation``, ``elements`` (the
        LO heart model, :meth:`lvenv.params.Arrangement.from_dict`; default the single cell),
        ``weights`` and ``anatomy`` optional (``null`` means the default; module docstring)."""
        if not isinstance(record, dict):
            raise InputError(f"a patient record must be a JSON object, got {type(record).__name__}")
        for key in ("name", "geometry", "targets"):
            if key not in record:
                raise InputError(f"patient record is missing the field {key!r}")
        known = {"name", "geometry", "lo", "unload", "cell", "circulation", "elements", "targets", "weights", "anatomy"}
        if extra := set(record) - known:
            raise InputError(f"patient record has unknown field(s) {sorted(extra)}; known: {sorted(known)}")
        parts = {}
        for key, part_cls in (("geometry", Geometry), ("lo", LOParams), ("cell", CellParams), ("circulation", Circulation)):
            value = record.get(key)
            if key == "lo" and value == "regression":
                continue
            if value is None:
                if key == "geometry":
                    raise InputError("patient.geometry must be an object of named numbers, got null")
                continue
            if not isinstance(value, dict):
                allowed = ' or "regression"' if key == "lo" else ""
                raise InputError(f"patient.{key} must be an object of named numbers{allowed}, got {value!r}")
            names = {f.name for f in dataclasses.fields(part_cls)}
            if extra := set(value) - names:
                raise InputError(f"patient.{key} has unknown field(s) {sorted(extra)}; known: {sorted(names)}")
            if key == "geometry" and (missing := names - set(value)):
                raise InputError(f"patient.geometry is missing the field(s) {sorted(missing)}")
            parts[key] = part_cls(**{k: _number(v, f"{key}.{k}") for k, v in value.items()})
        if record.get("elements") is not None:
            parts["elements"] = Arrangement.from_dict(record["elements"], "patient.elements")
        for key in ("targets", "weights", "anatomy"):
            if record.get(key) is not None and not isinstance(record[key], dict):
                raise InputError(f"patient.{key} must be an object, got {type(record[key]).__name__}")
        anatomy = dict(record.get("anatomy") or {})
        if record.get("unload") is not None:
            maps = None if record.get("lo") == "regression" else parts.get("lo", LOParams())  # None: the regression's, at each trial shape
            parts["geometry"], anatomy["unloading"] = _unloaded(parts["geometry"], record["unload"], maps)
        if record.get("lo") == "regression":
            from lvenv.anatomy import from_geometry, maps_note

            try:
                model = presets.model_of(parts.get("elements"))
            except InputError as err:
                raise InputError(f"patient.lo = 'regression': the record's {err}") from None
            trained = from_geometry(parts["geometry"], model=model)
            parts["lo"], parts["elements"], anatomy["maps"] = trained.lo, trained.elements, maps_note(trained)
        return cls(
            name=record["name"],
            heart=Heart(**parts),
            targets={k: _number(v, f"targets[{k!r}]") for k, v in (record["targets"] or {}).items()},
            weights={k: _number(v, f"weights[{k!r}]") for k, v in (record.get("weights") or {}).items()},
            anatomy=anatomy,
        )

    @classmethod
    def from_json(cls, text_or_path: str | pathlib.Path) -> "Patient":
        """A patient from JSON text (starting with ``{``) or from the path of a JSON file."""
        if isinstance(text_or_path, str) and text_or_path.lstrip().startswith(("{", "[")):
            text, source = text_or_path, "patient JSON text"
        elif isinstance(text_or_path, (str, pathlib.Path)):
            path = pathlib.Path(text_or_path)
            try:
                text = path.read_text()
            except OSError as err:
                raise InputError(f"cannot read the patient record {str(path)!r}: {err.strerror or err}") from None
            except UnicodeDecodeError as err:
                raise InputError(f"patient record {str(path)!r} is not UTF-8 JSON text ({err.reason} at byte {err.start})") from None
            source = f"patient record {str(path)!r}"
        else:
            raise InputError(f"expected JSON text or a path to a JSON file, got {type(text_or_path).__name__}")
        try:
            record = json.loads(text)
        except json.JSONDecodeError as err:
            raise InputError(f"{source} is not valid JSON: {err}") from None
        return cls.from_dict(record)


def _unloaded(imaged: Geometry, spec: Any, lo: LOParams | None) -> tuple[Geometry, dict[str, Any]]:
    """The unloaded geometry of an imaged one by a record's ``unload`` field (module docstring)
    and what was done, for :attr:`Patient.anatomy`. ``lo``: the maps whose passive curve an
    ``edp`` search uses (None: the regression's)."""
    from lvenv.anatomy import ED_STRAIN, unload, unload_to_volume

    ways = ("strain", "group", "edp")
    if not isinstance(spec, dict) or len(spec) != 1 or next(iter(spec)) not in ways:
        raise InputError(f"patient.unload = {spec!r} must be an object with one of the fields {ways}")
    (way, value), = spec.items()
    if way == "group":
        if value not in ED_STRAIN:
            raise InputError(f"patient.unload.group = {value!r} is not a group; choose from {sorted(ED_STRAIN)}")
        way, value = "strain", ED_STRAIN[value]
    value = _number(value, f"unload.{way}")
    if way == "strain":
        unloaded, strain = unload(imaged, real("patient.unload.strain", value, 0.0, 1.0)), value
    else:
        unloaded, strain = unload_to_volume(imaged, real("patient.unload.edp", value, 0.0, 10.0), lo=lo)
    return unloaded, {"imaged": dataclasses.asdict(imaged), "how": dict(spec), "strain": strain}


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"patient.{where} = {value!r} must be a number")
    return float(value)


def builtin(name: str, model: str = "single") -> Patient:
    """The built-in record ``"normal"`` or ``"heart_failure"`` (illustrative targets), its heart
    the preset of the LO heart ``model`` (:data:`lvenv.presets.LO_MODELS`)."""
    if name == "normal":
        return Patient("normal", presets.normal(model=model), {"EF": 0.60, "ET": 0.300, "IVRT": 0.080, "P_ao_pulse": mmhg_to_kpa(45.0)})
    if name == "heart_failure":
        return Patient("heart_failure", presets.heart_failure(model=model), {"EF": 0.486, "ET": 0.363, "IVRT": 0.100, "P_ao_pulse": mmhg_to_kpa(45.0)})
    raise InputError(f"unknown built-in patient {name!r}; choose from {BUILTIN}")


BUILTIN = ("normal", "heart_failure")


def resolve(patient: str | pathlib.Path | Patient | dict | list, num_envs: int) -> list[Patient]:
    """One Patient per member from a built-in name, a JSON file path or text, a Patient, a record
    dict, or a list with one of those per member."""
    if isinstance(patient, (list, tuple)):
        if len(patient) != num_envs:
            raise InputError(f"patient list has {len(patient)} records for num_envs = {num_envs}")
        return [resolve(p, 1)[0] for p in patient]
    if isinstance(patient, str) and patient in BUILTIN:
        record = builtin(patient)
    elif isinstance(patient, pathlib.Path) or (isinstance(patient, str) and (patient.lstrip().startswith("{") or patient.endswith(".json") or pathlib.Path(patient).is_file())):
        record = Patient.from_json(patient)
    elif isinstance(patient, str):
        raise InputError(f"patient = {patient!r} is neither a built-in patient {BUILTIN} nor a JSON record file")
    elif isinstance(patient, dict):
        record = Patient.from_dict(patient)
    elif isinstance(patient, Patient):
        record = patient
    else:
        raise InputError(f"patient must be a built-in name, a JSON path, a Patient, a dict or a list of them, got {type(patient).__name__}")
    return [record] * num_envs
