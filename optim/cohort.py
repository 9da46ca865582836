"""Cohort fitting from echo reports: every patient fitted together in one vector env.

Input: a CSV with one echo report per row (:func:`read_reports`). Required columns, units in
their names: ``id``, ``EF_pct``, ``ET_ms``, ``IVRT_ms``, ``SBP_mmHg``, ``DBP_mmHg``, ``HR_bpm``.
Optional: ``EDV_ml``, ``ESV_ml`` (more targets), the geometry ``Rb_mm``, ``L_mm``, ``Z_mm``,
``H_mm``, ``e``, ``C0_deg`` (any subset replaces the base heart's), and weights ``w_<target>``
(``w_EF``, ``w_ET``, ``w_IVRT``, ``w_DBP``, ``w_MAP``, ``w_EDV``, ``w_ESV``; default 1). Any other
column is carried through to the output unchanged. A bad row (a missing or non-numeric required
value, an impossible number, a duplicate id, targets that contradict each other) is reported
with its line number and reason and skipped; it never stops the others.

Cuff pressures → the model's aortic targets. A brachial cuff measures the systolic pressure of
the arm, which exceeds the central aortic systolic pressure by a pulse amplification that varies
between people (typically 5–15 mmHg), while diastolic and mean pressure change little along the
large arteries (Nichols WW, O'Rourke MF, *McDonald's Blood Flow in Arteries*, 6th ed. 2011,
ch. 24; Pauca AL et al., Hypertension 38:932, 2001). So the cuff values set two targets:

    P_ao_dia  = DBP,
    P_ao_mean = DBP + 0.412 (SBP − DBP)      (Meaney E et al., Heart 84:64, 2000),

and the central systolic pressure is left free (reported as ``fit_SBP_central_mmHg``).
:func:`cuff_from_central` is the inverse used by ``scripts/make_cohort.py``.

The heart: the base heart (``presets.normal(model=CohortOptions.model)``, the trained LO maps of
the single cell by default, or of a multi-element LO heart, :data:`lvenv.presets.LO_MODELS`,
which runs the fixed scheme; the amortised posterior flags its rows as not covered, and
``refine`` samples them by MCMC) at the row's heart rate,
which is a per-member parameter of the LO heart (the beat period is 60 / HR), and with the row's
geometry where given (the unloaded shape, as :class:`lvenv.geometry.Geometry` has it). A row
with a geometry gets the LO maps of its own anatomy from the anatomy regression of the base
heart's model (:func:`lvenv.anatomy.from_geometry`, and a multi-element heart its cells'
onsets too; ``CohortOptions.maps = "regression"``, the default), or keeps the base heart's
(``"base"``); the output's ``maps`` column says which, with any
extrapolation of the regression (a geometry outside its sampled box) or clipped parameter.
Without an artefact to load (:data:`lvenv.anatomy.ARTEFACT_ENV` naming a missing file) the
regression choice is refused before any fit. The fitted parameters are :data:`lvenv.identification.DEFAULT_ACTION_PARAMS`
(τ2, Sa, R2, R3, C, Cat) inside their identification bounds.

Fitting (:func:`fit_reports`): ``slots`` patients at a time, each with ``candidates`` members of
one vector env (members = patients × candidates), one env step per round for all of them. Each
patient has its own CMA-ES (:mod:`optim.cmaes`, λ = candidates, IPOP restarts) started from the
base heart's values and seeded from its ``id``. A patient's search stops when its best mismatch
falls below ``stop_mismatch``, when its CMA-ES stops for good, or at ``budget`` evaluations; its
members are then refilled with the next report (:meth:`LVHeartVectorEnv.replace_patients`), so
the step never changes shape and is compiled once. Each env step runs at most ``max_beats``
beats per member from the member's warm state (a member not yet at steady state carries on from
there in its next step); before a fit is reported, its best point is *confirmed*: evaluated on
all the patient's members until one reaches the steady-state criterion of
:func:`lvenv.simulate` (``rtol``), for at most ``confirm_steps`` more steps. The reported
metrics, mismatch and ``status`` are those of the confirmed steady state; a best point that
never settles is reported ``not_converged``, one that fails with its failure status.

A patient's fit depends only on its own report, the options and its seed: never on the other
patients, on its slot, or on how the cohort was split (the member computations are elementwise
and padded, :mod:`lvenv.devices`). So a cohort split over Dask workers (:func:`run_cohort`)
gives the same fits, and a resumed run refits nothing.

Output (:func:`output_columns`): ``id``, the carried-through columns,
the fitted parameters (internal units, in the column names), ``mismatch`` (weighted mean relative
error over the row's targets, a fraction), ``mismatch_<target>`` (abs(relative error) per target),
the model's values at the fit (``fit_<column>``), the unmeasured filling pressures
``fit_EDP_mmHg`` and ``fit_P_at_mean_mmHg`` (kept within 4–25 mmHg by the objective's
plausibility bands unless ``CohortOptions.plausibility`` is False), ``evaluations``, ``stop``, ``status``,
``maps`` and the input ``line``. Rows are written as patients finish; failed values are empty cells, never zeros.

Posterior (``posterior=PosteriorOptions()``, ``lvenv cohort --posterior amortised``): before the
fits, every pending row's amortised posterior (:func:`optim.identify.identify_patients`, one
batched pass) adds, per fitted parameter, ``<column>_post_median``, ``<column>_post_q05`` and
``<column>_post_q95`` (``<column>`` its fitted column, e.g. ``tau2_s_post_median``: the median
and the 90 % equal-tailed interval, internal units), then ``post_sampler`` (``amortised``,
``importance`` where ``PosteriorOptions.importance`` reweights the flow's draws, or the MCMC
sampler of a refined row), ``post_refined`` (1 or 0), ``post_ood`` (1 if the amortised answer is
flagged: outside the training distribution, unreliable importance weights, or a row the estimator
does not cover, e.g. one with EDV_ml or a geometry outside the anatomy box) and
``post_ood_reason``. With ``refine`` the flagged rows get the
MCMC posterior (:func:`optim.identify.posterior`, minutes each) instead. A row's draws depend
on the seed and on the batch it was drawn in, so a resumed run draws its remaining rows afresh.

Length: over 600 lines because reading reports, the vectorised cohort fit and the resumable
output are one pipeline around one row format (:func:`output_columns`); splitting them would
spread that format over modules.
"""

