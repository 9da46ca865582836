"""The FE oracle's training runs: N and HF under Table 2 conditions ①②③; prints one JSON object.

    python scripts/fe_training_runs.py [--mesh-size 10] [--dt 0.01] [--cache-dir DIR]

One beat each from the documented initial state (DESIGN §1.2), plus a fidelity-check setting:
N in the default closed loop (``lvenv.params.Circulation()``), second beat of two. Per run: EDV,
ESV (ml), EF, peak P_lv (kPa and mmHg), IVCT, ET, IVRT (ms) from
:func:`fe_oracle.metrics.beat_metrics`, the fibre-stretch range seen by the quadrature-point
cells (min, 1st and 99th percentile, max over the run) and the wall-clock time. Results are
cached, so a second call only reads them back.
"""

from __future__ import annotations

import argparse
import json

import fe_oracle
from fe_oracle.cases import HF_UNLOADED, N_UNLOADED
from fe_oracle.metrics import beat_metrics
from lvenv.params import Circulation
from lvenv.units import kpa_to_mmhg, s_to_ms


def _row(geometry, case, h: float, dt: float, cache_dir, beats: int = 1) -> dict:
    res = fe_oracle.run(geometry, case, mesh_size=h, dt=dt, beats=beats, cache_dir=cache_dir)
    m, meta = beat_metrics(res), res.metadata
    return {
        "EDV_ml": m["EDV"],
        "ESV_ml": m["ESV"],
        "EF": m["EF"],
        "P_lv_peak_kPa": m["P_lv_peak"],
        "P_lv_peak_mmHg": float(kpa_to_mmhg(m["P_lv_peak"])),
        **{f"{k}_ms": float(s_to_ms(m[k])) for k in ("IVCT", "ET", "IVRT")},
        "P_ao_sys_dia_mmHg": [float(kpa_to_mmhg(m["P_ao_sys"])), float(kpa_to_mmhg(m["P_ao_dia"]))],
        "valve_cycle_found": bool(m["valid"]),
        "stretch_min_p01_p99_max": [meta["stretch_min"], meta["stretch_p01"], meta["stretch_p99"], meta["stretch_max"]],
        "activation_time_max_ms": float(s_to_ms(meta["activation_time_max_s"])),
        "wall_s": meta["wall_s"],
        "from_cache": res.from_cache,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh-size", type=float, default=10.0, help="mesh size h (mm)")
    parser.add_argument("--dt", type=float, default=0.01, help="time step (s)")
    parser.add_argument("--cache-dir", default=None, help="oracle cache (default: fe_oracle's)")
    args = parser.parse_args()
    report = {"mesh_size_mm": args.mesh_size, "dt_s": args.dt, "runs": {}}
    for name, geometry in (("N", N_UNLOADED), ("HF", HF_UNLOADED)):
        for k in (1, 2, 3):
            report["runs"][f"{name}{k}"] = _row(geometry, k, args.mesh_size, args.dt, args.cache_dir)
    report["runs"]["N_closed_loop"] = _row(N_UNLOADED, Circulation(), args.mesh_size, args.dt, args.cache_dir, beats=2)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
