"""Trained LO maps for any anatomy from the virtual cohort's Gaussian-process regression (DESIGN §5).

One Gaussian process per trained quantity maps the six unloaded geometric parameters (Rb, L, Z,
H in mm, e, C0 in degrees) to a trained LO parameter (μ1, μ2, γ, α, β, a, b, c, the activation
delay) or to the trained heart's congruency C. A quantity that cannot be negative is regressed
in log (the output spec's ``"log"``; `optim.regression` decides): its prediction stays positive,
and a spread that grows with the value, as γ's does towards weakly contracting anatomies, becomes
even. Inputs and outputs (after the log) are standardised (mean 0, sd 1 over the training
anatomies); the kernel is::

    k(x, x') = σ² · Matern_ν=5/2(‖(x − x') / ℓ‖) + σ_n² δ(x, x')

with one length scale ℓ_j per input (ARD) and a white-noise term σ_n² for what varies from
anatomy to anatomy without following the geometry smoothly. The hyperparameters maximise the
log marginal likelihood within bounds: σ² in [1e-3, 1e3], ℓ_j in [:data:`MIN_LENGTH_SCALE`,
1e3] and σ_n² in [:data:`MIN_NOISE`, 1] (standardised units). The two floors are ours. With
floors of 1e-2 and 1e-8 instead, the fits over the first 30 accepted anatomies put σ_n² at
1e-8 for 6 of the 8 outputs, and their 2-sd coverage in cross-validation was 63–93 %: the GPs
claimed a precision the data do not give, and γ's (R² 0.01) followed one odd anatomy. Training
an anatomy again with another seed reproduces its maps to within about 1 %, but each anatomy
has its own FE mesh, whose scatter no replicate shows; hence σ_n² ≥ 1e-2, a tenth of the
output's sd. The floors were chosen among six variants by the campaign's cross-validation, so
those figures are slightly optimistic: the held-out anatomies (:func:`optim.regression.held_out`)
are the independent check. The predictive mean and standard deviation at a new anatomy come from
scikit-learn's ``GaussianProcessRegressor`` rebuilt with the stored hyperparameters (no
optimisation), so loading is exact and fast; the sd includes σ_n. A log output's predicted
value is the median exp(m) of its log-normal predictive distribution, and its sd that
distribution's (exp(m) √(exp(s²) − 1) for a log-scale sd s).

The artefact is one JSON file (:data:`ARTEFACT`, format :data:`FORMAT_VERSION`): the inputs'
and outputs' scalings, each GP's hyperparameters and cross-validation figures, the training
anatomies (their ids and standardised values) and the provenance (dataset, mesh size, time
step, code versions). `optim.regression` fits and writes it; nothing here unpickles.

:func:`from_geometry` returns a :class:`~lvenv.trained.TrainedLO` in milliseconds, with the
predictive sd of every parameter in ``provenance["sd"]``; a geometry outside the sampled box
gets an :class:`ExtrapolationWarning` naming the parameter.

A multi-element LO heart (:data:`lvenv.presets.LO_MODELS`, e.g. ``"series3"``) has a regression
of its own (:func:`artefact`; `optim.regression.fit` with ``model=``, over the model's table of
the dataset): the same outputs and its cells' onsets (:func:`onset_outputs`), so that
``from_geometry(geometry, model="series3")`` gives a record with its cells (``elements``).

Imaged ventricles are loaded; the regression takes the unloaded shape. :func:`unload` applies
the paper's rule, an assumed mid-wall end-diastolic strain (:data:`ED_STRAIN`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import pathlib
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.optimize import brentq

from lvenv import presets
from lvenv.geometry import Geometry, GeometryError, cavity_volume, wall_volume
from lvenv.params import Arrangement, CellParams, LOParams
from lvenv.trained import DATA, TrainedLO
from lvenv.validation import InputError, integer, real

__all__ = ["ARTEFACT", "ARTEFACT_ENV", "artefact", "onset_outputs", "FORMAT_VERSION", "INPUTS", "LO_OUTPUTS", "ED_STRAIN", "STRAIN_RANGE", "ExtrapolationWarning", "Regression", "kernel", "log_normal", "load_regression", "from_geometry", "maps_note", "predicted_maps", "map_draws", "unload", "inflate", "unload_to_volume"]

ARTEFACT = DATA / "anatomy" / "regression.json"

FORMAT_VERSION = 2
#: The GP inputs: the `Geometry` fields, in order.
INPUTS = tuple(f.name for f in dataclasses.fields(Geometry))
#: The trained LO parameters a regression predicts.
LO_OUTPUTS = tuple(f.name for f in dataclasses.fields(LOParams))
#: Matern smoothness ν.
NU = 2.5
#: Smallest length scale of a standardised input, and smallest white-noise variance of a
#: standardised output (module docstring).
MIN_LENGTH_SCALE, MIN_NOISE = 0.3, 1e-2


def artefact(model: str = "single") -> pathlib.Path:
    """The shipped regression of LO heart ``model`` (:data:`lvenv.presets.LO_MODELS`):
    :data:`ARTEFACT` for the single cell, ``regression_<model>.json`` beside it for a
    multi-element model."""
    presets.check_model(model)
    return ARTEFACT if model == "single" else ARTEFACT.with_name(f"regression_{model}.json")


def onset_outputs(model: str) -> tuple[str, ...]:
    """What a regression of ``model`` predicts besides the LO parameters and C: each cell's
    onset ``onset_<k>`` (s, relative to the LO delay; none for the single cell)."""
    spec = presets.LO_MODELS[presets.check_model(model)]
    return () if spec is None else tuple(f"onset_{k}" for k in range(1, spec[1] + 1))


def log_normal(mean: np.ndarray, sd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The median and sd (physical units) of a log-normal whose log has ``mean`` and ``sd``:
    how a log output's prediction is reported (module docstring)."""
    median = np.exp(mean)
    return median, median * np.sqrt(np.expm1(sd**2))


