"""Gaussian-process regression from geometry to the trained LO maps, over a campaign's dataset (DESIGN §5).

`fit(directory)` reads the accepted training anatomies of a campaign (`optim.campaign`), fits
one scikit-learn ``GaussianProcessRegressor`` per trained quantity (the LO parameters of
:data:`lvenv.anatomy.LO_OUTPUTS` and the congruency C) with the kernel of
:func:`lvenv.anatomy.kernel` on standardised inputs and outputs, maximising the log marginal
likelihood from ``restarts`` + 1 starts, and cross-validates each by k-fold (the
hyperparameters refitted on every training fold). An output that cannot be negative
(:data:`NON_NEGATIVE`) and is positive at every training anatomy is regressed in log
(:func:`in_log`; why in :mod:`lvenv.anatomy`). It returns a :class:`lvenv.anatomy.Regression`,
which `save` writes as the package's JSON artefact.

Cross-validation figures per output: R² = 1 − Σ(y − ŷ)² / Σ(y − ȳ)² over the held-out
predictions, the RMSE (physical units) and the fraction of held-out anatomies within 2
predictive sd of their trained value, all in physical units except that a log output's
prediction ŷ is its median and its 2-sd band is taken on the log scale. An output with one value over every training anatomy
(a parameter congruency training keeps fixed, such as α and β) gets no GP: the artefact marks
it ``fixed`` and predicts that value with sd 0, and it has no cross-validation figures.

A multi-element LO heart (``model="series3"``) is regressed the same way over its table of the
dataset (`optim.campaign.train_model_table`), with its cells' onsets as further outputs
(:func:`outputs_of`); the artefact records the model (``provenance["model"]``).

`held_out(regression)` checks the regression where it matters, on the campaign's held-out
anatomies (sampled apart, never in the training set): the congruency C of the GP-predicted maps
against each anatomy's own FE beats, beside that of its directly trained maps and of the N
preset's maps.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os
import pathlib
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from lvenv import archive, presets
from lvenv.anatomy import INPUTS, LO_OUTPUTS, Regression, artefact, kernel, log_normal, onset_outputs
from lvenv.params import LOParams
from lvenv.validation import InputError, integer
from optim import campaign
from optim.cohort import GEOMETRY_COLUMNS

__all__ = ["OUTPUTS", "NON_NEGATIVE", "MIN_ANATOMIES", "outputs_of", "training_set", "is_fixed", "in_log", "fit_gp", "cross_validate", "fit", "save", "held_out"]

#: What the regression predicts: the LO parameters and the trained heart's C.
OUTPUTS = (*LO_OUTPUTS, "C")
#: The outputs that cannot be negative: the LO parameters whose allowed range starts at 0 or
#: above (:class:`lvenv.params.LOParams`), and C.
NON_NEGATIVE = (*(f.name for f in dataclasses.fields(LOParams) if f.metadata["range"][0] >= 0), "C")
#: Fewer accepted anatomies than this make no regression (5 folds of at least 2).
MIN_ANATOMIES = 10


def outputs_of(model: str = "single") -> tuple[str, ...]:
    """What a regression of LO heart ``model`` predicts: :data:`OUTPUTS`, and a multi-element
    model's cells' onsets (:func:`lvenv.anatomy.onset_outputs`)."""
    return (*OUTPUTS, *onset_outputs(model))


def training_set(directory: str | os.PathLike[str] = campaign.DATASET, split: str = "train", model: str = "single") -> tuple[list[str], np.ndarray, dict[str, np.ndarray]]:
    """Ids, geometries (anatomies × 6, `Geometry` field order) and trained values
    (:func:`outputs_of`) of the accepted anatomies of ``split`` ("train" or "heldout"): the
    single cell's from the index, a multi-element model's from its table
    (:func:`optim.campaign.train_model_table`; anatomies it has not trained are left out)."""
    rows = [r for r in campaign.read_index(directory) if r["status"] == "accepted" and r["split"] == split]
    if presets.check_model(model) != "single":
        table = {r["id"]: r for r in campaign.read_model_table(directory, model)}
        rows = [{**r, **table[r["id"]]} for r in rows if r["id"] in table]
    column = {name: col for col, name in GEOMETRY_COLUMNS.items()}
    x = np.array([[r[column[k]] for k in INPUTS] for r in rows], float).reshape(len(rows), len(INPUTS))
    return [r["id"] for r in rows], x, {name: np.array([r[name] for r in rows], float) for name in outputs_of(model)}


def _scaling(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean, scale = values.mean(axis=0), values.std(axis=0)
    return mean, np.where(scale > 0, scale, 1.0)


def is_fixed(values: np.ndarray) -> bool:
    """Whether ``values`` are one number (to 1e-12 relative): an output the training kept fixed."""
    return bool(np.ptp(values) <= 1e-12 * max(1.0, float(np.max(np.abs(values)))))


def in_log(name: str, values: np.ndarray) -> bool:
    """Whether output ``name`` is regressed in log: it cannot be negative and ``values`` (its
    trained values over the anatomies) are all positive."""
    return name in NON_NEGATIVE and bool(np.all(values > 0))


def fit_gp(x: np.ndarray, y: np.ndarray, restarts: int = 5, seed: int = 0):
    """A fitted ``GaussianProcessRegressor`` on standardised ``x`` (n × 6) and ``y`` (n,).

    scikit-learn warns when a hyperparameter ends at its bound; here that is the point of ARD (a
    length scale at its upper bound marks an input the output does not depend on; the noise at its
    lower bound, a noise-free output), so those warnings are silenced.
    """
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process import GaussianProcessRegressor

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return GaussianProcessRegressor(kernel(x.shape[1]), alpha=1e-10, n_restarts_optimizer=restarts, random_state=seed).fit(x, y)


def _hyperparameters(gp) -> dict[str, Any]:
    k = gp.kernel_
    return {"constant": float(k.k1.k1.constant_value), "length_scale": np.atleast_1d(k.k1.k2.length_scale).astype(float).tolist(),
            "noise": float(k.k2.noise_level), "log_marginal_likelihood": float(gp.log_marginal_likelihood_value_)}


def cross_validate(x: np.ndarray, y: dict[str, np.ndarray], folds: int = 5, restarts: int = 5, seed: int = 0) -> dict[str, dict[str, Any]]:
    """k-fold cross-validation per varying output (module docstring; fixed ones are left out):
    ``r2``, ``rmse``, ``coverage_2sd``, ``log`` (:func:`in_log`) and the held-out ``predicted``
    values and ``sd`` (physical units, as :meth:`lvenv.anatomy.Regression.predict` gives them)
    in the anatomies' order."""
    from sklearn.model_selection import KFold

    folds = integer("folds", folds, 2, len(x))
    out = {}
    for name, values in y.items():
        if is_fixed(values):
            continue
        log = in_log(name, values)
        target = np.log(values) if log else values
        mean, sd = np.empty(len(x)), np.empty(len(x))
        for train, test in KFold(folds, shuffle=True, random_state=seed).split(x):
            x_mean, x_scale = _scaling(x[train])
            y_mean, y_scale = _scaling(target[train])
            gp = fit_gp((x[train] - x_mean) / x_scale, (target[train] - y_mean) / y_scale, restarts, seed)
            m, s = gp.predict((x[test] - x_mean) / x_scale, return_std=True)
            mean[test], sd[test] = m * y_scale + y_mean, s * y_scale
        covered = np.abs(target - mean) <= 2.0 * sd
        if log:
            mean, sd = log_normal(mean, sd)
        residual = values - mean
        total = np.sum((values - values.mean()) ** 2)
        out[name] = {"r2": float(1.0 - np.sum(residual**2) / total) if total > 0 else float("nan"), "rmse": float(np.sqrt(np.mean(residual**2))),
                     "coverage_2sd": float(np.mean(covered)), "log": log, "predicted": mean.tolist(), "sd": sd.tolist()}
    return out


