"""The unloading of imaged ventricles, checked through the FE oracle on the campaign's anatomies (DESIGN §5).

Every accepted anatomy of a campaign's dataset (`optim.campaign`) carries the FE passive
inflation of its unloaded geometry G0: the cavity volume V_FE(P) (ml) at pressures 0–4 kPa,
interpolated here by a monotone cubic (PCHIP). :func:`check` asks, per anatomy and per group of
the paper's rule (:data:`lvenv.anatomy.ED_STRAIN`: mid-wall strain ε = 10 % N, 15 % HF) at that
group's end-diastolic pressure (:func:`reference_edp`):

* ``EDV_error``: the rule says the ventricle imaged at end-diastole is ``inflate(G0, ε)``, whose
  cavity volume is the imaged EDV. Inflating G0 in the oracle to EDP must give it back; the
  error is V_FE(EDP) / EDV − 1.
* ``strain_fe``: the strain of the rule's family at which the FE wall actually is at EDP, the ε
  with cavity_volume(inflate(G0, ε)) = V_FE(EDP).
* On the ventricle imaged as the oracle has it, ``inflate(G0, strain_fe)`` (EDV = V_FE(EDP)), the
  unloaded cavity volume V0 recovered against the true one: ``V0_error_rule`` by the paper's
  rule (``unload`` at ε), ``V0_error_fit`` by :func:`lvenv.anatomy.unload_to_volume` with the
  anatomy's own trained maps (the LO passive curve the GP approximates) and, given a regression,
  ``V0_error_gp`` with the GP-predicted maps.

No FE run: everything comes from the dataset's traces and trained parameters.
"""

from __future__ import annotations

import os
import warnings
from typing import Any

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq

from lvenv.anatomy import ED_STRAIN, LO_OUTPUTS, STRAIN_RANGE, ExtrapolationWarning, Regression, inflate, unload, unload_to_volume
from lvenv.geometry import cavity_volume
from lvenv.params import LOParams
from optim import campaign

__all__ = ["reference_edp", "check", "summary"]


def reference_edp() -> dict[str, float]:
    """The end-diastolic pressure (kPa) of each group of :data:`~lvenv.anatomy.ED_STRAIN`: the
    EDP of the built-in heart's steady beat (``lvenv.simulate(presets.normal())`` for N,
    ``heart_failure()`` for HF)."""
    import lvenv
    from lvenv import presets

    hearts = {"N": presets.normal(), "HF": presets.heart_failure()}
    return {group: float(lvenv.simulate(hearts[group]).metrics["EDP"]) for group in ED_STRAIN}


def check(directory: str | os.PathLike[str] = campaign.DATASET, edp: dict[str, float] | None = None,
          regression: Regression | None = None) -> list[dict[str, Any]]:
    """The rows of the module docstring, one per accepted anatomy and group (both splits):
    ``id``, ``group``, ``strain`` (the rule's ε), ``EDP_kPa``, ``EDV_ml`` (the rule's imaged
    volume), ``V_fe_ml``, ``EDV_error``, ``strain_fe``, ``V0_ml``, ``V0_error_rule``,
    ``V0_error_fit`` and, with ``regression``, ``V0_error_gp`` (relative errors as fractions)."""
    edp = reference_edp() if edp is None else edp
    rows = []
    for row in campaign.read_index(directory):
        if row["status"] != "accepted":
            continue
        data = campaign.oracle_data(directory, row["id"])
        g0, trained = data.geometry, LOParams(**{name: row[name] for name in LO_OUTPUTS})
        volume_at = PchipInterpolator(data.passive.traces["P_lv"], data.passive.traces["V"])
        v0 = cavity_volume(g0)
        for group, strain in ED_STRAIN.items():
            v_fe = float(volume_at(edp[group]))
            edv = cavity_volume(inflate(g0, strain))
            strain_fe = brentq(lambda s: cavity_volume(inflate(g0, s)) - v_fe, 0.0, STRAIN_RANGE[1], xtol=1e-10)
            imaged = inflate(g0, strain_fe)
            out = {"id": row["id"], "split": row["split"], "group": group, "strain": strain, "EDP_kPa": edp[group], "EDV_ml": edv, "V_fe_ml": v_fe,
                   "EDV_error": v_fe / edv - 1.0, "strain_fe": strain_fe, "V0_ml": v0,
                   "V0_error_rule": cavity_volume(unload(imaged, strain)) / v0 - 1.0,
                   "V0_error_fit": cavity_volume(unload_to_volume(imaged, edp[group], lo=trained)[0]) / v0 - 1.0}
            if regression is not None:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", ExtrapolationWarning)
                    out["V0_error_gp"] = cavity_volume(unload_to_volume(imaged, edp[group], regression)[0]) / v0 - 1.0
            rows.append(out)
    return rows


def summary(rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per group: the anatomies, the median and the largest absolute value of each error, and
    the median and range of ``strain_fe``."""
    out = {}
    for group in ED_STRAIN:
        mine = [r for r in rows if r["group"] == group]
        if not mine:
            continue
        figures: dict[str, float] = {"anatomies": len(mine)}
        for key in ("EDV_error", "V0_error_rule", "V0_error_fit", "V0_error_gp"):
            if key in mine[0]:
                values = np.abs([r[key] for r in mine])
                figures[f"{key}_median_abs"], figures[f"{key}_max_abs"] = float(np.median(values)), float(values.max())
        strains = [r["strain_fe"] for r in mine]
        figures.update(strain_fe_median=float(np.median(strains)), strain_fe_min=float(min(strains)), strain_fe_max=float(max(strains)))
        out[group] = figures
    return out
