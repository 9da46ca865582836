"""Named parameter sets: the paper's N and HF hearts and the Table 2 training conditions.

Geometry: Table 1 unloaded configurations. LO parameters, by name (``lo=``):

* ``"trained"`` (default): congruency-trained against our own 3-D FE oracle at its default mesh
  (:mod:`optim.congruency`; records ``lvenv/data/trained_normal.json`` and
  ``trained_heart_failure.json`` with their congruency and provenance, :mod:`lvenv.trained`);
* ``"table3"``: the paper's values, trained against *their* FE model (DESIGN §1 table, "Table 3").

LO heart models, by name (``model=``, :data:`LO_MODELS`): ``"single"`` (default), the paper's
single cell; ``"series3"``, three cells in series with equal volume shares whose calcium
transients start at the 5, 50 and 95 % quantiles of the wall's activation times
(:mod:`lvenv.multielement`, issue 30), with its own maps trained against the same oracle runs
(records ``trained_normal_series3.json`` and ``trained_heart_failure_series3.json``,
:func:`optim.congruency.train_model`; ``lo="trained"`` only).

Cell defaults: :class:`lvenv.params.CellParams` (README, "Cell defaults"). Circulation defaults
(closed loop, 60 bpm): README, "Circulation defaults".
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from lvenv import trained
from lvenv.geometry import Geometry
from lvenv.params import Arrangement, Circulation, Heart, LOParams
from lvenv.validation import InputError, choice

__all__ = ["normal", "heart_failure", "LO_SETS", "LO_MODELS", "MULTI_ELEMENT_MODELS", "record_name", "check_model", "model_of", "ONSET_RANGE", "onset_quantiles", "lo_params", "training_circulation", "training_condition", "TRAINING_CONDITIONS", "N_UNLOADED", "HF_UNLOADED", "N_END_DIASTOLE", "HF_END_DIASTOLE"]

N_UNLOADED = Geometry(Rb=35.0, L=9.6, Z=54.0, H=12.0, e=0.70, C0=-53.0)
HF_UNLOADED = Geometry(Rb=38.0, L=10.0, Z=49.0, H=7.7, e=0.66, C0=-64.0)
N_END_DIASTOLE = Geometry(Rb=38.0, L=8.2, Z=52.0, H=11.0, e=0.76, C0=-61.0)
HF_END_DIASTOLE = Geometry(Rb=42.0, L=8.2, Z=49.0, H=6.0, e=0.71, C0=-78.0)

#: The paper's Table 3 LO parameters (N and HF geometry), ``lo="table3"``.
N_LO = LOParams(mu1=0.191, mu2=0.183, gamma=4.97, alpha=0.640, beta=1.39, a=1.70, b=-1.41, c=1.64)
#: See :data:`N_LO`.
HF_LO = LOParams(mu1=0.190, mu2=0.173, gamma=5.17, alpha=0.571, beta=1.47, a=1.77, b=-1.47, c=1.61)

#: Table 2: k -> (Pat kPa, R3 kPa·s/ml, C ml/kPa); R1 = 0.0015 kPa·s/ml and R2 = 0 throughout.
TRAINING_CONDITIONS = {1: (0.33, 0.20, 8.0), 2: (0.66, 0.05, 8.0), 3: (1.5, 0.20, 8.0)}
TRAINING_R1 = 0.0015
TRAINING_PC0 = 10.0


#: Names of the LO parameter sets.
LO_SETS = ("trained", "table3")
#: The LO heart models with shipped maps: name → ``None`` (the single cell) or the multi-element
#: arrangement's (kind, cells, spread of the volume shares w_ξ) (module docstring).
LO_MODELS = {"single": None, "series3": ("series", 3, (1.0, 1.0))}
#: The multi-element ones among :data:`LO_MODELS` (trained from the single cell's records).
MULTI_ELEMENT_MODELS = tuple(name for name, spec in LO_MODELS.items() if spec is not None)
#: A multi-element model's cells start at the wall's activation times at quantiles evenly
#: spaced over this range (:func:`onset_quantiles`).
ONSET_RANGE = (0.05, 0.95)


def check_model(model: str) -> str:
    """``model`` if it names an LO heart model of :data:`LO_MODELS`, else an
    :class:`~lvenv.validation.InputError` naming it and the models."""
    return choice("model", model, tuple(LO_MODELS))


def model_of(elements: Arrangement | None) -> str:
    """The name in :data:`LO_MODELS` of the LO heart model ``elements`` (``Heart.elements``)
    is, whatever its onsets: "single" for None. Cells of no named model's kind, number and
    spread raise :class:`~lvenv.validation.InputError` naming them: only the named models
    have trained maps and anatomy regressions."""
    if elements is None:
        return "single"
    name = next((name for name, spec in LO_MODELS.items() if spec is not None and spec == elements.model_key()), None)
    if name is None:
        raise InputError(f"elements {elements.model_key()} are no LO heart model of {list(LO_MODELS)}; only those have trained maps and an anatomy regression")
    return name


def onset_quantiles(cells: int) -> tuple[float, ...]:
    """The activation-time quantiles (fractions) at which ``cells`` cells start (:data:`ONSET_RANGE`)."""
    return tuple(float(q) for q in np.linspace(*ONSET_RANGE, cells))


@functools.cache
def _trained_record(name: str) -> trained.TrainedLO:
    return trained.builtin(name)


def _trained(name: str) -> LOParams:
    return _trained_record(name).lo


def record_name(heart: str, model: str = "single") -> str:
    """The name of the shipped trained record (:func:`lvenv.trained.builtin`) of preset ``heart``
    and LO heart ``model``: ``heart``, or ``<heart>_<model>`` for a multi-element model."""
    return heart if model == "single" else f"{heart}_{model}"


def lo_params(heart: str, lo: str = "trained") -> LOParams:
    """The LO parameters of preset ``heart`` ("normal" or "heart_failure") by set name (module docstring)."""
    choice("heart", heart, ("normal", "heart_failure"))
    choice("lo", lo, LO_SETS)
    if lo == "table3":
        return N_LO if heart == "normal" else HF_LO
    return _trained(heart)


def normal(lo: str = "trained", model: str = "single") -> Heart:
    """Healthy heart N (F 77): unloaded geometry, LO maps ``lo`` of the LO heart ``model``
    (module docstring), default cell and circulation."""
    return _preset("normal", N_UNLOADED, lo, model)


def heart_failure(lo: str = "trained", model: str = "single") -> Heart:
    """Heart-failure heart HF (M 77, no infarct): unloaded geometry, LO maps ``lo`` of the LO
    heart ``model``, default cell and circulation."""
    return _preset("heart_failure", HF_UNLOADED, lo, model)


def _preset(heart: str, geometry: Geometry, lo: str, model: str) -> Heart:
    check_model(model)
    if model == "single":
        return Heart(geometry=geometry, lo=lo_params(heart, lo), circulation=Circulation())
    if choice("lo", lo, LO_SETS) != "trained":
        raise InputError(f"lo = {lo!r}: model {model!r} has trained maps only (lo='trained')")
    return _trained_record(record_name(heart, model)).heart()


def training_circulation(k: int, base: Circulation | None = None) -> Circulation:
    """The circulation ``base`` (default :class:`~lvenv.params.Circulation`) under Table 2 condition ``k`` ∈ {1, 2, 3}.

    Open loop: constant atrial pressure Pat, venous side at 0 kPa, R1 = 0.0015, R2 = 0, and the
    training protocol's initial capacitor pressure P_c(0) = 10 kPa; heart rate and Rmv stay
    ``base``'s. The FE oracle and the LO heart are trained under exactly these circulations.
    """
    choice("training condition k", k, tuple(TRAINING_CONDITIONS))
    pat, r3, c = TRAINING_CONDITIONS[k]
    base = Circulation() if base is None else base
    return dataclasses.replace(base, Pat=pat, R3=r3, C=c, R1=TRAINING_R1, R2=0.0, Pc0=TRAINING_PC0, closed_loop=0.0)


def training_condition(k: int, base: Heart | None = None) -> Heart:
    """``base`` (default :func:`normal`) under Table 2 condition ``k`` (:func:`training_circulation`).
    Simulate one beat from the default initial state (``lvenv.simulate(heart, beats=1)``)."""
    base = normal() if base is None else base
    return dataclasses.replace(base, circulation=training_circulation(k, base.circulation))
