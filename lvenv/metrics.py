"""The one registry of beat metrics (DESIGN §1.5): name, unit, display, observation bounds, target range.

Every table, plot, observation space and patient check reads this registry; nothing else lists
metric names, units or bounds. Internal units: 1 (EF), ml, s, kPa, ml/s. Display units are what
people read (%, ml, ms, mmHg, l/min); every display conversion is a scaling by
:attr:`Metric.scale` from :mod:`lvenv.units`.

``bounds`` are the environment's observation-space bounds. ``target`` is the range a measured
target may take in a patient record (open below: zero or negative volumes, durations and
pressures are impossible measurements).
"""

from __future__ import annotations

import dataclasses
import math

from lvenv.units import MMHG_PER_KPA, MS_PER_S

__all__ = ["Metric", "METRICS", "METRIC_NAMES", "SUMMARY_NAMES", "N_FRAMES", "FRAME_NAMES", "OBS_NAMES", "header", "display"]


@dataclasses.dataclass(frozen=True)
class Metric:
    """One beat metric. ``units`` internal; ``label``/``display_units``/``scale`` for people."""

    name: str
    units: str
    doc: str
    label: str
    display_units: str
    scale: float
    bounds: tuple[float, float]
    target: tuple[float, float]

    def to_display(self, value):
        """Internal units → display units (``value * scale``)."""
        return value * self.scale

    def from_display(self, value):
        """Display units → internal units."""
        return value / self.scale


_ML_S_TO_L_MIN = 60.0 / 1000.0
_VOLUME = dict(units="ml", display_units="ml", scale=1.0, bounds=(0.0, 1e5), target=(0.0, 1000.0))
_DURATION = dict(units="s", display_units="ms", scale=MS_PER_S, bounds=(0.0, 3.0), target=(0.0, 3.0))
_PRESSURE = dict(units="kPa", display_units="mmHg", scale=MMHG_PER_KPA, bounds=(-200.0, 200.0), target=(0.0, 40.0))

#: Frames of the volume trace per beat, uniformly spaced from the onset (a cine MRI's phases over the RR interval).
N_FRAMES = 20
#: Names of the volume-trace metrics: ``V_frame_00`` (at the onset) … ``V_frame_19``.
FRAME_NAMES = tuple(f"V_frame_{j:02d}" for j in range(N_FRAMES))

#: Every metric by name: units, display units, observation bounds and target range.
METRICS: dict[str, Metric] = {
    m.name: m
    for m in (
        Metric("EF", "1", "ejection fraction SV / EDV", "EF", "%", 100.0, (0.0, 1.0), (0.0, 1.0)),
        Metric("EDV", doc="end-diastolic volume, V at mitral closing", label="EDV", **_VOLUME),
        Metric("ESV", doc="end-systolic volume, V at aortic closing", label="ESV", **_VOLUME),
        Metric("SV", doc="stroke volume EDV − ESV", label="SV", **_VOLUME),
        Metric("IVCT", doc="isovolumic contraction time, mitral closing → aortic opening", label="IVCT", **_DURATION),
        Metric("ET", doc="ejection time, aortic opening → closing", label="ET", **_DURATION),
        Metric("IVRT", doc="isovolumic relaxation time, aortic closing → mitral opening", label="IVRT", **_DURATION),
        Metric("filling_time", doc="mitral opening → next mitral closing", label="filling", **_DURATION),
        Metric("P_lv_peak", doc="peak LV pressure", label="P_lv peak", **_PRESSURE),
        Metric("P_ao_sys", doc="systolic (maximum) central aortic pressure", label="P_ao sys", **_PRESSURE),
        Metric("P_ao_dia", doc="diastolic (minimum) central aortic pressure", label="P_ao dia", **_PRESSURE),
        Metric("P_ao_pulse", "kPa", "aortic pulse pressure sys − dia", "P_ao pulse", "mmHg", MMHG_PER_KPA, (0.0, 400.0), (0.0, 40.0)),
        Metric("P_ao_mean", doc="time-averaged central aortic pressure", label="P_ao mean", **_PRESSURE),
        Metric("CO", "ml/s", "cardiac output SV / T", "CO", "l/min", _ML_S_TO_L_MIN, (0.0, 1e4), (0.0, 1000.0)),
        Metric("EDP", doc="end-diastolic LV pressure, P_lv at mitral closing", label="EDP", **_PRESSURE),
        Metric("P_at_mean", doc="time-averaged atrial pressure (the filling pressure)", label="P_at mean", **_PRESSURE),
        *(Metric(name, doc=f"LV volume at t = {j}/{N_FRAMES} of the beat after its onset (cine frame {j})", label=f"V frame {j}", **_VOLUME)
          for j, name in enumerate(FRAME_NAMES)),
    )
}

#: Metrics of one beat, in the order :func:`lvenv.events.finish` reports them.
METRIC_NAMES = tuple(METRICS)

#: Observation vector of the environment (internal units).
OBS_NAMES = ("EF", "IVCT", "ET", "IVRT", "filling_time", "EDV", "ESV", "P_ao_sys", "P_ao_dia", "P_ao_pulse", "P_ao_mean", "EDP",
             "P_at_mean", *FRAME_NAMES)

#: The beat's summary metrics: all but the volume trace (what tables show).
SUMMARY_NAMES = tuple(n for n in METRIC_NAMES if n not in FRAME_NAMES)


def header(name: str) -> str:
    """Column header with display units, e.g. ``"ET (ms)"``."""
    m = METRICS[name]
    return f"{m.label} ({m.display_units})"


def display(name: str, value: float, digits: int | None = None) -> str:
    """``value`` (internal units) in display units; NaN (a failed member) shows as ``—``."""
    if value is None or not math.isfinite(value):
        return "—"
    digits = (2 if name == "CO" else 1) if digits is None else digits
    return f"{METRICS[name].to_display(float(value)):.{digits}f}"
