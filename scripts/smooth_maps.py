"""Would maps that follow the cell smoothly carry over to the unseen scenarios (issue 30)? JSON
out, and a table in ``--out``/smooth_maps.md.

    python scripts/smooth_maps.py [--hearts normal heart_failure] [--model series3] [--passive] [--order 1] [--ridge 0.01]
                                  [--ends vmax_x4 ...] [--check-dt 0.0025]

Along each scenario's axis (`optim.studies.UNSEEN`, its position s: `optim.studies._position`)
the maps are the trained ones changed smoothly with the position: with f = s / s_i, s_i the
position of the axis' interior point (`optim.studies.INTERIOR`), and e = x1 f (``--order 1``) or
x1 f + x2 f² (``--order 2``), m(s) = m0 exp(e) for μ1, μ2, γ (and with ``--passive`` α, β, a, b,
c) and delay(s) = delay0 + `DELAY_UNIT` e. At s = 0 (the training beats) the maps are the trained
ones, so the training C does not change. x is fitted by least squares from x = 0 on the
congruency residuals (`optim.congruency.residuals`) of the interior point's FE beat, and with
``--order 2`` also of the point three quarters of the way to the end (`optim.studies.OUTER`),
plus ``--ridge`` × ‖x‖² (a ridge on the maps' relative change). Order 1 keeps the maps at the
fitted points and at the end inside their boxes (`optim.congruency.ACTIVE_BOUNDS`,
`optim.congruency.passive_bounds`); order 2 clips them into the boxes. The maps are then carried
to the scenario's end, which the fit never sees: C and the largest pointwise pressure error there
(`optim.studies.generalisation`'s measures) against the frozen maps'. With ``--order 1`` the
outer point is held out: C there with the carried maps (``held_out``) checks the carry on an FE
beat that the fit does not see, without using the scenario's end. It reads the shipped FE
beats (`fe_oracle.run`'s cache) and runs no FE; about 2 min per heart with the nine maps.
``--ends`` keeps some of the scenarios. ``--check-dt`` also measures both at each end against the
FE beat at that time step (s; an FE run of a few minutes per end, cached), to tell the oracle's
own time-step error apart from what the maps miss; the maps are fitted at the oracle's default.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import fe_oracle  # noqa: E402
from lvenv import presets  # noqa: E402
from lvenv.params import Heart  # noqa: E402
from optim.congruency import ACTIVE_BOUNDS, MAP_NAMES, PASSIVE_NAMES, one_beat, passes_validation, passive_bounds, residuals  # noqa: E402
from optim.studies import INTERIOR, OUTER, UNSEEN, _errors, _position, scenario  # noqa: E402
from scripts.train_presets import HEARTS  # noqa: E402

#: LO steps per beat, as `optim.studies` runs its scenarios.
STEPS_PER_BEAT = 1000
#: The delay's change (s) per unit of x at the interior point.
DELAY_UNIT = 0.05


class Carry:
    """The smooth maps of one heart: m0 the trained maps of ``names``, their boxes, and the order
    of e in the position (module docstring); x holds the order's coefficient vectors, x1 first."""

    def __init__(self, heart: Heart, names: tuple[str, ...], order: int = 1):
        self.heart, self.names, self.order = heart, names, order
        box = {**ACTIVE_BOUNDS, **passive_bounds(heart.lo)}
        self.m0 = np.array([float(getattr(heart.lo, n)) for n in names])
        self.log = np.array([n != "delay" for n in names])
        self.lower, self.upper = (np.array([box[n][i] for n in names]) for i in (0, 1))

    def maps(self, x: np.ndarray, f: float) -> np.ndarray:
        """The maps at f times the interior point's position (not clipped)."""
        e = sum(row * f ** (k + 1) for k, row in enumerate(np.reshape(x, (self.order, len(self.names)))))
        return np.where(self.log, self.m0 * np.exp(e), self.m0 + DELAY_UNIT * e)

    def x_box(self, f: float) -> tuple[np.ndarray, np.ndarray]:
        """The x of order 1 whose maps at f times the interior position lie inside the boxes."""
        ends = [np.where(self.log, np.log(np.where(self.log, b, 1.0) / self.m0), (b - self.m0) / DELAY_UNIT) / f for b in (self.lower, self.upper)]
        return np.minimum(*ends), np.maximum(*ends)

    def heart_at(self, change: dict[str, float], x: np.ndarray, f: float) -> Heart:
        """The heart in the scenario ``change`` with the maps at f times the interior position,
        clipped into their boxes."""
        values = np.clip(self.maps(x, f), self.lower, self.upper)
        lo = dataclasses.replace(self.heart.lo, **dict(zip(self.names, map(float, values))))
        return scenario(dataclasses.replace(self.heart, lo=lo), change)


