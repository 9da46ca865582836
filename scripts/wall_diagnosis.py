"""The FE wall's distribution of stretch, stretch rate and active tension against the LO cells (issue 30, diagnosis); JSON out.

    python scripts/wall_diagnosis.py [--hearts normal heart_failure] [--conditions 1 2 3] [--mesh-size 6] [--dt 0.005] [--out out/diagnosis]

For each built-in trained heart and training condition, one FE beat of the oracle (as
`optim.congruency.oracle_data` runs it) that also records, at every accepted step, the 5, 25,
50, 75 and 95 % quantiles and the mean over the wall's quadrature points of the fibre stretch
λ, its rate dλ/dt and the active tension Ta (`fe_oracle.dolfinx_backend.run_beat`'s
``wall_quantiles``), beside the trained LO heart's beat under the same condition. The LO heart's
pressure law P = μ2 Ta + Ppass(V) (`lvenv.coupling`) read backwards turns each beat into the
tension it implies: the LO cell's own Ta, and the FE beat's Ta_FE = (P_FE − Ppass(V_FE)) / μ2
with the same maps. These questions separate the candidate mechanisms:

* **Kinetics:** does the wall's tension (mean over the points) rise and fall like the one
  LO cell's? Reported: the time of the peak, the times of 50 % rise and of 50 % and 10 % fall
  from the peak (ms after the beat's onset), and the fall from 50 % to 10 % (ms).
* **Pressure law:** is the FE pressure the LO law of the wall's mean tension, i.e. is
  g(t) = Ta_FE / mean Ta (the gain the LO cell's μ2 has to stand for) constant over the beat?
  Reported: its median per window of the FE beat (`optim.diagnosis.window_masks`), over the
  samples where the wall's mean Ta is at least 10 % of its peak.
* **Which points carry the pressure:** the least-squares gain G and the relative residual
  ‖Ta_FE − G q(t)‖ / ‖Ta_FE‖ of Ta_FE against each recorded quantile q(t) of the wall's
  tension and against its mean: the trace that fits best is the part of the wall whose
  tension the cavity pressure follows.
* **Is the wall's stretch a function of the volume?** The LO maps make each cell's λ a
  function of its volume (linear, :func:`lvenv.coupling.stretch`). Each quantile of the wall's
  fibre stretch is fitted over the beat by a polynomial in x = V_FE/V0 − 1 of degree 1 and of
  degree :data:`POLY_DEGREE`. Reported: the RMS residual of each (a curved map would shrink
  the second), the share of the linear residual² per window, and the quantile's swing inside
  the isovolumic windows (upstroke and relaxation), where V stands still and every function of
  V does too. Then the plane λ ≈ λ0 + s x + k P_FE: its RMS residual and k (1/kPa), i.e. how
  much of what V leaves the cavity pressure explains. Beside them the range of λ over the beat
  of the single LO cell and of the 3-cell series heart's cells (:mod:`lvenv.multielement`,
  its shipped record ``<heart>_series3``).
* **Would a better stretch map help the cell?** One Land cell driven by the FE beat's own
  kinematics, λ(t) = 1 + μ1 x_FE(t) + k P_FE(t) (:func:`driven_tension`), gives the pressure
  μ2 Ta + Ppass(V_FE) with μ2 by least squares. Reported: its relative misfit to P_FE at the
  trained maps (k = 0), with (μ1, delay) refitted (k = 0), and with (μ1, delay, k) refitted
  (:func:`driven_fit`). If the stretch map limited the LO heart, the third would fall well
  below the second.
* **Would a gain that follows the volume help?** The wall's geometry turns fibre tension into
  cavity pressure with a gain that grows as the cavity shrinks and the wall thickens (a
  thick-walled sphere's Laplace law), which the LO law's constant μ2 cannot follow. The same
  driven cell read through P = μ2 (1 + κ x_FE) Ta + Ppass(V_FE), with (μ2, κ) by least squares
  (:func:`pressure_law`) and (μ1, delay) refitted: if the constant gain limited the LO heart,
  its misfit would fall well below the (μ1, delay) fit's and κ would be negative in every beat.

Also per window the wall's interquartile range of λ and dλ/dt against the LO λ's range. Each
FE beat is written to ``--out``/wall/<heart>_<condition>_h<h>_dt<dt>ms.npz (`lvenv.archive`); a
rerun reads it instead of solving again. One FE beat takes about a minute on one core at h = 6 mm.
Writes ``--out``/wall.md (tables) and wall.png (the wall's tension quantiles, the FE-implied
tension and the LO cell's, each over its peak, under condition ②).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import fe_oracle  # noqa: E402
from lvenv import archive, cell, coupling, integrator, multielement, presets  # noqa: E402
from lvenv.geometry import cavity_volume  # noqa: E402
from lvenv.params import CellParams, Heart, LOParams, ranges  # noqa: E402
from lvenv.simulation import simulate  # noqa: E402
from lvenv.trained import builtin  # noqa: E402
from optim import congruency, diagnosis  # noqa: E402
from scripts.train_presets import HEARTS  # noqa: E402

#: The quantiles over the quadrature points that the FE beat records.
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
#: Samples whose wall mean Ta is below this fraction of its peak carry no gain.
GAIN_FLOOR = 0.1
#: Degree of the curved stretch map that the linear one is compared with.
POLY_DEGREE = 5
#: The windows in which the cavity volume stands still.
ISOVOLUMIC = ("upstroke", "relaxation")
#: ROS2 steps per sample interval of the FE beat for the driven cell.
DRIVEN_SUBSTEPS = 10
#: Starting points of the driven fits: μ1 (k = 0), then k (1/kPa) from the best (μ1, delay).
DRIVEN_STARTS = {"mu1": (0.1, 0.2, 0.3), "k": (-0.006, -0.002, 0.002)}


def fe_beat(geometry, condition: int, mesh_size: float, dt: float, path: pathlib.Path) -> tuple[dict[str, np.ndarray], dict]:
    """The FE beat with its wall record, from ``path`` or solved (and saved there)."""
    if path.exists():
        return archive.load(path, "wall-diagnosis beat")
    from fe_oracle.dolfinx_backend import run_beat
    from fe_oracle.material import Guccione

    traces, meta, _ = run_beat(geometry, presets.training_circulation(condition), CellParams(), Guccione(), mesh_size, dt, 1, wall_quantiles=QUANTILES)
    archive.save(path, traces, {k: v for k, v in meta.items() if isinstance(v, (int, float, str, list))})
    return traces, meta


def _crossing(t: np.ndarray, y: np.ndarray, level: float, after: int, rising: bool) -> float:
    """First time after index ``after`` where ``y`` crosses ``level`` (`optim.diagnosis.crossings`), ms."""
    times = diagnosis.crossings(t[after:], y[after:] - level, rising)
    return float(1000 * times[0]) if len(times) else float("nan")


def timing(t: np.ndarray, ta: np.ndarray) -> dict[str, float]:
    """Peak, 50 % rise, 50 % and 10 % fall times (ms) of a tension trace, and the 50 → 10 % fall (ms)."""
    k = int(np.argmax(ta))
    peak = float(ta[k])
    out = {"peak_ms": float(1000 * t[k]), "rise50_ms": _crossing(t[: k + 1], ta[: k + 1], 0.5 * peak, 0, True),
           "fall50_ms": _crossing(t, ta, 0.5 * peak, k, False), "fall10_ms": _crossing(t, ta, 0.1 * peak, k, False)}
    out["fall50_to_10_ms"] = out["fall10_ms"] - out["fall50_ms"]
    return out


def stretch_map(x: np.ndarray, pressure: np.ndarray, lam: np.ndarray, masks: dict[str, np.ndarray]) -> dict:
    """How well a function of the volume, x = V/V0 − 1, gives one stretch trace ``lam`` over a
    beat, and how much the cavity ``pressure`` (kPa) adds.

    Returns the slope dλ/dx of the linear fit, the RMS residuals of the linear fit, of a
    polynomial of degree :data:`POLY_DEGREE` and of the plane λ0 + s x + k P (with k, 1/kPa), the
    linear residual²'s share per window of ``masks``, and the trace's swing (max − min) in each
    :data:`ISOVOLUMIC` window and over the beat.
    """
    linear = np.polyfit(x, lam, 1)
    r1 = lam - np.polyval(linear, x)
    r_poly = lam - np.polyval(np.polyfit(x, lam, POLY_DEGREE), x)
    design = np.column_stack([np.ones_like(x), x, pressure])
    plane = np.linalg.lstsq(design, lam, rcond=None)[0]
    r_plane = lam - design @ plane
    total = float(np.sum(r1**2))
    return {"slope": float(linear[0]), "rms_linear": float(np.sqrt(np.mean(r1**2))), "rms_poly": float(np.sqrt(np.mean(r_poly**2))),
            "rms_plane": float(np.sqrt(np.mean(r_plane**2))), "dlam_dP_per_kPa": float(plane[2]),
            "share": {w: float(np.sum(r1[m] ** 2) / total) for w, m in masks.items()},
            "swing": {w: float(np.ptp(lam[masks[w]])) for w in ISOVOLUMIC} | {"beat": float(np.ptp(lam))}}


@jax.jit
def driven_tension(t: jax.Array, lam: jax.Array, delay: jax.Array) -> jax.Array:
    """Ta (kPa) at the samples ``t`` (s) of Land cells (default :class:`~lvenv.params.CellParams`)
    whose stretch follows ``lam`` (samples, B), linear between samples, each with its calcium
    transient delayed by ``delay`` (s, (B,)): ROS2 (:func:`lvenv.integrator.ros2_step`),
    :data:`DRIVEN_SUBSTEPS` steps per interval, from the rest state at ``lam[0]``. Shape (samples, B)."""
    p = CellParams()
    rates, norm = cell.rates(p), cell.transient_norm(p)
    lo = LOParams(delay=delay)
    rate = jnp.diff(lam, axis=0) / jnp.diff(t)[:, None]

    def interval(y, i):
        h = (t[i + 1] - t[i]) / DRIVEN_SUBSTEPS
        f = lambda u, yy: cell.derivatives(yy, coupling.calcium(u, lo, p, norm), lam[i] + rate[i] * (u - t[i]), rate[i], p, rates)

        def sub(y, j):
            t0 = t[i] + j * h
            return integrator.ros2_step(f, y, h, t0, t0 + h, jnp.ones_like(t0)), None

        y, _ = jax.lax.scan(sub, y, jnp.arange(DRIVEN_SUBSTEPS))
        return y, cell.active_tension(y, lam[i + 1], p)

    y0 = cell.rest_state(lam[0], p)
    _, ta = jax.lax.scan(interval, y0, jnp.arange(len(t) - 1))
    return jnp.concatenate([cell.active_tension(y0, lam[0], p)[None], ta])


def pressure_law(ta: np.ndarray, x: np.ndarray, passive: np.ndarray, pressure: np.ndarray, gain: bool) -> tuple[float, np.ndarray]:
    """The relative misfit ‖P − Ppass − μ2 (1 + κ x) Ta‖ / ‖P‖ of the LO pressure law, with μ2
    (and with ``gain`` also κ, the gain's slope in x = V/V0 − 1) by least squares, and the
    coefficients: (μ2,) or (μ2, μ2 κ). ``ta``, ``passive`` and ``pressure`` in kPa."""
    design = np.column_stack([ta, ta * x] if gain else [ta])
    coefficients = np.linalg.lstsq(design, pressure - passive, rcond=None)[0]
    return float(np.linalg.norm(design @ coefficients + passive - pressure) / np.linalg.norm(pressure)), coefficients


def driven_fit(traces: dict[str, np.ndarray], v0: float, lo: LOParams) -> dict:
    """The relative pressure misfit of one cell driven by the FE beat's kinematics (module
    docstring): at the trained ``lo`` (``trained``), with (μ1, delay) fitted at k = 0
    (``volume``), with (μ1, delay, k) fitted (``volume_and_pressure``) and with (μ1, delay)
    fitted through the gain μ2 (1 + κ x) (``volume_gain``); each with its parameters (delay in
    ms, k in 1/kPa, κ per unit x). Nelder–Mead from :data:`DRIVEN_STARTS`."""
    t, v, pressure = (np.asarray(traces[k], float) for k in ("t", "V", "P_lv"))
    x, passive = v / v0 - 1.0, np.asarray(coupling.passive_pressure(v, v0, lo))
    bounds = ranges()

    def law(mu1: float, k: float, delay: float, gain: bool = False) -> tuple[float, np.ndarray]:
        if not (bounds["mu1"][0] <= mu1 <= bounds["mu1"][1] and bounds["delay"][0] <= delay <= bounds["delay"][1]):
            return np.inf, np.full(1 + gain, np.nan)
        ta = np.asarray(driven_tension(t, (1.0 + mu1 * x + k * pressure)[:, None], np.array([delay])))[:, 0]
        return pressure_law(ta, x, passive, pressure, gain)

    def misfit(mu1: float, k: float, delay: float, gain: bool = False) -> float:
        return law(mu1, k, delay, gain)[0]

    options = {"xatol": 1e-6, "fatol": 1e-7, "maxfev": 600}
    volume = min((minimize(lambda z: misfit(z[0], 0.0, z[1]), [m, lo.delay], method="Nelder-Mead", options=options)
                  for m in DRIVEN_STARTS["mu1"]), key=lambda r: r.fun)
    both = min((minimize(lambda z: misfit(*z), [volume.x[0], k, volume.x[1]], method="Nelder-Mead", options=options)
                for k in DRIVEN_STARTS["k"]), key=lambda r: r.fun)
    gain = min((minimize(lambda z: misfit(z[0], 0.0, z[1], gain=True), [m, volume.x[1]], method="Nelder-Mead", options=options)
                for m in (volume.x[0], *DRIVEN_STARTS["mu1"])), key=lambda r: r.fun)
    mu2, mu2_kappa = law(gain.x[0], 0.0, gain.x[1], gain=True)[1]
    return {"trained": misfit(lo.mu1, 0.0, lo.delay),
            "volume": {"misfit": float(volume.fun), "mu1": float(volume.x[0]), "delay_ms": 1000 * float(volume.x[1])},
            "volume_and_pressure": {"misfit": float(both.fun), "mu1": float(both.x[0]), "k_per_kPa": float(both.x[1]), "delay_ms": 1000 * float(both.x[2])},
            "volume_gain": {"misfit": float(gain.fun), "mu1": float(gain.x[0]), "kappa": float(mu2_kappa / mu2), "delay_ms": 1000 * float(gain.x[1])}}


def compare(name: str, condition: int, traces: dict[str, np.ndarray], meta: dict) -> dict:
    """The comparison of the module docstring for one FE beat and the trained LO heart ``name``."""
    trained = builtin(name)
    lo, geometry = trained.lo, HEARTS[name][0]
    v0 = float(cavity_volume(geometry))
    heart = Heart(geometry=geometry, lo=lo, cell=CellParams(), circulation=presets.training_circulation(condition))
    sim = simulate(heart, beats=1, steps_per_beat=1000)
    t_lo, v_lo, p_lo = (np.asarray(getattr(sim.traces, k), float) for k in ("t", "V", "P_lv"))
    t = np.asarray(traces["t"], float)
    wall = np.asarray(traces["wall"], float)  # (samples, field, quantiles + mean)
    lam_q, rate_q, ta_q = wall[:, 0], wall[:, 1], wall[:, 2]
    ta_mean = ta_q[:, -1]
    ta_lo = (p_lo - np.asarray(coupling.passive_pressure(v_lo, v0, lo))) / lo.mu2
    ta_fe = (traces["P_lv"] - np.asarray(coupling.passive_pressure(traces["V"], v0, lo))) / lo.mu2
    lam_lo = np.interp(t, t_lo, np.asarray(coupling.stretch(v_lo, v0, lo)))
    masks = diagnosis.window_masks(t, diagnosis.valve_events(traces))
    strong = ta_mean >= GAIN_FLOOR * ta_mean.max()
    gain = np.where(strong, ta_fe / np.where(strong, ta_mean, 1.0), np.nan)
    windows = {}
    for w, m in masks.items():
        g = gain[m & strong]
        windows[w] = {"gain_median": float(np.median(g)) if len(g) else None,
                      "lam_iqr": float(np.median(lam_q[m, 3] - lam_q[m, 1])) if m.any() else None,
                      "rate_iqr_per_s": float(np.median(rate_q[m, 3] - rate_q[m, 1])) if m.any() else None,
                      "lam_lo_range": [float(lam_lo[m].min()), float(lam_lo[m].max())] if m.any() else None}
    c = float(np.sqrt(congruency.congruency(traces, t_lo, v_lo[None], p_lo[None])[0]))
    fits, stretch = {}, {}
    x, pressure = np.asarray(traces["V"], float) / v0 - 1.0, np.asarray(traces["P_lv"], float)
    for j, label in enumerate([f"q{round(100 * q):02d}" for q in QUANTILES] + ["mean"]):
        q = ta_q[:, j]
        fitted = float(np.dot(q, ta_fe) / np.dot(q, q))
        fits[label] = {"gain": fitted, "rel_residual": float(np.linalg.norm(ta_fe - fitted * q) / np.linalg.norm(ta_fe))}
        stretch[label] = stretch_map(x, pressure, lam_q[:, j], masks)
    series = builtin(f"{name}_series3")
    series_heart = series.heart(circulation=presets.training_circulation(condition))
    lo_range = {"single": [float(lam_lo.min()), float(lam_lo.max())],
                "series3": [float(v) for v in multielement.simulate(series_heart, series.elements, steps_per_beat=1000, traces=False).stretch],
                "wall_q05_q95": [float(lam_q[:, 0].min()), float(lam_q[:, 4].max())]}
    return {"heart": name, "condition": condition, "C": c, "mu2": lo.mu2, "delay_ms": 1000 * lo.delay,
            "activation_quantiles_ms": [1000 * x for x in meta.get("activation_quantiles_s", [])],
            "timing": {"wall_mean": timing(t, ta_mean), "wall_median": timing(t, ta_q[:, 2]), "fe_implied": timing(t, ta_fe),
                       "lo_cell": timing(t_lo, ta_lo)},
            "peak_kPa": {"wall_mean": float(ta_mean.max()), "wall_p95": float(ta_q[:, 4].max()), "fe_implied": float(ta_fe.max()), "lo_cell": float(ta_lo.max())},
            "windows": windows, "pressure_fit": fits, "stretch_map": stretch, "stretch_range": lo_range, "driven": driven_fit(traces, v0, lo), "fe_wall_s": meta.get("wall_s"),
            "volume_range": [float(x.min()), float(x.max())],
            "curves": {"t": t, "wall": ta_q, "fe_implied": ta_fe, "t_lo": t_lo, "lo_cell": ta_lo}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hearts", nargs="+", choices=sorted(HEARTS), default=sorted(HEARTS))
    parser.add_argument("--conditions", nargs="+", type=int, choices=congruency.CONDITIONS, default=list(congruency.CONDITIONS))
    parser.add_argument("--mesh-size", type=float, default=fe_oracle.DEFAULT_MESH_SIZE, help="oracle mesh size h (mm)")
    parser.add_argument("--dt", type=float, default=0.005, help="oracle time step (s)")
    parser.add_argument("--out", default="out/diagnosis", help="folder of wall.md, wall.png and the FE beats (wall/, resumed from)")
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    (out / "wall").mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.hearts:
        for k in args.conditions:
            t0 = time.perf_counter()
            traces, meta = fe_beat(HEARTS[name][0], k, args.mesh_size, args.dt, out / "wall" / f"{name}_{k}_h{args.mesh_size:g}_dt{1000 * args.dt:g}ms.npz")
            rows.append(compare(name, k, traces, meta) | {"seconds": time.perf_counter() - t0})
            print(f"{name} condition {k}: C {100 * rows[-1]['C']:.2f} %", file=sys.stderr, flush=True)
    command = "python scripts/wall_diagnosis.py " + " ".join(sys.argv[1:])
    (out / "wall.md").write_text(markdown(rows, command))
    figure([r for r in rows if r["condition"] == 2] or rows, out / "wall.png")
    print(json.dumps({"settings": vars(args), "quantiles": QUANTILES, "rows": [{k: v for k, v in r.items() if k != "curves"} for r in rows]}, indent=1))


def markdown(rows: list[dict], command: str) -> str:
    """The tables of wall.md: tension timing per trace, the fit of the FE pressure to each quantile, the gain per
    window, the stretch maps of the wall, the LO cells' stretch range and the driven cell, with a constant gain and one that
    follows the volume."""
    traces = ("wall_median", "wall_mean", "fe_implied", "lo_cell")
    lines = [f"Made by `{command}` (its FE beats are kept in `wall/` beside this page). Times in ms after the beat's onset.", "",
             "| heart | condition | C (%) | trace | peak | 50 % rise | 50 % fall | 10 % fall |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for name in traces:
            tm = r["timing"][name]
            lines.append(f"| {r['heart']} | {r['condition']} | {100 * r['C']:.2f} | {name} | {tm['peak_ms']:.0f} | {tm['rise50_ms']:.0f} | "
                         f"{tm['fall50_ms']:.0f} | {tm['fall10_ms']:.0f} |")
    labels = list(rows[0]["pressure_fit"])
    lines += ["", "The FE cavity pressure read as tension through the LO law, Ta_FE = (P_FE − Ppass(V_FE)) / μ2, fitted by one gain "
              "to each quantile of the wall's tension over the quadrature points and to its mean: relative residual (the smallest "
              "marks the part of the wall the pressure follows).", "",
              "| heart | condition | " + " | ".join(labels) + " |", "|---|---|" + "---|" * len(labels)]
    lines += [f"| {r['heart']} | {r['condition']} | " + " | ".join(f"{r['pressure_fit'][k]['rel_residual']:.3f}" for k in labels) + " |" for r in rows]
    windows = list(rows[0]["windows"])
    lines += ["", "Gain Ta_FE / (wall mean Ta) per window of the FE beat (median; a constant gain would make the LO law exact "
              "for the wall's mean tension):", "", "| heart | condition | " + " | ".join(windows) + " |", "|---|---|" + "---|" * len(windows)]
    lines += [f"| {r['heart']} | {r['condition']} | " + " | ".join("–" if r["windows"][w]["gain_median"] is None else f"{r['windows'][w]['gain_median']:.2f}"
                                                                 for w in windows) + " |" for r in rows]
    windows = list(rows[0]["stretch_map"]["q50"]["share"])
    lines += ["", f"The wall's fibre stretch read as a function of the cavity volume: each quantile fitted over the beat by a line and by a "
              f"polynomial of degree {POLY_DEGREE} in V/V0 − 1 (RMS residual), the line's residual² per window (%), and the quantile's "
              "swing in the isovolumic windows, where V stands still, against its swing over the beat; then the plane "
              "λ0 + s x + k P_FE (RMS residual and k).", "",
              "| heart | condition | trace | dλ/dx | RMS line | RMS poly | " + " | ".join(f"{w} (%)" for w in windows)
              + " | swing upstroke | swing relaxation | swing beat | RMS x, P | k (1/kPa) |", "|---|---|---|" + "---|" * (3 + len(windows) + 5)]
    for r in rows:
        for label, m in r["stretch_map"].items():
            lines.append(f"| {r['heart']} | {r['condition']} | {label} | {m['slope']:.3f} | {m['rms_linear']:.4f} | {m['rms_poly']:.4f} | "
                         + " | ".join(f"{100 * m['share'][w]:.0f}" for w in windows)
                         + f" | {m['swing']['upstroke']:.3f} | {m['swing']['relaxation']:.3f} | {m['swing']['beat']:.3f} | {m['rms_plane']:.4f} | "
                         f"{m['dlam_dP_per_kPa']:+.4f} |")
    lines += ["", "The range of λ over the beat: the wall's (from the least of its 5 % quantile to the most of its 95 % quantile), "
              "the single LO cell's and the 3-cell series heart's cells'.", "",
              "| heart | condition | wall 5–95 % | single cell | 3-cell series |", "|---|---|---|---|---|"]
    lines += [f"| {r['heart']} | {r['condition']} | " + " | ".join("{:.3f}–{:.3f}".format(*r["stretch_range"][k]) for k in ("wall_q05_q95", "single", "series3")) + " |"
              for r in rows]
    lines += ["", "One Land cell driven by the FE beat's kinematics, λ = 1 + μ1 (V_FE/V0 − 1) + k P_FE, read through P = μ2 Ta + Ppass(V_FE) "
              "(μ2 by least squares): the relative misfit to P_FE at the trained maps, with (μ1, delay) fitted and k = 0, and with "
              "(μ1, delay, k) fitted; beside it k of the wall's mean stretch (the plane above).", "",
              "| heart | condition | trained | (μ1, delay) | μ1 | delay (ms) | (μ1, delay, k) | μ1 | delay (ms) | k (1/kPa) | wall mean's k |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d, vol, both = r["driven"], r["driven"]["volume"], r["driven"]["volume_and_pressure"]
        lines.append(f"| {r['heart']} | {r['condition']} | {100 * d['trained']:.1f} % | {100 * vol['misfit']:.1f} % | {vol['mu1']:.3f} | {vol['delay_ms']:.0f} | "
                     f"{100 * both['misfit']:.1f} % | {both['mu1']:.3f} | {both['delay_ms']:.0f} | {both['k_per_kPa']:+.4f} | "
                     f"{r['stretch_map']['mean']['dlam_dP_per_kPa']:+.4f} |")
    lines += ["", "The same driven cell read through a gain that follows the volume, P = μ2 (1 + κ (V_FE/V0 − 1)) Ta + Ppass(V_FE) "
              "((μ2, κ) by least squares, (μ1, delay) fitted), against the constant gain's (μ1, delay) fit above.", "",
              "| heart | condition | V_FE/V0 − 1 | (μ1, delay) | (μ1, delay) with κ | μ1 | delay (ms) | κ |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        vol, gain = r["driven"]["volume"], r["driven"]["volume_gain"]
        lines.append(f"| {r['heart']} | {r['condition']} | " + "{:+.2f} to {:+.2f}".format(*r["volume_range"]) + f" | {100 * vol['misfit']:.1f} % | "
                     f"{100 * gain['misfit']:.1f} % | {gain['mu1']:.3f} | {gain['delay_ms']:.0f} | {gain['kappa']:+.3f} |")
    return "\n".join(lines) + "\n"


def figure(rows: list[dict], path: pathlib.Path) -> None:
    """Per row: the wall's Ta quantile bands, its median, the FE-implied and the LO cell's Ta, each over its peak."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(rows), figsize=(4.2 * len(rows), 3.2), squeeze=False)
    for ax, r in zip(axes[0], rows):
        c = r["curves"]
        t, wall = 1000 * np.asarray(c["t"]), np.asarray(c["wall"])
        scale = wall[:, 2].max()
        ax.fill_between(t, wall[:, 0] / scale, wall[:, 4] / scale, color="C0", alpha=0.2, lw=0, label="wall 5–95 %")
        ax.fill_between(t, wall[:, 1] / scale, wall[:, 3] / scale, color="C0", alpha=0.35, lw=0, label="wall 25–75 %")
        ax.plot(t, wall[:, 2] / scale, "C0-", lw=1, label="wall median")
        ax.plot(t, np.asarray(c["fe_implied"]) / np.max(c["fe_implied"]), "k-", lw=1.4, label="FE pressure as tension")
        ax.plot(1000 * np.asarray(c["t_lo"]), np.asarray(c["lo_cell"]) / np.max(c["lo_cell"]), "C3--", lw=1.2, label="LO cell")
        ax.set(xlabel="t (ms)", ylabel="Ta / peak of the median", title=f"{r['heart']}, condition {r['condition']}")
    axes[0, 0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