def fit(directory: str | os.PathLike[str] = campaign.DATASET, *, restarts: int = 5, folds: int = 5, seed: int = 0,
        outputs: Sequence[str] | None = None, model: str = "single") -> Regression:
    """The regression of LO heart ``model``'s maps over the accepted training anatomies of the
    campaign in ``directory``, with each output's cross-validation figures (module docstring).
    ``outputs``: default all of :func:`outputs_of`; a multi-element model's regression needs
    the LO parameters and its cells' onsets."""
    restarts, seed = integer("restarts", restarts, 0), integer("seed", seed, 0)
    known = outputs_of(model)
    outputs = known if outputs is None else tuple(outputs)
    unknown = [o for o in outputs if o not in known]
    if unknown:
        raise InputError(f"outputs {unknown} are not trained quantities of model {model!r}; choose from {list(known)}")
    if model != "single" and (missing := [o for o in (*LO_OUTPUTS, *onset_outputs(model)) if o not in outputs]):
        raise InputError(f"outputs: a regression of model {model!r} needs {missing} too (its cells' onsets and LO parameters)")
    ids, x, y = training_set(directory, model=model)
    if len(ids) < MIN_ANATOMIES:
        trained = "" if model == "single" else f" trained for model {model!r} (`optim.campaign.train_model_table`)"
        raise InputError(f"the campaign in {str(directory)!r} has {len(ids)} accepted training anatomies{trained}; a regression needs at least {MIN_ANATOMIES}")
    y = {name: y[name] for name in outputs}
    cv = cross_validate(x, y, folds, restarts, seed)
    x_mean, x_scale = _scaling(x)
    xs = (x - x_mean) / x_scale
    specs, ys = {}, {}
    for name, values in y.items():
        if is_fixed(values):
            specs[name], ys[name] = {"mean": float(values[0]), "fixed": True}, np.zeros_like(values)
            continue
        log = cv[name]["log"]
        target = np.log(values) if log else values
        y_mean, y_scale = _scaling(target)
        ys[name] = (target - y_mean) / y_scale
        gp = fit_gp(xs, ys[name], restarts, seed)
        specs[name] = {"mean": float(y_mean), "scale": float(y_scale), "log": log, **_hyperparameters(gp),
                       "cv": {k: v for k, v in cv[name].items() if k in ("r2", "rmse", "coverage_2sd")} | {"folds": folds}}
    config = json.loads((pathlib.Path(directory) / "campaign.json").read_text())
    index = (pathlib.Path(directory) / "anatomies.csv").read_bytes()
    provenance = {"model": model, "dataset": str(directory), "dataset_sha256": hashlib.sha256(index).hexdigest()[:16], "settings": config["settings"],
                  "oracle_code": sorted({r["oracle_code"] for r in campaign.read_index(directory) if r["id"] in set(ids)}),
                  **({} if model == "single" else {"model_table_sha256": hashlib.sha256(campaign.model_table_path(directory, model).read_bytes()).hexdigest()[:16]}),
                  "restarts": restarts, "seed": seed, "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  "cv_predictions": {name: {"predicted": v["predicted"], "sd": v["sd"]} for name, v in cv.items()}}
    box = {k: tuple(v) for k, v in config["box"].items()}
    return Regression(x_mean, x_scale, xs, ys, specs, box, tuple(ids), provenance)


def save(regression: Regression, path: str | os.PathLike[str] | None = None) -> pathlib.Path:
    """Write the artefact (JSON) atomically, by default the package's of its model
    (:func:`lvenv.anatomy.artefact`); returns its path."""
    return archive.write_text(artefact(regression.model) if path is None else path, json.dumps(regression.to_dict(), indent=1) + "\n")



def held_out(regression: Regression, directory: str | os.PathLike[str] = campaign.DATASET, *, baseline: LOParams | None = None,
             steps_per_beat: int = 1000) -> list[dict[str, Any]]:
    """The regression on the campaign's accepted held-out anatomies, from their dataset traces
    (no FE run): per anatomy the C of its directly trained heart (``C_trained``), of the
    GP-predicted maps (``C_predicted``) and of ``baseline``'s maps (default: the shipped trained
    N record of the regression's model, ``C_baseline``), each against the anatomy's own three
    training beats. A multi-element model's hearts run with their own cells' onsets: the
    trained ones of its table (anatomies it has not trained are left out), the predicted ones,
    and N's."""
    from lvenv.anatomy import from_geometry
    from lvenv.trained import builtin
    from optim import congruency

    model = regression.model
    n_record = builtin(presets.record_name("normal", model))
    baseline = n_record.lo if baseline is None else baseline
    rows = [r for r in campaign.read_index(directory) if r["status"] == "accepted" and r["split"] == "heldout"]
    if model != "single":
        table = {r["id"]: r for r in campaign.read_model_table(directory, model)}
        rows = [{**r, **table[r["id"]]} for r in rows if r["id"] in table]
    out = []
    for row in rows:
        data = campaign.oracle_data(directory, row["id"])
        predicted = from_geometry(data.geometry, regression)
        trained = LOParams(**{name: row[name] for name in LO_OUTPUTS})
        if model == "single":
            c = congruency.overall(congruency.run_congruency(data, [trained, predicted.lo, baseline], steps_per_beat))
        else:
            own = regression.arrangement({name: [row[name]] for name in onset_outputs(model)})
            c = [congruency.overall(congruency.run_congruency(data, [lo], steps_per_beat, arrangement)[0])
                 for lo, arrangement in ((trained, own), (predicted.lo, predicted.elements), (baseline, n_record.elements))]
        out.append({"id": row["id"], "C_trained": float(c[0]), "C_predicted": float(c[1]), "C_baseline": float(c[2]),
                    "C_row": row["C"], "predicted_C": predicted.congruency["C"]})
    return out