from __future__ import annotations

import codecs
import collections
import csv
import dataclasses
import hashlib
import io
import json
import math
import os
import time
import warnings
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lvenv import archive, presets
from lvenv.anatomy import ExtrapolationWarning, Regression, from_geometry, load_regression, maps_note
from lvenv.env.core import default_scheme
from lvenv.env.vector import info_metrics
from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.lo_model import check_scheme
from lvenv.metrics import FRAME_NAMES, METRICS, OBS_NAMES, Metric
from lvenv.params import Heart, ranges
from lvenv.patients import Patient
from lvenv.plausibility import FILLING
from lvenv.simulation import SCHEMES
from lvenv.status import EF_MIN, is_usable
from lvenv.units import kpa_to_mmhg, mmhg_to_kpa
from lvenv.validation import InputError, choice, integer, real
from optim.cluster import client
from optim.cmaes import CmaEs, CmaOptions
from optim.fit import make_env
from optim.minimize import unit_bounds

__all__ = [
    "FORM_FACTOR", "REQUIRED", "TARGETS", "GEOMETRY_COLUMNS", "MAPS", "maps_label", "CohortOptions", "Report", "BadRow",
    "Reports", "read_reports", "cuff_targets", "cuff_from_central", "parameter_column", "output_columns",
    "fit_reports", "run_cohort", "summarise", "distribution", "patient_seed", "CohortError", "PosteriorOptions", "posterior_columns",
]

#: Fraction of the pulse pressure above DBP at which the mean pressure lies (Meaney et al. 2000).
FORM_FACTOR = 0.412

REQUIRED = ("id", "EF_pct", "ET_ms", "IVRT_ms", "SBP_mmHg", "DBP_mmHg", "HR_bpm")


@dataclasses.dataclass(frozen=True)
class Target:
    """One report target: its label (``w_<label>``, ``mismatch_<label>``), model observation and
    column, in the display units of :data:`lvenv.metrics.METRICS` (``fit_<column>`` in the output)."""

    label: str
    obs: str
    column: str

    @property
    def metric(self) -> Metric:
        return METRICS[self.obs]


#: The targets a report can set. DBP and MAP come from the cuff pressures (module docstring).
TARGETS = (
    Target("EF", "EF", "EF_pct"),
    Target("ET", "ET", "ET_ms"),
    Target("IVRT", "IVRT", "IVRT_ms"),
    Target("DBP", "P_ao_dia", "DBP_mmHg"),
    Target("MAP", "P_ao_mean", "MAP_mmHg"),
    Target("EDV", "EDV", "EDV_ml"),
    Target("ESV", "ESV", "ESV_ml"),
)
_CUFF = ("DBP", "MAP")

#: Optional geometry columns → :class:`lvenv.geometry.Geometry` fields.
GEOMETRY_COLUMNS = {"Rb_mm": "Rb", "L_mm": "L", "Z_mm": "Z", "H_mm": "H", "e": "e", "C0_deg": "C0"}
#: Where a row with a geometry takes its LO maps from (module docstring).
MAPS = ("regression", "base")
_KNOWN = set(REQUIRED) | {"EDV_ml", "ESV_ml"} | set(GEOMETRY_COLUMNS) | {f"w_{t.label}" for t in TARGETS}


class CohortError(InputError):
    """A cohort file that cannot be used at all (missing columns, an output of other options)."""


def cuff_targets(sbp_mmhg: float, dbp_mmhg: float) -> tuple[float, float]:
    """Cuff SBP, DBP (mmHg) → the model's targets (P_ao_dia, P_ao_mean) in kPa (module docstring)."""
    return float(mmhg_to_kpa(dbp_mmhg)), float(mmhg_to_kpa(dbp_mmhg + FORM_FACTOR * (sbp_mmhg - dbp_mmhg)))


def cuff_from_central(p_dia_kpa: float, p_mean_kpa: float) -> tuple[float, float]:
    """The cuff (SBP, DBP) in mmHg that :func:`cuff_targets` maps to these central pressures."""
    dia, mean = float(kpa_to_mmhg(p_dia_kpa)), float(kpa_to_mmhg(p_mean_kpa))
    return dia + (mean - dia) / FORM_FACTOR, dia


def parameter_column(name: str) -> str:
    """Output column of a fitted parameter, units in the name: ``tau2_s``, ``R3_kPa_s_per_ml``."""
    units = ACTION_BOUNDS[name].units
    if units == "1":
        return name
    return f"{name}_" + units.replace("·", "_").replace("/", "_per_")


