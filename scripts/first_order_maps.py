"""Would maps that follow the cell to first order carry over to the unseen scenarios (issue 30)?
JSON out, and a table in ``--out``/first_order_maps.md.

    python scripts/first_order_maps.py [--hearts normal heart_failure] [--model series3] [--passive] [--ridge 0.01]

Along each scenario's axis (`optim.studies.UNSEEN`, its position `optim.studies._position`) the
maps are the trained ones changed in proportion to the position: m(s) = m0 exp(x s / s_i) for
μ1, μ2, γ (and with ``--passive`` α, β, a, b, c), and delay(s) = delay0 + `DELAY_UNIT` x s / s_i,
where s_i is the position of the axis' interior point (`optim.studies.INTERIOR`). At s = 0 (the
training beats) the maps are the trained ones, so the training C does not change. x is fitted
on the interior point's FE beat alone, by least squares from x = 0 on the congruency residuals
(`optim.congruency.residuals`) plus ``--ridge`` × ‖x‖² (a ridge on the maps' relative change),
with the maps at the interior point and at the scenario's end inside their boxes
(`optim.congruency.ACTIVE_BOUNDS`, `optim.congruency.passive_bounds`). The maps are then carried
to the scenario's end, which the fit never sees: C and the largest pointwise pressure error
there (`optim.studies.generalisation`'s measures) against the frozen maps'. It reads the shipped
FE beats (`fe_oracle.run`'s cache) and runs no FE; about 2 min per heart with the nine maps.
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
from optim.studies import INTERIOR, UNSEEN, _errors, _position, scenario  # noqa: E402

#: LO steps per beat, as `optim.studies` runs its scenarios.
STEPS_PER_BEAT = 1000
#: The delay's change (s) per unit of x at the interior point.
DELAY_UNIT = 0.05


class Carry:
    """The first-order maps of one heart: m0 the trained maps of ``names``, their boxes."""

    def __init__(self, heart: Heart, names: tuple[str, ...]):
        self.heart, self.names = heart, names
        box = {**ACTIVE_BOUNDS, **passive_bounds(heart.lo)}
        self.m0 = np.array([float(getattr(heart.lo, n)) for n in names])
        self.log = np.array([n != "delay" for n in names])
        self.lower, self.upper = (np.array([box[n][i] for n in names]) for i in (0, 1))

    def maps(self, x: np.ndarray, f: float) -> np.ndarray:
        """The maps at f times the interior point's position."""
        return np.where(self.log, self.m0 * np.exp(x * f), self.m0 + DELAY_UNIT * x * f)

    def x_box(self, f: float) -> tuple[np.ndarray, np.ndarray]:
        """The x whose maps at f times the interior position lie inside the boxes."""
        ends = [np.where(self.log, np.log(np.where(self.log, b, 1.0) / self.m0), (b - self.m0) / DELAY_UNIT) / f for b in (self.lower, self.upper)]
        return np.minimum(*ends), np.maximum(*ends)

    def heart_at(self, change: dict[str, float], x: np.ndarray, f: float) -> Heart:
        """The heart in the scenario ``change`` with the maps at f times the interior position."""
        lo = dataclasses.replace(self.heart.lo, **dict(zip(self.names, map(float, self.maps(x, f)))))
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


