"""Local identifiability: the noise-scaled sensitivity of a patient's targets at a parameter set.

:func:`sensitivity`: S = diag(1/σ) dM/dθ · dθ/du at a parameter set, by :func:`lvenv.jacobian`,
with σ the measurement errors of :mod:`optim.identify.noise`, per unit-cube coordinate u of
:class:`lvenv.identification.ParameterSpace` (log axes where marked): its singular values (χ per
unit-cube step) and the directions that change no target to first order (singular value below
1e-3 of the largest), by parameter name.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

import lvenv
from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.patients import Patient
from lvenv.validation import InputError
from optim.identify.noise import NOISE, Relative, measurement_sd

__all__ = ["Sensitivity", "sensitivity"]


@dataclasses.dataclass(frozen=True)
class Sensitivity:
    """S (targets × parameters), its singular values and null directions by parameter name."""

    names: tuple[str, ...]
    targets: tuple[str, ...]
    matrix: np.ndarray
    singular_values: np.ndarray
    null_directions: list[dict[str, float]]

    def null_component(self, name: str) -> float:
        """Length of parameter ``name``'s part of the null space (0: locally pinned)."""
        return float(np.sqrt(sum(d[name] ** 2 for d in self.null_directions)))


def sensitivity(patient: Patient, parameters: Mapping[str, float] | None = None, *, noise: Mapping[str, float | Relative] = NOISE,
                steps_per_beat: int = 1000) -> Sensitivity:
    """S at ``parameters`` (default: the patient's own values) of :data:`DEFAULT_ACTION_PARAMS`."""
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    heart = patient.heart.replace(**dict(parameters or {}))
    targets = tuple(patient.targets)
    jac = lvenv.jacobian(heart, wrt=space.names, metrics=targets, steps_per_beat=steps_per_beat)
    if jac.status != "ok":
        raise InputError(f"the heart at these parameters has no usable steady state (status {jac.status!r})")
    x = np.array([float(heart.get(n)) for n in space.names])
    matrix = jac.values * space.rate(x)[None, :] / measurement_sd(patient.targets, noise)[:, None]
    _, sv, vt = np.linalg.svd(matrix)
    rank = int(np.sum(sv > 1e-3 * sv[0]))
    null = [dict(zip(space.names, map(float, v))) for v in vt[rank:]]
    return Sensitivity(space.names, targets, matrix, sv, null)
