"""Write a synthetic cohort of echo reports (CSV) with known ground truths, for `lvenv cohort`.

Each patient: heart rate uniform in [50, 100] bpm, (τ2, Sa, R2, R3, C, Cat) uniform in the unit
cube of the identification bounds (log-uniform on log axes), on the base heart
(`presets.normal()`). Its closed-loop steady state at 1000 steps per beat (finer than the fit's
500) gives the report, rounded as reports are (EF to 1 %, times to 1 ms, pressures to 1 mmHg);
the cuff pressures are those that `optim.cohort.cuff_targets` maps back to the central diastolic
and mean pressure. A draw is kept when its beat is `ok`, EF is in [0.2, 0.8] and every
plausibility band of the env holds (`lvenv.plausibility`: mean aortic pressure 80–120 mmHg,
mean atrial pressure and EDP 4–25 mmHg), so that an exact fit exists; the acceptance rate is
printed. The truths are carried in `true_<parameter column>` columns (carried through by the fit).

`--bad-fraction` corrupts that fraction of the rows in turn in one of `BAD_KINDS` ways (a missing
value, text for a number, EF above 100 %, a negative duration, DBP above SBP, a repeated id,
a heart rate outside 20–240 bpm, a row with too few fields); `lvenv cohort` must report
each with its line and fit the rest.

    python scripts/make_cohort.py --patients 1000 --out out/cohort/reports.csv
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

from lvenv import presets
from lvenv.identification import DEFAULT_ACTION_PARAMS
from optim.cohort import REQUIRED, cuff_from_central, parameter_column
from optim.fit import draw_truths

BAD_KINDS = ("missing", "text", "ef_over_100", "negative_duration", "dbp_above_sbp", "repeated_id", "heart_rate", "short_row")


def draw(n: int, seed: int, batch: int = 256) -> tuple[list[dict[str, object]], float]:
    """``n`` report rows and the acceptance rate of the draws (module docstring; the truths are
    :func:`optim.fit.draw_truths`')."""
    truths = draw_truths(n, np.random.default_rng(seed), presets.normal(), ef=(0.2, 0.8), heart_rate=(50.0, 100.0), batch=batch,
                         simulation={"steps_per_beat": 1000, "max_beats": 200})
    m = truths.metrics
    rows: list[dict[str, object]] = []
    for i, (x, hr) in enumerate(zip(truths.parameters, truths.heart_rate)):
        sbp, dbp = cuff_from_central(float(m["P_ao_dia"][i]), float(m["P_ao_mean"][i]))
        row: dict[str, object] = {
            "id": f"P{i:05d}", "EF_pct": round(100 * float(m["EF"][i])), "ET_ms": round(1000 * float(m["ET"][i])),
            "IVRT_ms": round(1000 * float(m["IVRT"][i])), "SBP_mmHg": round(sbp), "DBP_mmHg": round(dbp),
            "HR_bpm": round(float(hr), 1),
        }
        row.update({f"true_{parameter_column(name)}": f"{float(v):.6g}" for name, v in zip(DEFAULT_ACTION_PARAMS, x)})
        rows.append(row)
    return rows, n / truths.tried


def corrupt(rows: list[dict[str, object]], fraction: float, seed: int) -> list[tuple[int, str]]:
    """Corrupt ``fraction`` of the rows in place, cycling through :data:`BAD_KINDS`; returns
    (row index, kind) of each corrupted row."""
    rng = np.random.default_rng(seed + 1)
    picked = sorted(rng.choice(np.arange(1, len(rows)), size=int(round(fraction * len(rows))), replace=False).tolist())
    done = []
    for j, i in enumerate(picked):
        kind = BAD_KINDS[j % len(BAD_KINDS)]
        row = rows[i]
        if kind == "missing":
            row["ET_ms"] = ""
        elif kind == "text":
            row["SBP_mmHg"] = "n/a"
        elif kind == "ef_over_100":
            row["EF_pct"] = 160
        elif kind == "negative_duration":
            row["IVRT_ms"] = -abs(int(row["IVRT_ms"]))
        elif kind == "dbp_above_sbp":
            row["DBP_mmHg"], row["SBP_mmHg"] = row["SBP_mmHg"], row["DBP_mmHg"]
        elif kind == "repeated_id":
            row["id"] = rows[i - 1]["id"]
        elif kind == "heart_rate":
            row["HR_bpm"] = 400
        elif kind == "short_row":
            row["__short__"] = True
        done.append((i, kind))
    return done


def write(rows: list[dict[str, object]], path: Path) -> None:
    columns = [c for c in rows[0] if c != "__short__"]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for row in rows:
            values = [row.get(c, "") for c in columns]
            writer.writerow(values[: len(REQUIRED) - 2] if row.get("__short__") else values)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--patients", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bad-fraction", type=float, default=0.0, help="fraction of rows to corrupt (0–0.5)")
    parser.add_argument("--out", type=Path, default=Path("out/cohort/reports.csv"))
    args = parser.parse_args(argv)
    if args.patients < 1 or not 0.0 <= args.bad_fraction <= 0.5:
        parser.error("--patients must be ≥ 1 and --bad-fraction in [0, 0.5]")
    start = time.perf_counter()
    rows, acceptance = draw(args.patients, args.seed)
    bad = corrupt(rows, args.bad_fraction, args.seed) if args.bad_fraction > 0 else []
    write(rows, args.out)
    json.dump({"out": str(args.out), "patients": len(rows), "acceptance": acceptance,
               "bad_rows": [{"line": i + 2, "kind": k} for i, k in bad], "wall_time_s": time.perf_counter() - start},
              sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