def study(label: str, heart: Heart, names: tuple[str, ...], ridge: float, scenarios: dict[str, dict[str, float]] = UNSEEN,
          backend: str = "dolfinx", **oracle_options) -> list[dict]:
    """One row per scenario of ``scenarios`` (module docstring), against ``backend``'s beats
    (``oracle_options`` go to `fe_oracle.run`); ``label`` names the heart in the progress lines."""
    carry, zero, rows = Carry(heart, names), np.zeros(len(names)), []
    for end, change in scenarios.items():
        inner, inner_change = INTERIOR[end]
        w = _position(heart, change) / _position(heart, inner_change)
        oracles = {}
        for key, ch in ((inner, inner_change), (end, change)):
            target = scenario(heart, ch)
            oracles[key] = fe_oracle.run(target.geometry, target.circulation, backend, cell=target.cell, progress=False, **oracle_options).traces
        samples = 2 * len(oracles[inner]["t"])

        def residual(x: np.ndarray) -> np.ndarray:
            h = carry.heart_at(inner_change, x, 1.0)
            if not passes_validation(h):
                return np.concatenate([np.ones(samples), np.sqrt(ridge) * x])
            status, t, v, p, _ = one_beat([h], STEPS_PER_BEAT)
            r = residuals(oracles[inner], t[0], v, p)[0]
            return np.concatenate([r if status[0] == "ok" and np.all(np.isfinite(r)) else np.ones(samples), np.sqrt(ridge) * x])

        (lo1, hi1), (lo_w, hi_w) = carry.x_box(1.0), carry.x_box(w)
        lower, upper = np.minimum(np.maximum(lo1, lo_w), -1e-9), np.maximum(np.minimum(hi1, hi_w), 1e-9)
        fit = least_squares(residual, zero, bounds=(lower, upper), diff_step=1e-4, max_nfev=60 * len(names))
        frozen_i, fitted_i = measure(oracles[inner], [carry.heart_at(inner_change, zero, 1.0), carry.heart_at(inner_change, fit.x, 1.0)])
        frozen_e, carried_e = measure(oracles[end], [carry.heart_at(change, zero, w), carry.heart_at(change, fit.x, w)])
        rows.append({"scenario": end, "interior": inner, "w": w, "x": dict(zip(names, fit.x.round(4).tolist())), "evaluations": int(fit.nfev),
                     "interior_C_frozen": frozen_i["C"], "interior_C_fitted": fitted_i["C"],
                     "end_C_frozen": frozen_e["C"], "end_C_carried": carried_e["C"],
                     "end_P_error_frozen": frozen_e["max_rel_error_P"], "end_P_error_carried": carried_e["max_rel_error_P"]})
        print(f"{label} {end}: C {frozen_e['C']:.4f} -> {carried_e['C']:.4f}", file=sys.stderr, flush=True)
    return rows


def table(results: dict[str, list[dict]], command: str) -> str:
    """The results as a markdown table, with the command that made it."""
    lines = [f"Made by `{command}`.", "", "| heart | scenario | interior C frozen → fitted | end C frozen → carried | end pressure error frozen → carried |",
             "|---|---|---|---|---|"]
    for name, rows in results.items():
        for r in rows:
            lines.append(f"| {name} | {r['scenario']} ({r['interior']} fitted) | {100 * r['interior_C_frozen']:.1f} → {100 * r['interior_C_fitted']:.1f} % "
                         f"| {100 * r['end_C_frozen']:.1f} → {100 * r['end_C_carried']:.1f} % "
                         f"| {100 * r['end_P_error_frozen']:.1f} → {100 * r['end_P_error_carried']:.1f} % |")
        worst = max(rows, key=lambda r: r["end_C_carried"])
        lines.append(f"| {name} | **worst end** | | {100 * max(r['end_C_frozen'] for r in rows):.1f} → {100 * worst['end_C_carried']:.1f} % ({worst['scenario']}) | |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hearts", nargs="+", default=["normal", "heart_failure"], choices=["normal", "heart_failure"])
    parser.add_argument("--model", default="series3", choices=sorted(presets.LO_MODELS), help="the LO heart model (default series3)")
    parser.add_argument("--passive", action="store_true", help="carry the passive maps too (nine maps)")
    parser.add_argument("--ridge", type=float, default=0.01, help="weight of ‖x‖² beside C² (default 0.01)")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/diagnosis"))
    args = parser.parse_args()
    if not args.ridge >= 0:
        parser.error(f"--ridge = {args.ridge} must be >= 0")
    names = (*MAP_NAMES, *PASSIVE_NAMES) if args.passive else MAP_NAMES
    results = {name: study(name, getattr(presets, name)(model=args.model), names, args.ridge) for name in args.hearts}
    command = "python scripts/first_order_maps.py " + " ".join(sys.argv[1:])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "first_order_maps.md").write_text(table(results, command))
    print(json.dumps({"command": command, "names": names, "ridge": args.ridge, "results": results}, indent=1))


if __name__ == "__main__":
    main()
