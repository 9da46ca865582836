"""The anatomy regression's uncertainty in the LO maps, carried into a fit (DESIGN §5).

A patient whose maps come from the anatomy regression (a record with ``"lo": "regression"``;
:func:`lvenv.anatomy.predicted_maps`) is fitted with the predicted maps, but those maps have a
predictive sd. :func:`refit` refits the patient at ``draws`` draws of its maps from the
regression's predictive distribution (:func:`lvenv.anatomy.map_draws`), and once more at the
predicted maps themselves (the *control*). Each refit is a least-squares fit
(:func:`optim.lm.fit_lm`) from one start, the first fit's parameters: it follows the solution
from the predicted maps to the drawn ones, so a parameter the targets do not pin down stays
where the first fit put it rather than wandering along its null direction. The spread of the
refitted parameters over the draws is the part of their uncertainty that the maps carry; it adds
to the measurement part (the posterior, `optim.identify`). The control's distance from the first
fit shows how far the refit itself moves a solution that needs no change.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from lvenv import presets
from lvenv.anatomy import Regression, map_draws
from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.patients import Patient
from lvenv.status import is_usable
from lvenv.validation import InputError, integer
from optim.lm import fit_lm

__all__ = ["MapSpread", "require_regression_maps", "refit"]


@dataclasses.dataclass(frozen=True)
class MapSpread:
    """The refits of :func:`refit`: per fitted parameter (internal units) the value of each draw's
    refit (NaN where the refit has no usable steady state), the draws' mismatches and statuses,
    and the control refit at the predicted maps."""

    parameters: dict[str, np.ndarray]
    mismatch: np.ndarray
    status: tuple[str, ...]
    control: dict[str, float]
    control_mismatch: float

    @property
    def usable(self) -> int:
        return sum(map(is_usable, self.status))

    def summary(self) -> dict[str, dict[str, float]]:
        """Per parameter over the usable draws: ``median``, ``sd`` (ddof 1), ``q05``, ``q95``,
        and the ``control`` refit's value."""
        out = {}
        for name, values in self.parameters.items():
            v = values[np.isfinite(values)]
            q05, median, q95 = np.quantile(v, (0.05, 0.5, 0.95)) if len(v) else (np.nan,) * 3
            out[name] = {"median": float(median), "sd": float(np.std(v, ddof=1)) if len(v) > 1 else float("nan"),
                         "q05": float(q05), "q95": float(q95), "control": self.control[name]}
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"draws": len(self.status), "usable": self.usable, "summary": self.summary(),
                "mismatch": self.mismatch.tolist(), "status": list(self.status), "control_mismatch": self.control_mismatch}


def require_regression_maps(patient: Patient) -> None:
    """:class:`~lvenv.validation.InputError` unless ``patient``'s maps come from the anatomy
    regression (its record's ``"lo": "regression"``): only those have an uncertainty to refit over."""
    if patient.anatomy.get("maps", {}).get("source") != "regression":
        raise InputError(f"the maps of {patient.name!r} do not come from the anatomy regression, so they have no uncertainty "
                         "to refit over; give its record \"lo\": \"regression\"")


def refit(patient: Patient, parameters: Mapping[str, float], draws: int, *, seed: int = 0, budget: int = 24, steps_per_beat: int = 1000,
          plausibility: bool = True, regression: Regression | None = None, progress: Callable[[int, int], None] | None = None) -> MapSpread:
    """Refit ``patient`` at ``draws`` draws of its maps and at its predicted maps (module
    docstring), each from ``parameters`` (the first fit's, :data:`DEFAULT_ACTION_PARAMS`).

    ``seed``: of the draws; ``budget``, ``steps_per_beat``, ``plausibility``: each refit's
    (:func:`optim.lm.fit_lm`); ``regression``: the artefact the maps came from (None: the one
    the patient's record used, :func:`lvenv.anatomy.load_regression`); ``progress(done, total)``
    after each refit; the regression is of the patient's LO heart model. A patient whose maps do not come from the regression raises
    :class:`~lvenv.validation.InputError`.
    """
    draws, seed = integer("draws", draws, 2, 1000), integer("seed", seed, 0)
    require_regression_maps(patient)
    if missing := [n for n in DEFAULT_ACTION_PARAMS if n not in parameters]:
        raise InputError(f"parameters lack {missing}; a refit starts from every one of {list(DEFAULT_ACTION_PARAMS)}")
    start = patient.heart.replace(**{n: parameters[n] for n in DEFAULT_ACTION_PARAMS})
    maps = [patient.heart.lo, *map_draws(patient.heart.geometry, draws, seed=seed, regression=regression, model=presets.model_of(patient.heart.elements))]
    results = []
    for j, lo in enumerate(maps):
        one = dataclasses.replace(patient, name=f"{patient.name}, maps {j}", heart=start.replace(lo=lo))
        results.append(fit_lm(one, budget=budget, starts=1, steps_per_beat=steps_per_beat, plausibility=plausibility))
        if progress is not None:
            progress(j + 1, len(maps))
    control, refits = results[0], results[1:]
    values = {n: np.array([r.parameters[n] if is_usable(r.status) else np.nan for r in refits]) for n in DEFAULT_ACTION_PARAMS}
    return MapSpread(values, np.array([r.mismatch for r in refits]), tuple(r.status for r in refits),
                     {n: float(control.parameters[n]) for n in DEFAULT_ACTION_PARAMS}, float(control.mismatch))