@dataclasses.dataclass(frozen=True)
class Report:
    """One fit to do: its input line, id, the patient, the carried-through columns and, for
    constrained fits (`optim.identify.profile`), parameters held fixed at the given values."""

    line: int
    id: str
    patient: Patient
    extra: dict[str, str]
    fixed: Mapping[str, float] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class BadRow:
    """A row that was skipped: its input line, id (if any) and the reason."""

    line: int
    id: str
    reason: str


@dataclasses.dataclass(frozen=True)
class Reports:
    """What :func:`read_reports` found: good rows, bad rows and the extra column names."""

    rows: list[Report]
    bad: list[BadRow]
    extra_columns: list[str]


def _value(row: Mapping[str, str], column: str, required: bool) -> float | None:
    text = (row.get(column) or "").strip()
    if not text:
        if required:
            raise InputError(f"{column} is missing")
        return None
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{column} = {text!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{column} = {text!r} must be finite")
    return value


def _display_range(column: str, value: float, metric: Metric) -> None:
    """``value`` (display units) inside the metric's target range, else InputError in the CSV's terms."""
    lo, hi = (float(metric.to_display(b)) for b in metric.target)
    real(column, value, lo, hi, lo_open=True)


def _in_columns(message: str) -> str:
    """A message about `Geometry` fields in the CSV's column names (the same mm and degrees)."""
    for column, field in GEOMETRY_COLUMNS.items():
        message = message.replace(f"geometry.{field} ", f"{column} ")
    return message


def _patient(row: Mapping[str, str], base: Heart, regression: Regression | None = None) -> Patient:
    """The patient of one report row (module docstring); InputError naming the column, in the
    CSV's own units, on bad input. ``regression``: the anatomy regression of the base heart's
    model that gives a row with a geometry its maps, and a multi-element heart its onsets (None:
    the base heart's)."""
    v = {c: _value(row, c, c in REQUIRED) for c in (*REQUIRED[1:], "EDV_ml", "ESV_ml")}
    if not EF_MIN * 100.0 < v["EF_pct"] <= 100.0:
        raise InputError(f"EF_pct = {v['EF_pct']:g} must lie in ({100 * EF_MIN:g}, 100] (a percentage; 0.6 would be 0.6 %)")
    hr_lo, hr_hi = ranges()["HR"][:2]
    real("HR_bpm", v["HR_bpm"], hr_lo, hr_hi)
    for t in TARGETS:
        if t.label not in _CUFF and t.column != "EF_pct" and v[t.column] is not None:
            _display_range(t.column, v[t.column], t.metric)
    _display_range("SBP_mmHg", v["SBP_mmHg"], METRICS["P_ao_sys"])
    _display_range("DBP_mmHg", v["DBP_mmHg"], METRICS["P_ao_dia"])
    if not v["DBP_mmHg"] < v["SBP_mmHg"]:
        raise InputError(f"DBP_mmHg = {v['DBP_mmHg']:g} must be below SBP_mmHg = {v['SBP_mmHg']:g}")
    if v["ESV_ml"] is not None and v["EDV_ml"] is not None and not v["ESV_ml"] < v["EDV_ml"]:
        raise InputError(f"ESV_ml = {v['ESV_ml']:g} must be below EDV_ml = {v['EDV_ml']:g}")
    period_ms = 60e3 / v["HR_bpm"]
    if v["ET_ms"] + v["IVRT_ms"] > period_ms:
        raise InputError(f"ET_ms + IVRT_ms = {v['ET_ms'] + v['IVRT_ms']:g} ms must not exceed one beat, {period_ms:g} ms at HR_bpm = {v['HR_bpm']:g}")
    targets = {t.obs: float(t.metric.from_display(v[t.column])) for t in TARGETS if t.label not in _CUFF and v[t.column] is not None}
    targets["P_ao_dia"], targets["P_ao_mean"] = cuff_targets(v["SBP_mmHg"], v["DBP_mmHg"])
    weights = {}
    for t in TARGETS:
        w = _value(row, f"w_{t.label}", False)
        if w is not None:
            if t.obs not in targets:
                raise InputError(f"w_{t.label} = {w:g} weights a target the row does not give ({t.column})")
            weights[t.obs] = real(f"w_{t.label}", w, 0.0)
    if weights and not any(weights.get(k, 1.0) > 0.0 for k in targets):
        raise InputError(f"{', '.join(f'w_{t.label}' for t in TARGETS if t.obs in weights)} are all zero: at least one target needs a positive weight")
    geometry = {field: _value(row, column, False) for column, field in GEOMETRY_COLUMNS.items()}
    heart = base.replace(HR=v["HR_bpm"])
    anatomy = {}
    if any(g is not None for g in geometry.values()):
        try:
            shape = dataclasses.replace(base.geometry, **{k: g for k, g in geometry.items() if g is not None})
        except InputError as err:
            raise InputError(_in_columns(str(err))) from None
        heart = dataclasses.replace(heart, geometry=shape)
        if regression is not None:
            with warnings.catch_warnings():  # the row's `maps` cell reports them
                warnings.simplefilter("ignore", ExtrapolationWarning)
                trained = from_geometry(shape, regression, model=presets.model_of(base.elements))
            heart = dataclasses.replace(heart, lo=trained.lo, elements=trained.elements)
            anatomy["maps"] = maps_note(trained)
    return Patient(str(row["id"]).strip(), heart, targets, weights, anatomy)


def maps_label(patient: Patient) -> str:
    """The output's ``maps`` cell: ``base``, or ``regression`` with any extrapolation (CSV units)."""
    note = patient.anatomy.get("maps")
    if not note:
        return "base"
    flags = [_in_columns(m) for m in (*note["outside_box"], *note["clipped"])]
    return "regression" + (f" ({'; '.join(flags)})" if flags else "")


def _text(path: Path) -> str:
    """A report file's text: UTF-8 (a byte-order mark is dropped) or UTF-16 with its mark;
    :class:`CohortError` naming the file and what to do for anything else (a binary file,
    another encoding)."""
    try:
        data = path.read_bytes()
    except OSError as err:
        raise CohortError(f"cannot read the report file {str(path)!r}: {err.strerror or err}") from None
    utf16 = data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE))
    if not utf16 and b"\x00" in data:
        raise CohortError(f"{str(path)!r} is not a text file (it holds NUL bytes); save the reports as CSV text")
    try:
        return data.decode("utf-16" if utf16 else "utf-8-sig")
    except UnicodeDecodeError as err:
        line = data[:err.start].count(b"\n") + 1
        raise CohortError(f"{str(path)!r} is not UTF-8 text: byte 0x{data[err.start]:02x} on line {line} ({err.reason}); "
                          "save it as 'CSV UTF-8' (a Latin-1 or Windows-1252 export is the usual cause)") from None