def measure(oracle: dict, hearts: list[Heart]) -> list[dict[str, float]]:
    """C and the largest pointwise errors of each heart's beat against ``oracle`` (NaN for a heart
    whose passive maps fail validation)."""
    ok = [passes_validation(h) for h in hearts]
    _, t, v, p, _ = one_beat([h for h, good in zip(hearts, ok) if good], STEPS_PER_BEAT)
    rows, k = [], 0
    for good in ok:
        if good:
            rows.append(_errors(oracle, t[k], v[k], p[k]))
            k += 1
        else:
            rows.append({"C": float("nan"), "max_rel_error_V": float("nan"), "max_rel_error_P": float("nan")})
    return rows


def study(label: str, heart: Heart, names: tuple[str, ...], ridge: float, order: int = 1, scenarios: dict[str, dict[str, float]] = UNSEEN,
          backend: str = "dolfinx", check_dt: float | None = None, **oracle_options) -> list[dict]:
    """One row per scenario of ``scenarios`` (module docstring), against ``backend``'s beats
    (``oracle_options`` go to `fe_oracle.run`); with ``check_dt`` (s) the end's C and pressure
    error also against its beat at that time step (``end_check``); ``label`` names the heart in
    the progress lines."""
    carry, rows = Carry(heart, names, order), []
    zero = np.zeros(order * len(names))
    for end, change in scenarios.items():
        inner = [INTERIOR[end], OUTER[end]]
        points = inner[:order]
        s_i = _position(heart, points[0][1])
        at = {name: (ch, _position(heart, ch) / s_i) for name, ch in [*inner, (end, change)]}
        oracles = {}
        for name, (ch, _) in at.items():
            target = scenario(heart, ch)
            oracles[name] = fe_oracle.run(target.geometry, target.circulation, backend, cell=target.cell, progress=False, **oracle_options).traces

        def residual(x: np.ndarray) -> np.ndarray:
            """The inner points' congruency residuals (ones for a beat that cannot run or fails),
            from one batched simulation, and the ridge's."""
            hearts = {name: carry.heart_at(at[name][0], x, at[name][1]) for name, _ in points}
            valid = [name for name, h in hearts.items() if passes_validation(h)]
            parts = {name: np.ones(2 * len(oracles[name]["t"])) for name in hearts}
            if valid:
                status, t, v, p, _ = one_beat([hearts[name] for name in valid], STEPS_PER_BEAT)
                for i, name in enumerate(valid):
                    beat = residuals(oracles[name], t[i], v[i:i + 1], p[i:i + 1])[0]
                    if status[i] == "ok" and np.all(np.isfinite(beat)):
                        parts[name] = beat
            return np.concatenate([*parts.values(), np.sqrt(ridge) * x])

        if order == 1:
            (lo1, hi1), (lo_w, hi_w) = carry.x_box(1.0), carry.x_box(at[end][1])
            bounds = (np.minimum(np.maximum(lo1, lo_w), -1e-9), np.maximum(np.minimum(hi1, hi_w), 1e-9))
        else:
            bounds = (-np.inf, np.inf)
        fit = least_squares(residual, zero, bounds=bounds, diff_step=1e-4, max_nfev=60 * len(zero))
        fitted, held_out = [], []
        for k, (name, _) in enumerate(inner):
            ch, f = at[name]
            before, after = measure(oracles[name], [carry.heart_at(ch, zero, f), carry.heart_at(ch, fit.x, f)])
            if k >= order:
                held_out.append({"scenario": name, "C_frozen": before["C"], "C_carried": after["C"]})
            else:
                fitted.append({"scenario": name, "C_frozen": before["C"], "C_fitted": after["C"]})
        ends = [carry.heart_at(change, zero, at[end][1]), carry.heart_at(change, fit.x, at[end][1])]
        frozen_e, carried_e = measure(oracles[end], ends)
        rows.append({"scenario": end, "w": at[end][1], "x": np.reshape(fit.x, (order, len(names))).round(4).tolist(), "evaluations": int(fit.nfev),
                     "fitted": fitted, "held_out": held_out, "end_C_frozen": frozen_e["C"], "end_C_carried": carried_e["C"],
                     "end_P_error_frozen": frozen_e["max_rel_error_P"], "end_P_error_carried": carried_e["max_rel_error_P"]})
        if check_dt is not None:
            target = scenario(heart, change)
            fine = fe_oracle.run(target.geometry, target.circulation, backend, cell=target.cell, dt=check_dt, progress=False, **oracle_options).traces
            oracle_change = _errors(oracles[end], fine["t"], fine["V"], fine["P_lv"])
            rows[-1]["end_check"] = {"dt": check_dt, "oracle_C": oracle_change["C"], "oracle_P_error": oracle_change["max_rel_error_P"],
                                     **{f"{k}_{m}": e[key] for k, e in zip(("frozen", "carried"), measure(fine, ends))
                                        for m, key in (("C", "C"), ("P_error", "max_rel_error_P"))}}
        print(f"{label} {end}: C {frozen_e['C']:.4f} -> {carried_e['C']:.4f}", file=sys.stderr, flush=True)
    return rows


