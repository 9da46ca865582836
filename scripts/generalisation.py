"""Generalisation study (the paper's Fig. 7): trained LO heart against the 3-D oracle in unseen scenarios.

    python scripts/generalisation.py [--hearts normal heart_failure] [--out out/generalisation]

Maps frozen at the trained presets; one parameter at a time leaves its training value
(`optim.studies.UNSEEN`), one beat under condition ②. Writes `generalisation.csv`,
`generalisation.md` and `generalisation.png` / `.pdf` (oracle solid, LO dashed; `lvenv.plots`) and
prints the rows as JSON.
"""

from __future__ import annotations

import argparse
import csv
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from lvenv import presets  # noqa: E402
from lvenv.plots import generalisation_figure  # noqa: E402
from optim.studies import UNSEEN, generalisation  # noqa: E402

FIELDS = ("heart", "scenario", "C", "max_rel_error_V", "max_rel_error_P", "lo_status", "oracle_key")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hearts", nargs="+", choices=("normal", "heart_failure"), default=["normal", "heart_failure"])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/generalisation"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.hearts:
        rows += [{"heart": name, **r} for r in generalisation(getattr(presets, name)(), progress=False)]
    with open(args.out / "generalisation.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    lines = ["| heart | scenario | C (%) | max error V (%) | max error P (%) |", "|---|---|---|---|---|"]
    lines += [f"| {r['heart']} | {r['scenario']} | {100 * r['C']:.2f} | {100 * r['max_rel_error_V']:.1f} | {100 * r['max_rel_error_P']:.1f} |" for r in rows]
    (args.out / "generalisation.md").write_text("\n".join(lines) + "\n")
    for suffix in (".png", ".pdf"):
        generalisation_figure(rows, args.out / f"generalisation{suffix}", columns=len(UNSEEN))
    print(json.dumps([{k: r[k] for k in FIELDS} for r in rows], indent=2))


if __name__ == "__main__":
    main()