def _separator_hint(path: Path, header: str) -> str:
    """Why a header lacks the required columns, when the file uses another separator than commas."""
    for separator, name, cause in ((";", "semicolons", "a spreadsheet in a locale whose decimal mark is a comma saves CSV that way"),
                                   ("\t", "tabs", "a spreadsheet's 'Unicode text' or TSV export")):
        if header.count(separator) > header.count(","):
            return (f"{str(path)!r} separates its fields by {name}, not commas ({cause}); save it as CSV with commas between "
                    "fields and points as the decimal mark")
    return ""


def read_reports(path: str | os.PathLike[str], base: Heart | None = None, maps: str = "regression") -> Reports:
    """Parse a report CSV (module docstring). A file without a required column raises
    :class:`CohortError` naming the missing columns; a bad row is listed in ``bad``. ``maps``:
    where a row with a geometry takes its LO maps from (:data:`MAPS`)."""
    base = presets.normal() if base is None else base
    maps = choice("maps", maps, MAPS)
    path = Path(path)
    text = _text(path)
    with io.StringIO(text, newline="") as handle:
        reader = csv.DictReader(handle)
        try:
            columns = [c.strip() for c in (reader.fieldnames or [])]
        except csv.Error as err:
            raise CohortError(f"{str(path)!r}: the header on line 1 is not CSV ({err})") from None
        if missing := [c for c in REQUIRED if c not in columns]:
            hint = _separator_hint(path, text.partition("\n")[0])
            raise CohortError(hint or f"{str(path)!r} lacks the required column(s) {missing}; required: {list(REQUIRED)}")
        if len(set(columns)) != len(columns):
            raise CohortError(f"{str(path)!r} repeats a column name: {columns}")
        reader.fieldnames = columns
        extra_columns = [c for c in columns if c not in _KNOWN]
        if clash := sorted(set(extra_columns) & set(output_columns((), posterior=True))):
            raise CohortError(f"{str(path)!r} has the column(s) {clash}, which the output writes itself; rename them")
        regression = None
        if maps == "regression" and set(columns) & set(GEOMETRY_COLUMNS):
            try:
                regression = load_regression(model=presets.model_of(base.elements))
            except InputError as err:
                raise CohortError(f"{str(path)!r} has geometry columns, whose maps come from the anatomy regression: {err}; "
                                  "or fit them with the base heart's maps (maps = 'base', `lvenv cohort --maps base`)") from None
        rows, bad, seen = [], [], {}
        for row in _rows_of(reader, path, bad):
            line = reader.line_num
            rid = (row.get("id") or "").strip()
            try:
                if None in row:
                    raise InputError(f"the row has {len(columns) + len(row[None])} fields for {len(columns)} columns")
                if None in row.values():
                    raise InputError(f"the row has {sum(v is not None for v in row.values())} fields for {len(columns)} columns")
                if not rid:
                    raise InputError("id is missing")
                if rid in seen:
                    raise InputError(f"id {rid!r} repeats the row on line {seen[rid]}")
                patient = _patient(row, base, regression)
            except (InputError, ValueError) as err:
                bad.append(BadRow(line, rid, str(err)))
                continue
            seen[rid] = line
            rows.append(Report(line, rid, patient, {c: row.get(c) or "" for c in extra_columns}))
    return Reports(rows, bad, extra_columns)


def _rows_of(reader: csv.DictReader, path: Path, bad: list[BadRow]) -> Iterator[dict[str, str]]:
    """The reader's rows; a row the csv module cannot parse (an unclosed quote runs to the end of
    the file) becomes a bad row and ends the file."""
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as err:
            bad.append(BadRow(reader.line_num, "", f"not CSV from here on ({err}); the rest of {str(path)!r} is skipped"))
            return
        yield row


