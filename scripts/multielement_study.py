"""Multi-element study (the paper's Table 4): single-element LO hearts trained to 256-element models.

    python scripts/multielement_study.py [--arrangements parallel series] [--budget 480] [--out out/multielement]

Four sweeps of ten values (`optim.studies.SWEEPS`) × {parallel, series}; each cell is
`optim.congruency.train(geometry, backend="multielement", ...)` at that cell unit. Writes
`multielement.csv` and `multielement.md` (C in %, one row per sweep value) and prints JSON.
"""

from __future__ import annotations

import argparse
import csv
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from optim.studies import SWEEPS, multielement_table  # noqa: E402

FIELDS = ("arrangement", "sweep", "value", "1", "2", "3", "C", "delay", "C_without_delay")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arrangements", nargs="+", choices=("parallel", "series"), default=["parallel", "series"])
    parser.add_argument("--budget", type=int, default=480)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/multielement"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = multielement_table(arrangements=args.arrangements, budget=args.budget, progress=False)
    with open(args.out / "multielement.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    lines = []
    for sweep in SWEEPS:
        head = f"| {sweep} | " + " | ".join(f"C {a} (%)" for a in args.arrangements) + " |"
        lines += [head, "|" + "---|" * (1 + len(args.arrangements))]
        for value in SWEEPS[sweep]:
            cells = [next(f"{100 * r['C']:.2f}" for r in rows if r["sweep"] == sweep and r["value"] == float(value) and r["arrangement"] == a)
                     for a in args.arrangements]
            lines.append(f"| {value:.3g} | " + " | ".join(cells) + " |")
        lines.append("")
    (args.out / "multielement.md").write_text("\n".join(lines))
    print(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