def table(results: dict[str, list[dict]], command: str) -> str:
    """The results as a markdown table, with the command that made it."""
    lines = [f"Made by `{command}`.", "", "| heart | end | fitted points: C frozen → fitted | end C frozen → carried | end pressure error frozen → carried |",
             "|---|---|---|---|---|"]
    for name, rows in results.items():
        for r in rows:
            fitted = "; ".join([*(f"{p['scenario']} {100 * p['C_frozen']:.1f} → {100 * p['C_fitted']:.1f} %" for p in r["fitted"]),
                                *(f"held out: {p['scenario']} {100 * p['C_frozen']:.1f} → {100 * p['C_carried']:.1f} %" for p in r["held_out"])])
            lines.append(f"| {name} | {r['scenario']} | {fitted} | {100 * r['end_C_frozen']:.1f} → {100 * r['end_C_carried']:.1f} % "
                         f"| {100 * r['end_P_error_frozen']:.1f} → {100 * r['end_P_error_carried']:.1f} % |")
        for r in rows:
            if "end_check" in r:
                c = r["end_check"]
                lines.append(f"| {name} | {r['scenario']}, FE at dt = {1000 * c['dt']:g} ms (it moves by C {100 * c['oracle_C']:.2f} %, "
                             f"pressure {100 * c['oracle_P_error']:.1f} %) | | {100 * c['frozen_C']:.1f} → {100 * c['carried_C']:.1f} % "
                             f"| {100 * c['frozen_P_error']:.1f} → {100 * c['carried_P_error']:.1f} % |")
        worst = max(rows, key=lambda r: r["end_C_carried"])
        lines.append(f"| {name} | **worst end** | | {100 * max(r['end_C_frozen'] for r in rows):.1f} → {100 * worst['end_C_carried']:.1f} % ({worst['scenario']}) | |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hearts", nargs="+", default=list(HEARTS), choices=list(HEARTS))
    parser.add_argument("--model", default="series3", choices=sorted(presets.LO_MODELS), help="the LO heart model (default series3)")
    parser.add_argument("--passive", action="store_true", help="carry the passive maps too (nine maps)")
    parser.add_argument("--order", type=int, default=1, choices=(1, 2), help="the maps' change in the position: linear or quadratic (default 1)")
    parser.add_argument("--ridge", type=float, default=0.01, help="weight of ‖x‖² beside C² (default 0.01)")
    parser.add_argument("--ends", nargs="+", choices=list(UNSEEN), default=list(UNSEEN), help="the scenarios (default: all)")
    parser.add_argument("--check-dt", type=float, help="also measure each end against the FE beat at this time step (s)")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/diagnosis"))
    args = parser.parse_args()
    if not args.ridge >= 0:
        parser.error(f"--ridge = {args.ridge} must be >= 0")
    if args.check_dt is not None and not 0 < args.check_dt < 0.05:
        parser.error(f"--check-dt = {args.check_dt} must be in (0, 0.05) s")
    names = (*MAP_NAMES, *PASSIVE_NAMES) if args.passive else MAP_NAMES
    scenarios = {end: UNSEEN[end] for end in args.ends}
    results = {name: study(name, getattr(presets, name)(model=args.model), names, args.ridge, args.order, scenarios, check_dt=args.check_dt)
               for name in args.hearts}
    command = "python scripts/smooth_maps.py " + " ".join(sys.argv[1:])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "smooth_maps.md").write_text(table(results, command))
    print(json.dumps({"command": command, "names": names, "order": args.order, "ridge": args.ridge, "results": results}, indent=1))


if __name__ == "__main__":
    main()