@dataclasses.dataclass(frozen=True)
class CohortOptions:
    """How a cohort is fitted (module docstring). Defaults (ours) reach the issue-13 acceptance
    on the synthetic cohort of ``scripts/make_cohort.py`` on a 2-core CPU (README, "Fitting patients and cohorts")."""

    candidates: int = 8  # members per patient: CMA-ES λ
    slots: int = 128  # patients fitted at once
    budget: int = 640  # evaluations per patient, at most (confirmation not counted)
    stop_mismatch: float = 0.01  # a patient's search stops below this mismatch (fraction)
    sigma0: float = 0.25  # CMA-ES initial step, unit-cube units
    steps_per_beat: int = 500  # of the fixed scheme only
    scheme: str | None = None  # the env's integration scheme (lvenv.simulation.SCHEMES); None: the model's (lvenv.env.core.default_scheme)
    max_beats: int = 12  # beats per member and env step
    confirm_steps: int = 10  # env steps to confirm the best point's steady state, at most
    rtol: float = 1e-4  # steady-state criterion (lvenv.simulate)
    plausibility: bool = True  # the filling-pressure bands in the objective (lvenv.plausibility)
    maps: str = "regression"  # a row with a geometry: its anatomy's maps ("regression") or the base heart's ("base")
    seed: int = 0
    model: str = "single"  # the base heart's LO heart model (lvenv.presets.LO_MODELS)

    def __post_init__(self) -> None:
        integer("candidates", self.candidates, 2)
        integer("slots", self.slots, 1)
        integer("budget", self.budget, self.candidates)
        real("stop_mismatch", self.stop_mismatch, 0.0, 1.0)
        real("sigma0", self.sigma0, 0.0, 1.0, lo_open=True)
        integer("steps_per_beat", self.steps_per_beat, 10)
        base = self.base_heart()  # refuses a model not in presets.LO_MODELS, naming it
        if self.scheme is None:
            object.__setattr__(self, "scheme", default_scheme(base))
        choice("scheme", self.scheme, SCHEMES)
        check_scheme(base.elements, self.scheme)
        integer("max_beats", self.max_beats, 1)
        integer("confirm_steps", self.confirm_steps, 1)
        real("rtol", self.rtol, 0.0, 1.0, lo_open=True)
        if not isinstance(self.plausibility, bool):
            raise InputError(f"plausibility = {self.plausibility!r} must be True or False")
        choice("maps", self.maps, MAPS)
        integer("seed", self.seed, 0)

    def base_heart(self) -> Heart:
        """The base heart: the N preset of the LO heart :attr:`model`."""
        return presets.normal(model=self.model)

    def to_dict(self) -> dict[str, Any]:
        """The options as the output's record holds them; ``model`` only if not the single cell,
        so that outputs written before the field existed still resume."""
        out = dataclasses.asdict(self)
        if self.model == "single":
            del out["model"]
        return out


def patient_seed(seed: int, rid: str) -> int:
    """The CMA-ES seed of the patient ``rid``: a function of the run's seed and the id only."""
    return int(np.random.SeedSequence([seed, zlib.crc32(rid.encode())]).generate_state(1)[0])


class _Fit:
    """One patient: its CMA-ES search, then the confirmation of its best point (module docstring)."""

    def __init__(self, report: Report, options: CohortOptions) -> None:
        self.report, self.options = report, options
        self.space = ParameterSpace.for_names([n for n in DEFAULT_ACTION_PARAMS if n not in report.fixed])
        heart = report.patient.heart
        u0 = self.space.to_unit(self.space.clip(np.array([float(heart.get(n)) for n in self.space.names])))
        cma_options = CmaOptions(sigma0=options.sigma0, restarts=10**6)
        self.opt = CmaEs(unit_bounds(self.space), options.candidates, patient_seed(options.seed, report.id), cma_options, x0=u0)
        self.best_u: np.ndarray | None = None
        self.best = (math.inf, np.full(len(OBS_NAMES), np.nan), "failed")  # mismatch, observation, status
        self.last_status = "failed"
        self.stop: str | None = None
        self.confirming = 0
        self.result: dict[str, Any] | None = None
        self._asked: np.ndarray | None = None

    def physical(self, u: np.ndarray) -> np.ndarray:
        """Unit-cube points of the free parameters → (n, 6) values of every action parameter."""
        free = dict(zip(self.space.names, np.atleast_2d(self.space.from_unit(u)).T))
        n = len(np.atleast_2d(u))
        return np.stack([free[name] if name in free else np.full(n, float(self.report.fixed[name])) for name in DEFAULT_ACTION_PARAMS], axis=1)

    def points(self) -> np.ndarray | None:
        """The (candidates, k) unit-cube points of the next step; None once the fit is over."""
        lam = self.options.candidates
        if self.stop is None:
            u = self.opt.ask(self.options.budget - self.opt.evaluations)
            if len(u):
                self._asked = u
                return np.concatenate([u, np.repeat(u[-1:], lam - len(u), axis=0)])
            self.stop = "budget" if self.opt.evaluations >= self.options.budget else "optimiser"
        if self.best_u is None:
            self._finish(math.nan, np.full(len(OBS_NAMES), np.nan), self.last_status)
        elif self.best[2] == "ok":  # the best point already reached steady state in its step
            self._finish(*self.best)
        if self.result is not None:
            return None
        return np.repeat(self.best_u[None], lam, axis=0)

    def absorb(self, f: np.ndarray, mismatch: np.ndarray, obs: np.ndarray, status: np.ndarray) -> bool:
        """Take this patient's slice of a step's results; True when the fit is over."""
        usable = is_usable(status) & np.isfinite(mismatch)
        if self._asked is not None:
            q = len(self._asked)
            self.opt.tell(self._asked, f[:q], usable[:q])
            score = np.where(usable[:q], mismatch[:q], np.inf)
            i = int(np.argmin(score))
            if score[i] < self.best[0]:
                self.best_u, self.best = self._asked[i].copy(), (float(mismatch[i]), obs[i].copy(), str(status[i]))
            if not usable[:q].all():
                self.last_status = str(status[:q][~usable[:q]][0])
            self._asked = None
            if self.best[0] < self.options.stop_mismatch:
                self.stop = "tolerance"
            elif self.opt.evaluations >= self.options.budget:
                self.stop = "budget"
            return False
        self.confirming += 1
        settled = usable & (status == "ok")
        if settled.any():
            i = int(np.argmax(settled))
            self._finish(float(mismatch[i]), obs[i], "ok")
        elif not usable.any():
            self._finish(math.nan, np.full(len(OBS_NAMES), np.nan), str(status[0]))
        elif self.confirming >= self.options.confirm_steps:
            i = int(np.argmax(usable))
            self._finish(float(mismatch[i]), obs[i], "not_converged")
        return self.result is not None

    def _finish(self, mismatch: float, obs: np.ndarray, status: str) -> None:
        patient = self.report.patient
        x = self.physical(self.best_u)[0] if self.best_u is not None else np.full(len(DEFAULT_ACTION_PARAMS), np.nan)
        self.result = {
            "id": self.report.id,
            "line": self.report.line,
            "extra": self.report.extra,
            "parameters": dict(zip(DEFAULT_ACTION_PARAMS, map(float, x))),
            "observation": {k: float(v) for k, v in zip(OBS_NAMES, obs) if k not in FRAME_NAMES or math.isfinite(v)},  # frames if recorded
            "targets": dict(patient.targets),
            "mismatch": float(mismatch),
            "evaluations": self.opt.evaluations,
            "stop": self.stop or "failed",
            "status": status,
            "maps": maps_label(patient),
        }