class ExtrapolationWarning(UserWarning):
    """A geometry outside the box the regression's anatomies were sampled from."""


def kernel(n_inputs: int, *, constant: float = 1.0, length_scale: Sequence[float] | None = None, noise: float = MIN_NOISE, fixed: bool = False):
    """The kernel of the module docstring (scikit-learn), with free hyperparameters for fitting
    or, with ``fixed``, frozen at the given values for prediction."""
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    bounds = "fixed" if fixed else None
    scales = np.ones(n_inputs) if length_scale is None else np.asarray(length_scale, float)
    return (ConstantKernel(constant, constant_value_bounds=bounds or (1e-3, 1e3))
            * Matern(scales, length_scale_bounds=bounds or (MIN_LENGTH_SCALE, 1e3), nu=NU)
            + WhiteKernel(noise, noise_level_bounds=bounds or (MIN_NOISE, 1.0)))


@dataclasses.dataclass(frozen=True, eq=False)
class Regression:
    """A loaded regression artefact (module docstring). ``outputs`` maps a name to its scaling
    (``mean``, ``scale``, of the log where ``log`` is true), its hyperparameters (``constant``,
    ``length_scale``, ``noise``) and ``cv``, or, for an output the training kept at one value, to
    ``{"mean": value, "fixed": true}`` (predicted as that value with sd 0); ``x`` and ``y`` are
    the standardised training data; ``box`` the sampling box."""

    x_mean: np.ndarray
    x_scale: np.ndarray
    x: np.ndarray
    y: dict[str, np.ndarray]
    outputs: dict[str, dict[str, Any]]
    box: dict[str, tuple[float, float]]
    ids: tuple[str, ...]
    provenance: dict[str, Any]
    _gps: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False)

    @property
    def model(self) -> str:
        """The LO heart model whose maps it predicts (``provenance["model"]``; "single" if absent)."""
        return self.provenance.get("model", "single")

    def arrangement(self, mean: Mapping[str, np.ndarray], member: int = 0) -> Arrangement | None:
        """The model's cells with the onsets of ``mean`` (:meth:`predict`'s, anatomy ``member``);
        None for the single cell."""
        spec = presets.LO_MODELS[self.model]
        if spec is None:
            return None
        kind, cells, spread = spec
        return Arrangement(kind, cells, spread, onsets=tuple(float(mean[name][member]) for name in onset_outputs(self.model)))

    @classmethod
    def from_dict(cls, record: Mapping[str, Any], source: str = "regression record") -> Regression:
        """Validate and build; :class:`~lvenv.validation.InputError` naming the field otherwise."""
        if not isinstance(record, Mapping):
            raise InputError(f"{source} is not a JSON object")
        if record.get("format") != FORMAT_VERSION:
            raise InputError(f"{source} has format {record.get('format')!r}; this lvenv reads format {FORMAT_VERSION}")
        try:
            x = np.asarray(record["x"], float)
            outputs = {str(k): dict(v) for k, v in record["outputs"].items()}
            y = {k: np.asarray(record["y"][k], float) for k in outputs}
            reg = cls(np.asarray(record["x_mean"], float), np.asarray(record["x_scale"], float), x, y, outputs,
                      {k: (float(lo), float(hi)) for k, (lo, hi) in record["box"].items()}, tuple(record["ids"]), dict(record["provenance"]))
            for name, spec in outputs.items():
                for field in ("mean",) if spec.get("fixed") else ("mean", "scale", "constant", "noise"):
                    value = spec[field]
                    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                        raise ValueError(f"outputs.{name}.{field} = {value!r} is not a finite number")
                if not isinstance(spec.get("log", False), bool):
                    raise ValueError(f"outputs.{name}.log = {spec['log']!r} is not true or false")
                if not spec.get("fixed") and len(spec["length_scale"]) != len(INPUTS):
                    raise ValueError(f"outputs.{name}.length_scale has {len(spec['length_scale'])} entries, not {len(INPUTS)}")
        except (KeyError, TypeError, ValueError) as err:
            raise InputError(f"{source} is malformed: {type(err).__name__}: {err}") from None
        if x.ndim != 2 or x.shape[1] != len(INPUTS) or reg.x_mean.shape != (len(INPUTS),) or reg.x_scale.shape != (len(INPUTS),):
            raise InputError(f"{source} is malformed: x must be (anatomies, {len(INPUTS)}), x_mean and x_scale ({len(INPUTS)},)")
        if any(v.shape != (len(x),) for v in y.values()) or len(reg.ids) != len(x):
            raise InputError(f"{source} is malformed: y and ids must have one entry per anatomy ({len(x)})")
        if set(reg.box) != set(INPUTS):
            raise InputError(f"{source} is malformed: box must name {list(INPUTS)}, not {sorted(reg.box)}")
        if reg.model not in presets.LO_MODELS:
            raise InputError(f"{source} is malformed: provenance.model = {reg.model!r} is not one of {list(presets.LO_MODELS)}")
        if missing := [n for n in onset_outputs(reg.model) if n not in outputs]:
            raise InputError(f"{source} is malformed: a regression of model {reg.model!r} predicts its cells' onsets, and {missing} are missing")
        return reg

    @classmethod
    def load(cls, path: str | pathlib.Path = ARTEFACT) -> Regression:
        path = pathlib.Path(path)
        try:
            record = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"no anatomy regression at {str(path)!r}: it is written by `lvenv campaign regress` once the campaign "
                             "dataset has accepted anatomies (for a multi-element model, `lvenv campaign train-model` and then "
                             "`lvenv campaign regress --model`)") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise InputError(f"cannot read the anatomy regression {str(path)!r}: {type(err).__name__}: {err}") from None
        return cls.from_dict(record, f"anatomy regression {str(path)!r}")

    def _gp(self, name: str):
        """The scikit-learn GP of ``name`` with the stored hyperparameters (fitted once, no optimiser)."""
        from sklearn.gaussian_process import GaussianProcessRegressor

        if name not in self.outputs:
            raise InputError(f"the regression has no output {name!r}; it has {list(self.outputs)}")
        if name not in self._gps:
            spec = self.outputs[name]
            k = kernel(len(INPUTS), constant=spec["constant"], length_scale=spec["length_scale"], noise=spec["noise"], fixed=True)
            self._gps[name] = GaussianProcessRegressor(k, optimizer=None, alpha=1e-10).fit(self.x, self.y[name])
        return self._gps[name]

    def standardise(self, geometries: Sequence[Geometry]) -> np.ndarray:
        return (np.array([g.as_tuple() for g in geometries]) - self.x_mean) / self.x_scale

    def outside(self, geometry: Geometry) -> list[str]:
        """The parameters of ``geometry`` outside the sampling box, each with its value and range."""
        return [f"geometry.{k} = {getattr(geometry, k):g} outside the sampled range [{lo:g}, {hi:g}]"
                for k, (lo, hi) in self.box.items() if not lo <= getattr(geometry, k) <= hi]

    def latent(self, geometries: Sequence[Geometry], names: Sequence[str] | None = None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Predictive means and sds per output name, each of shape (anatomies,), on the scale
        each GP models: physical units, or their log where the spec says ``log``
        (:meth:`physical` maps a value on that scale back)."""
        names = tuple(self.outputs) if names is None else tuple(names)
        x = self.standardise(geometries)
        mean, sd = {}, {}
        for name in names:
            spec = self.outputs.get(name, {})
            if spec.get("fixed"):
                mean[name], sd[name] = np.full(len(x), float(spec["mean"])), np.zeros(len(x))
                continue
            m, s = self._gp(name).predict(x, return_std=True)
            mean[name], sd[name] = m * spec["scale"] + spec["mean"], s * spec["scale"]
        return mean, sd

    def physical(self, name: str, value: np.ndarray) -> np.ndarray:
        """``value`` of output ``name`` on its GP's scale (:meth:`latent`), in physical units."""
        return np.exp(value) if self.outputs[name].get("log") else value

    def predict(self, geometries: Sequence[Geometry], names: Sequence[str] | None = None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Predicted values and sds (physical units) per output name, each of shape (anatomies,):
        the GP's mean and sd, or for a log output its log-normal's median and sd (module docstring)."""
        mean, sd = self.latent(geometries, names)
        for name in mean:
            if self.outputs[name].get("log"):
                mean[name], sd[name] = log_normal(mean[name], sd[name])
        return mean, sd

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT_VERSION, "kind": "lvenv.anatomy.Regression", "inputs": list(INPUTS), "box": {k: list(v) for k, v in self.box.items()},
                "x_mean": self.x_mean.tolist(), "x_scale": self.x_scale.tolist(), "outputs": self.outputs, "ids": list(self.ids),
                "x": self.x.tolist(), "y": {k: v.tolist() for k, v in self.y.items()}, "provenance": self.provenance}


#: Environment variable naming a regression artefact to use instead of the shipped one of the single cell.
ARTEFACT_ENV = "LVENV_ANATOMY_REGRESSION"


@functools.lru_cache(maxsize=4)
def _loaded(path: str) -> Regression:
    return Regression.load(path)


def load_regression(regression: Regression | str | pathlib.Path | None = None, model: str | None = None) -> Regression:
    """``regression`` itself, the artefact at a path, or (None) the shipped one of LO heart
    ``model`` (:func:`artefact`, default the single cell's, or the one :data:`ARTEFACT_ENV`
    names if set); loaded once per path. A regression of another model than ``model`` (None:
    any) raises :class:`~lvenv.validation.InputError` naming both."""
    if model is not None:
        presets.check_model(model)
    if not isinstance(regression, Regression):
        default = "single" if model is None else model
        if regression is None and default == "single" and os.environ.get(ARTEFACT_ENV):
            path = pathlib.Path(os.environ[ARTEFACT_ENV])
            if not path.is_file():
                raise InputError(f"{ARTEFACT_ENV} = {str(path)!r} is not a file; it must name an anatomy regression artefact (`lvenv campaign regress --out`)")
            regression = path
        regression = _loaded(str(pathlib.Path(artefact(default) if regression is None else regression).resolve()))
    if model is not None and regression.model != model:
        raise InputError(f"the anatomy regression predicts the maps of model {regression.model!r}, not of model {model!r}")
    return regression


def from_geometry(geometry: Geometry, regression: Regression | str | pathlib.Path | None = None, cell: CellParams | None = None,
                  model: str | None = None) -> TrainedLO:
    """The GP-predicted trained LO maps of ``geometry`` (unloaded, mm), no FE run.

    ``regression``: a :class:`Regression`, a path to an artefact, or None for the shipped one of
    LO heart ``model`` (:func:`load_regression`; ``model`` None: the single cell's, or any
    model a given regression predicts). A multi-element model's record carries its cells
    (``elements``) with the onsets the regression predicts. The record's ``congruency["C"]`` is
    the predicted C of a heart trained on this anatomy; ``provenance["sd"]`` holds the predictive sd of every parameter and of C
    (same units), ``provenance["outside_box"]`` the parameters outside the sampled box, and
    ``provenance["clipped"]`` any predicted parameter that fell outside its allowed range
    (:class:`~lvenv.params.LOParams`) and was clipped into it, with a warning.
    """
    if not isinstance(geometry, Geometry):
        raise InputError(f"geometry must be an lvenv.geometry.Geometry, got {type(geometry).__name__}")
    regression = load_regression(regression, model)
    missing = [n for n in LO_OUTPUTS if n not in regression.outputs]
    if missing:
        raise InputError(f"the regression does not predict {missing}; it predicts {list(regression.outputs)}")
    outside = regression.outside(geometry)
    for message in outside:
        warnings.warn(f"{message}: the anatomy regression extrapolates there", ExtrapolationWarning, stacklevel=2)
    mean, sd = regression.predict([geometry])
    values, clipped = {}, []
    for field in dataclasses.fields(LOParams):
        low, high = field.metadata["range"]
        value = float(mean[field.name][0])
        values[field.name] = min(max(value, low), high)
        if values[field.name] != value:
            clipped.append(f"lo.{field.name} = {value:g} predicted, clipped to its allowed range [{low:g}, {high:g}]")
    for message in clipped:
        warnings.warn(message, ExtrapolationWarning, stacklevel=2)
    c = float(mean["C"][0]) if "C" in mean else math.nan
    provenance = {"source": "gaussian-process regression over geometry", "sd": {k: float(v[0]) for k, v in sd.items()},
                  "outside_box": outside, "clipped": clipped, "training_anatomies": len(regression.ids),
                  **{k: v for k, v in regression.provenance.items() if k not in ("cv", "cv_predictions")}}
    lo = LOParams(**values)
    return TrainedLO(geometry, lo, CellParams() if cell is None else cell, {"C": c}, None, math.nan, provenance, regression.arrangement(mean))


def maps_note(trained: TrainedLO) -> dict[str, Any]:
    """What a patient record keeps of the GP-predicted maps ``trained`` (:func:`from_geometry`;
    :attr:`lvenv.patients.Patient.anatomy` ``["maps"]``): the source, the predicted C, every
    output's predictive sd, the outside-box and clipping notes, and a multi-element model's name."""
    note = {"source": "regression", "C": trained.congruency["C"], **{k: trained.provenance[k] for k in ("sd", "outside_box", "clipped", "training_anatomies")}}
    return note if trained.elements is None else {**note, "model": presets.model_of(trained.elements)}


def predicted_maps(geometry: Geometry, regression: Regression | str | pathlib.Path | None = None) -> tuple[LOParams, dict[str, Any]]:
    """The regression's LO maps of ``geometry`` (:func:`from_geometry`, warnings and all) and
    what a patient record keeps of them (:func:`maps_note`)."""
    trained = from_geometry(geometry, regression)
    return trained.lo, maps_note(trained)


def map_draws(geometry: Geometry, n: int, *, seed: int = 0, regression: Regression | str | pathlib.Path | None = None,
              model: str | None = None) -> list[LOParams]:
    """``n`` draws of the LO maps of ``geometry`` from the regression's predictive distribution
    (``regression`` and ``model`` as :func:`load_regression` takes them): each parameter normal
    with its GP's mean and sd on the GP's scale (log-normal for a log output; one GP per
    parameter, so independent), clipped to its allowed range; a multi-element heart's cells keep
    their predicted onsets. Refitting a patient at each draw carries the maps' uncertainty into
    the fitted parameters."""
    n, seed = integer("n", n, 1, 10_000), integer("seed", seed, 0)
    regression = load_regression(regression, model)
    with warnings.catch_warnings():  # from_geometry's own call warns, not each draw
        warnings.simplefilter("ignore", ExtrapolationWarning)
        mean, sd = regression.latent([geometry], LO_OUTPUTS)
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(n):
        values = {}
        for field in dataclasses.fields(LOParams):
            low, high = field.metadata["range"]
            value = regression.physical(field.name, mean[field.name][0] + sd[field.name][0] * rng.standard_normal())
            values[field.name] = float(np.clip(value, low, high))
        draws.append(LOParams(**values))
    return draws


#: Assumed mid-wall end-diastolic strain by group (Di Achille et al. 2020: 10 % N, 15 % HF).
ED_STRAIN = {"N": 0.10, "HF": 0.15}


def _midwall_scaled(g: Geometry, factor: float) -> Geometry:
    """``g`` with its mid-wall basal radius Rb − L/2 and mid-wall long axis Z − H/2 scaled by
    ``factor`` and its wall thickness L, H by the one factor s that keeps the wall volume
    (incompressible myocardium; :func:`lvenv.geometry.wall_volume`), s found by Brent's method;
    e and C0 kept. :class:`GeometryError` if no valid geometry keeps the wall volume."""
    radius, axis = (g.Rb - g.L / 2) * factor, (g.Z - g.H / 2) * factor
    target = wall_volume(g)

    def shaped(s: float) -> Geometry:
        return Geometry(radius + s * g.L / 2, s * g.L, axis + s * g.H / 2, s * g.H, g.e, g.C0)

    def excess(s: float) -> float:
        try:
            return wall_volume(shaped(s)) - target
        except GeometryError:
            return math.inf

    if factor == 1.0:
        return g
    low = high = 1.0  # a smaller cavity needs a thicker wall for the same volume (s > 1), a larger one a thinner (s < 1)
    while factor < 1.0 and excess(high) < 0 and high < 4.0:
        high *= 1.25
    while factor > 1.0 and excess(low) > 0 and low > 0.1:
        low *= 0.8
    if not excess(low) <= 0 <= excess(high) or not math.isfinite(excess(high)):
        raise GeometryError(f"no geometry keeps the wall volume of {g} with its mid-wall dimensions scaled by {factor:g}")
    return shaped(brentq(excess, low, high, xtol=1e-12))


def unload(end_diastolic: Geometry, strain: float) -> Geometry:
    """The unloaded geometry of an imaged end-diastolic one under an assumed mid-wall strain ε
    (the paper's rule, :data:`ED_STRAIN`; our reading of it, DESIGN §5):

    * the mid-wall basal radius Rb − L/2 and the mid-wall long axis Z − H/2 shrink by 1/(1 + ε);
    * the wall thickens by one factor s on L and H such that the wall volume is kept
      (incompressible myocardium; :func:`lvenv.geometry.wall_volume`), s found by Brent's method;
    * the shape e and the truncation C0 are kept.

    ``strain`` ≥ 0 (0 returns the geometry itself). Raises :class:`GeometryError` if no valid
    geometry keeps the wall volume. :func:`inflate` is its inverse.
    """
    strain = real("strain", strain, 0.0, 1.0)
    return _midwall_scaled(end_diastolic, 1.0 / (1.0 + strain))


def inflate(unloaded: Geometry, strain: float) -> Geometry:
    """The end-diastolic geometry the paper's rule assigns to an unloaded one under mid-wall
    strain ε: the inverse of :func:`unload` (mid-wall dimensions × (1 + ε), the wall thinned to
    keep its volume). ``strain`` in [0, 1]; :class:`GeometryError` if no valid geometry exists."""
    strain = real("strain", strain, 0.0, 1.0)
    return _midwall_scaled(unloaded, 1.0 + strain)


#: The strains :func:`unload_to_volume` searches (the paper's rule takes 0.10–0.15).
STRAIN_RANGE = (0.0, 0.6)


def unload_to_volume(end_diastolic: Geometry, edp: float, regression: Regression | str | pathlib.Path | None = None, *,
                     lo: LOParams | None = None) -> tuple[Geometry, float]:
    """The unloaded geometry whose predicted passive curve reaches the imaged cavity volume
    (``cavity_volume(end_diastolic)``, ml) at the end-diastolic pressure ``edp`` (kPa), and its
    strain ε.

    The search runs over the rule's family ``unload(end_diastolic, ε)``, ε in
    :data:`STRAIN_RANGE`, by Brent's method: at each ε the LO passive volume at ``edp``
    (:func:`lvenv.coupling.passive_volume`) is computed with the maps the regression predicts
    for that unloaded shape (:func:`from_geometry`), or with fixed maps ``lo`` when given. So the
    strain comes from the anatomy's own stiffness instead of the assumed 10 or 15 %.
    :class:`InputError` naming the values if no strain in the range reaches the volume.
    """
    from lvenv.coupling import passive_volume

    if not isinstance(end_diastolic, Geometry):
        raise InputError(f"end_diastolic must be an lvenv.geometry.Geometry, got {type(end_diastolic).__name__}")
    edp = real("edp", edp, 0.0, 10.0)
    if lo is None:
        regression = load_regression(regression)
    edv = cavity_volume(end_diastolic)

    def maps(g: Geometry) -> LOParams:
        if lo is not None:
            return lo
        with warnings.catch_warnings():  # the solution's warnings are given once, below
            warnings.simplefilter("ignore", ExtrapolationWarning)
            return from_geometry(g, regression).lo

    def gap(strain: float) -> float:
        g = unload(end_diastolic, strain)
        return float(passive_volume(edp, cavity_volume(g), maps(g))) - edv

    low, high = STRAIN_RANGE
    if not gap(low) >= 0.0 >= gap(high):
        raise InputError(f"no unloaded shape with a mid-wall strain in [{low:g}, {high:g}] reaches the imaged volume {edv:.1f} ml "
                         f"at edp = {edp:g} kPa: the LO passive volume there spans [{gap(high) + edv:.1f}, {gap(low) + edv:.1f}] ml")
    strain = low if gap(low) == 0.0 else brentq(gap, low, high, xtol=1e-10)
    unloaded = unload(end_diastolic, strain)
    if lo is None:
        from_geometry(unloaded, regression)  # its extrapolation and clipping warnings, once
    return unloaded, strain
