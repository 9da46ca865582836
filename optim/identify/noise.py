"""The measurement model of identification: each target's error and the misfit χ².

Each target k is measured with an independent Gaussian error of standard deviation σ_k
(:data:`NOISE`, internal units; replace it with your laboratory's values), so a parameter set's
misfit is χ²(θ) = Σ_k ((o_k(θ) − t_k) / σ_k)². Where the defaults come from:

* EF 0.05: two expert readers of the same 2-D echo studies (Simpson's biplane, 140 patients)
  differed by 0.96 ± 7.0 EF points (Akil S et al., Clin Physiol Funct Imaging 2024,
  doi:10.1111/cpf.12918), so one reading's error is 7.0/√2 ≈ 5 points.
* Cuff pressures 5 mmHg: a validated cuff device may differ from the reference by a mean of at
  most 5 mmHg with a standard deviation of at most 8 mmHg (AAMI/ESH/ISO 81060-2; Stergiou G et
  al., J Hypertens 36:472, 2018). 5 mmHg is a device well inside that limit; give 8 mmHg for
  the worst device the standard admits.
* Volumes (EDV, ESV, each frame of a cine volume trace) 5 % of the measured volume
  (:class:`Relative`): two observers of the same biplane cine MR studies (18 normal subjects,
  EDV 120 ± 20 ml) differed in EDV by 5.6 ± 7.8 ml (Benjelloun H et al., Am J Cardiol 67:1413,
  1991), one reading's error 7.8/√2 ≈ 5.5 ml or 4.6 % of EDV; short-axis stacks of 10 healthy
  volunteers varied between operators by 4.2 % (EDV) and 6.2 % (ESV) (PMID 15881528). A
  relative error carries these figures over to a heart of another size: 5 ml on a 23 ml ESV
  would be 22 %. Stroke volume, the difference of two readings: 10 %. The frames' errors are
  taken as independent. A reader's contouring habit also shifts all frames together
  (Suinesiaputra A et al., J Cardiovasc Magn Reson 17:63, 2015); this model leaves that shared
  part out, so it overstates what a trace tells (an added shared error can only remove
  information). Pass ``noise={**NOISE, **dict.fromkeys(VOLUME_NAMES, 5.0)}`` for 5 ml on
  every volume.
* Time intervals 10 ms and filling-pressure estimates 5 mmHg: ours, illustrative (no published
  inter-observer error was at hand for them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from lvenv.metrics import FRAME_NAMES
from lvenv.patients import Patient
from lvenv.units import mmhg_to_kpa
from lvenv.validation import InputError, real

__all__ = ["NOISE", "Relative", "VOLUME_NAMES", "measurement_sd", "chi2_weighted", "chi2"]


@dataclasses.dataclass(frozen=True)
class Relative:
    """A measurement error proportional to the measured value: σ_k = ``fraction`` × abs(t_k).

    A :data:`NOISE` entry is either this or a plain number, the standard deviation in internal
    units. Scaling by a number scales the fraction (``2 * Relative(0.05)`` is ``Relative(0.1)``).
    """

    fraction: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "fraction", real("Relative.fraction", self.fraction, 0.0, lo_open=True))

    def __mul__(self, factor: float) -> Relative:
        return Relative(self.fraction * factor)

    __rmul__ = __mul__

    def __truediv__(self, divisor: float) -> Relative:
        return Relative(self.fraction / divisor)


#: The volume metrics: their measurement errors are relative (module docstring).
VOLUME_NAMES = ("EDV", "ESV", *FRAME_NAMES)
#: Standard deviation of each target's measurement error (sources in the module docstring):
#: EF 0.05, time intervals 10 ms, pressures 5 mmHg (filling pressures included), in internal
#: units; volumes 5 % of the measured volume (each frame of a volume trace too), stroke volume 10 %.
NOISE: dict[str, float | Relative] = {
    "EF": 0.05, "IVCT": 0.010, "ET": 0.010, "IVRT": 0.010, "filling_time": 0.010,
    "P_ao_sys": float(mmhg_to_kpa(5.0)), "P_ao_dia": float(mmhg_to_kpa(5.0)), "P_ao_mean": float(mmhg_to_kpa(5.0)),
    "P_ao_pulse": float(mmhg_to_kpa(5.0)), "P_lv_peak": float(mmhg_to_kpa(5.0)), "SV": Relative(0.10),
    "EDP": float(mmhg_to_kpa(5.0)), "P_at_mean": float(mmhg_to_kpa(5.0)), **dict.fromkeys(VOLUME_NAMES, Relative(0.05)),
}


def measurement_sd(targets: Mapping[str, float], noise: Mapping[str, float | Relative] = NOISE) -> np.ndarray:
    """σ_k of each target (internal units, in the targets' order): ``noise[k]``, or its fraction
    of abs(t_k) for a :class:`Relative` entry."""
    missing = [k for k in targets if k not in noise]
    if missing:
        raise InputError(f"no measurement error for the target(s) {missing}; give noise={{name: sd}} in internal units "
                         "or noise={name: Relative(fraction)}")
    sigma = np.array([noise[k].fraction * abs(float(t)) if isinstance(noise[k], Relative) else float(noise[k])
                      for k, t in targets.items()])
    bad = [f"{k} = {float(s)}" for k, s in zip(targets, sigma) if not (np.isfinite(s) and s > 0)]
    if bad:
        raise InputError(f"measurement error(s) {bad} must be finite and > 0 (a relative error of a zero target is 0)")
    return sigma


def chi2_weighted(patient: Patient, noise: Mapping[str, float | Relative] = NOISE) -> Patient:
    """``patient`` with target weights w_k = (t_k / σ_k)², so that the env's objective (relative
    errors, weighted) is χ² up to a constant factor."""
    sigma = measurement_sd(patient.targets, noise)
    return dataclasses.replace(patient, weights={k: (t / s) ** 2 for (k, t), s in zip(patient.targets.items(), sigma)})


def chi2(patient: Patient, observation: Mapping[str, float], noise: Mapping[str, float | Relative] = NOISE) -> float:
    """Σ_k ((o_k − t_k) / σ_k)² over the patient's targets (module docstring)."""
    o = np.array([observation[k] for k in patient.targets])
    t = np.array(list(patient.targets.values()))
    return float(np.sum(((o - t) / measurement_sd(patient.targets, noise)) ** 2))