def _relative_errors(result: Mapping[str, Any]) -> dict[str, float]:
    obs, targets = result["observation"], result["targets"]
    return {k: abs(obs[k] - t) / t for k, t in targets.items()}


def fit_reports(reports: Sequence[Report], options: CohortOptions | None = None, *, on_done: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Fit every report (module docstring); returns one result dict per report in finishing order
    and calls ``on_done(result)`` as each patient finishes."""
    options = options or CohortOptions()
    if not reports:
        return []
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    lam = options.candidates
    slots = min(options.slots, len(reports))
    queue = collections.deque(reports)
    venv = make_env([r.patient for r in reports[:slots] for _ in range(lam)], slots * lam, options.steps_per_beat, options.max_beats, options.rtol, options.scheme,
                    options.plausibility)
    env = venv.unwrapped
    env.start_cold()  # every member gets its patient below, before the first step
    fits: list[_Fit | None] = [None] * slots
    actions = np.repeat(space.from_unit(np.full((1, space.dimension), 0.5)), slots * lam, axis=0)
    results: list[dict[str, Any]] = []

    def done(s: int) -> None:
        results.append(fits[s].result)
        if on_done is not None:
            on_done(fits[s].result)
        fits[s] = None

    try:
        while queue or any(fits):
            members, incoming = [], []
            for s in range(slots):
                while fits[s] is not None or queue:
                    fresh = fits[s] is None
                    if fresh:
                        fits[s] = _Fit(queue.popleft(), options)
                    if (u := fits[s].points()) is None:
                        done(s)
                        continue
                    actions[s * lam:(s + 1) * lam] = fits[s].physical(u)
                    if fresh:
                        members.extend(range(s * lam, (s + 1) * lam))
                        incoming.extend([fits[s].report.patient] * lam)
                    break
            if not any(fits):
                break
            if members:
                env.replace_patients(members, incoming)
            _, reward, _, _, info = venv.step(env.config.actions.to_action(actions))
            obs = info_metrics(info)
            for s, fit in enumerate(fits):
                sl = slice(s * lam, (s + 1) * lam)
                if fit is not None and fit.absorb(-reward[sl], info["mismatch"][sl], obs[sl], info["status"][sl]):
                    done(s)
    finally:
        venv.close()
    return results


#: Unmeasured filling pressures reported per fit (the plausibility bands' quantities).
_FILLING = tuple(b.metric for b in FILLING)


def output_columns(extra_columns: Sequence[str], posterior: bool = False) -> list[str]:
    """The output CSV's columns for a report file with these carried-through columns, with the
    posterior's (:func:`posterior_columns`) before ``line`` if ``posterior``."""
    return [
        "id", *extra_columns, *(parameter_column(n) for n in DEFAULT_ACTION_PARAMS), "mismatch",
        *(f"mismatch_{t.label}" for t in TARGETS), *(f"fit_{t.column}" for t in TARGETS), "fit_SBP_central_mmHg",
        *(f"fit_{m}_mmHg" for m in _FILLING), "evaluations", "stop", "status", "maps", *(posterior_columns() if posterior else ()), "line",
    ]


#: Suffixes of a parameter's posterior columns: its median and its 90 % interval's ends (5 % and 95 % quantiles).
_POSTERIOR_STATS = ("post_median", "post_q05", "post_q95")


def posterior_columns() -> list[str]:
    """The posterior's output columns (module docstring)."""
    return [*(f"{parameter_column(n)}_{stat}" for n in DEFAULT_ACTION_PARAMS for stat in _POSTERIOR_STATS),
            "post_sampler", "post_refined", "post_ood", "post_ood_reason"]


@dataclasses.dataclass(frozen=True)
class PosteriorOptions:
    """The posterior beside each fit (module docstring): ``n_samples`` draws per row, ``importance``
    flow draws per row reweighted by the exact posterior where > 0 (:func:`optim.identify.amortised`),
    and with ``refine`` the MCMC posterior (:func:`optim.identify.posterior` with ``mcmc`` as
    keywords) for the flagged rows."""

    n_samples: int = 1000
    refine: bool = False
    seed: int = 0
    mcmc: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    importance: int = 0

    def __post_init__(self) -> None:
        integer("n_samples", self.n_samples, 8)
        if not isinstance(self.refine, bool):
            raise InputError(f"refine = {self.refine!r} must be True or False")
        integer("seed", self.seed, 0)
        if integer("importance", self.importance, 0) and self.importance < self.n_samples:
            raise InputError(f"importance = {self.importance}: give 0 or at least n_samples = {self.n_samples} proposals per row")

    def to_dict(self) -> dict[str, Any]:
        """JSON of the options; ``importance`` only where it is used, so that an output written
        before the option existed still resumes."""
        record = {**dataclasses.asdict(self), "mcmc": dict(self.mcmc)}
        if not self.importance:
            del record["importance"]
        return record


def _posterior_cells(identified: Any) -> dict[str, str]:
    """The posterior columns of one row from its :class:`optim.identify.Identified`."""
    post = identified.posterior
    row = {}
    for n in DEFAULT_ACTION_PARAMS:
        values = (math.nan,) * 3 if post is None else (post.median[n], *post.interval_90[n])
        row.update({f"{parameter_column(n)}_{stat}": _cell(v) for stat, v in zip(_POSTERIOR_STATS, values)})
    row.update(post_sampler="" if post is None else post.sampler, post_refined=str(int(identified.refined)), post_ood=str(int(bool(identified.flag))),
               post_ood_reason=identified.flag)
    return row



def _cell(value: float, digits: int = 6) -> str:
    return "" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def _row(result: Mapping[str, Any]) -> dict[str, str]:
    errors = _relative_errors(result)
    obs = result["observation"]
    row = {"id": result["id"], **result["extra"]}
    row.update({parameter_column(n): _cell(v) for n, v in result["parameters"].items()})
    row["mismatch"] = _cell(result["mismatch"])
    for t in TARGETS:
        row[f"mismatch_{t.label}"] = _cell(errors.get(t.obs, math.nan)) if math.isfinite(result["mismatch"]) else ""
        row[f"fit_{t.column}"] = _cell(t.metric.to_display(obs[t.obs]))
    row["fit_SBP_central_mmHg"] = _cell(METRICS["P_ao_sys"].to_display(obs["P_ao_sys"]))
    row.update({f"fit_{m}_mmHg": _cell(METRICS[m].to_display(obs[m])) for m in _FILLING})
    row.update(evaluations=str(result["evaluations"]), stop=result["stop"], status=result["status"], maps=result["maps"], line=str(result["line"]))
    return row


def _chunks(items: Sequence[Report], size: int) -> Iterator[list[Report]]:
    for start in range(0, len(items), size):
        yield list(items[start:start + size])


def _fit_chunk(reports: list[Report], options: CohortOptions) -> list[dict[str, Any]]:
    """A Dask task: fit one chunk of reports in the worker's own env."""
    return fit_reports(reports, options)


def _meta(reports_path: Path, options: CohortOptions, posterior: PosteriorOptions | None) -> dict[str, Any]:
    digest = hashlib.sha256(reports_path.read_bytes()).hexdigest()
    return {"reports_sha256": digest, "options": options.to_dict(), **({} if posterior is None else {"posterior": posterior.to_dict()})}


#: How the output CSV is written: the csv module's quoting for every header and cell, one line ending.
_DIALECT = dict(lineterminator="\n", quoting=csv.QUOTE_MINIMAL)


def _csv_text(records: Sequence[Sequence[str]]) -> str:
    with io.StringIO(newline="") as text:
        csv.writer(text, **_DIALECT).writerows(records)
        return text.getvalue()


def _finished(out: Path, columns: list[str]) -> set[str]:
    """Ids already in ``out``; a torn last record (a killed run) is dropped from the file."""
    with out.open(newline="", encoding="utf-8") as handle:
        text = handle.read()
    records: list[list[str]] = []
    torn = False
    try:
        records.extend(csv.reader(io.StringIO(text, newline=""), strict=True))
    except csv.Error:  # the file ends inside a quoted cell
        torn = True
    if not torn and records and (not text.endswith("\n") or len(records[-1]) != len(columns)):
        records.pop()
        torn = True
    if torn:
        archive.write_text(out, _csv_text(records or [columns]))
    if records and records[0] != columns:
        raise CohortError(f"{str(out)!r} has other columns than this run would write; delete it or choose another --out")
    return {r[0] for r in records[1:]}


def _stored_meta(meta_path: Path) -> Any:
    """The run record next to an output, or None when it is missing or not JSON."""
    try:
        return json.loads(meta_path.read_text(encoding="utf-8"))
    except (FileNotFoundError, UnicodeDecodeError, json.JSONDecodeError):
        return None


def run_cohort(
    reports_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    options: CohortOptions | None = None,
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: Callable[[int, int, dict[str, Any] | None], None] | None = None,
    on_bad: Callable[[BadRow], None] | None = None,
    posterior: PosteriorOptions | None = None,
    posterior_progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Fit a report CSV into ``out_path`` (module docstring); resumable.

    ``out_path`` gets a row per patient as it finishes; ``<out_path>.json`` records the input's
    SHA-256 and the options. If both exist, the run resumes: patients already in the output are
    not refitted; an output written for another input or other options is refused
    (:class:`CohortError`). With ``scheduler`` (a Dask scheduler address) or ``workers`` > 1 (a
    Dask ``LocalCluster`` of that many single-threaded processes), the remaining reports are cut
    into chunks of ``slots`` patients fitted by the workers; the fits are the same.
    ``progress(done, total, result)`` is called at the start (result None) and per patient;
    ``on_bad(row)`` once per bad row, before any fitting. ``posterior``: also each row's
    posterior (module docstring), drawn before the fits; ``posterior_progress(done, total, id)``
    before each refining MCMC run.

    Returns a summary: counts, bad rows, wall time, the mismatch distribution of this file and,
    with ``posterior``, how many of this run's rows were flagged and refined.
    """
    options = options or CohortOptions()
    workers = integer("workers", workers, 1)
    start = time.perf_counter()
    reports_path, out = Path(reports_path), Path(out_path)
    parsed = read_reports(reports_path, options.base_heart(), maps=options.maps)
    if on_bad is not None:
        for bad in parsed.bad:
            on_bad(bad)
    columns = output_columns(parsed.extra_columns, posterior is not None)
    meta_path = out.with_name(out.name + ".json")
    meta = _meta(reports_path, options, posterior)
    done: set[str] = set()
    try:
        if out.exists() and out.stat().st_size:
            if _stored_meta(meta_path) != meta:
                raise CohortError(f"{str(out)!r} was written for another report file or other options "
                                  f"(see {str(meta_path)!r}); delete both or choose another --out")
            done = _finished(out, columns)
        else:
            archive.write_text(meta_path, json.dumps(meta, indent=2))
            archive.write_text(out, _csv_text([columns]))
    except (OSError, UnicodeDecodeError) as err:
        raise CohortError(f"cannot write the output {str(out)!r} (or {str(meta_path)!r}): {getattr(err, 'strerror', None) or err}") from None
    pending = [r for r in parsed.rows if r.id not in done]
    identified = {}
    if posterior is not None and pending:
        from optim.identify.sampler import identify_patients

        answers = identify_patients([r.patient for r in pending], posterior.n_samples, seed=posterior.seed, refine=posterior.refine,
                                    mcmc_options=posterior.mcmc, progress=posterior_progress, importance=posterior.importance)
        identified = {r.id: a for r, a in zip(pending, answers)}
    total = len(parsed.rows)
    count = total - len(pending)
    if progress is not None:
        progress(count, total, None)
    with out.open("a", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, columns, **_DIALECT)

        def write(result: dict[str, Any]) -> None:
            nonlocal count
            writer.writerow({**_row(result), **(_posterior_cells(identified[result["id"]]) if identified else {})})
            handle.flush()
            os.fsync(handle.fileno())
            count += 1
            if progress is not None:
                progress(count, total, result)

        if scheduler is None and workers == 1:
            fit_reports(pending, options, on_done=write)
        else:
            _distributed(pending, options, write, workers, scheduler)
    flagged = {"posterior": {"flagged": sum(bool(a.flag) for a in identified.values()), "refined": sum(a.refined for a in identified.values())}}
    return {**summarise(out), "bad_rows": [dataclasses.asdict(b) for b in parsed.bad], "resumed": len(done),
            "wall_time_s": time.perf_counter() - start, "output": str(out), **(flagged if posterior is not None else {})}


def _distributed(pending: list[Report], options: CohortOptions, write: Callable[[dict[str, Any]], None],
                 workers: int, scheduler: str | None) -> None:
    from dask.distributed import as_completed

    with client(workers, scheduler) as handle:
        futures = [handle.submit(_fit_chunk, chunk, options, pure=False) for chunk in _chunks(pending, options.slots)]
        for future in as_completed(futures):
            for result in future.result():
                write(result)


def summarise(out_path: str | os.PathLike[str]) -> dict[str, Any]:
    """Counts and the mismatch distribution (median, 95th percentile, max) of an output CSV."""
    with Path(out_path).open(newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    mismatch = np.array([float(r["mismatch"]) if r["mismatch"] else np.inf for r in rows])
    status = collections.Counter(r["status"] for r in rows)
    finite = mismatch[np.isfinite(mismatch)]
    return {"fitted": len(rows), "status": dict(status), "mismatch": distribution(mismatch), "usable": int(len(finite))}


def distribution(mismatch: Sequence[float]) -> dict[str, float]:
    """Median, 95th percentile and maximum of mismatches (fractions; a failed fit counts as inf);
    empty for no fits."""
    m = np.asarray(mismatch, float)
    if not len(m):
        return {}
    return {"median": float(np.median(m)), "p95": float(np.percentile(m, 95)), "max": float(np.max(m))}

