"""PV loop and pressure/volume traces as an RGB array (matplotlib, Agg backend)."""

from __future__ import annotations

import numpy as np

from lvenv.patients import Patient
from lvenv.simulation import simulate
from lvenv.units import MS_PER_S, kpa_to_mmhg


def pv_image(heart, y, patient: Patient, steps_per_beat: int) -> np.ndarray:
    """One beat of ``heart`` from state ``y``: PV loop (left) and P, V against time (right)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    res = simulate(heart, beats=1, initial_state=y, steps_per_beat=steps_per_beat)
    tr = res.traces
    fig = Figure(figsize=(8, 3.5), dpi=80)
    canvas = FigureCanvasAgg(fig)
    ax_pv, ax_t = fig.subplots(1, 2)
    ax_pv.plot(tr.V, kpa_to_mmhg(tr.P_lv), color="C3")
    ax_pv.set(xlabel="V (ml)", ylabel="P_lv (mmHg)", title=f"{patient.name}: EF {100 * res.metrics['EF']:.0f} %")
    t_ms = tr.t * MS_PER_S
    ax_t.plot(t_ms, kpa_to_mmhg(tr.P_lv), label="P_lv", color="C3")
    ax_t.plot(t_ms, kpa_to_mmhg(tr.P_ao), label="P_ao", color="C0")
    ax_t.set(xlabel="t (ms)", ylabel="P (mmHg)")
    ax_v = ax_t.twinx()
    ax_v.plot(t_ms, tr.V, label="V", color="C2", ls="--")
    ax_v.set_ylabel("V (ml)")
    ax_t.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
