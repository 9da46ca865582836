"""Where the trained LO hearts miss their FE beats, over the anatomy campaign's dataset; prints one JSON object.

    python scripts/congruency_diagnosis.py [--dataset lvenv/data/anatomy] [--limit N] [--out out/diagnosis]

For every accepted anatomy of the campaign (`optim.campaign`, no FE run): its trained maps on its
own three training beats, C split into the upstroke, ejection, relaxation and filling windows
and into timing (the share a pure time shift of the LO beat removes) and amplitude
(`optim.diagnosis`); then the medians over anatomies. ``--out`` also gets ``diagnosis.md``, the
tables of the results page (`lvenv report`).
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from lvenv.params import LOParams  # noqa: E402
from optim import campaign, diagnosis  # noqa: E402


def markdown(summary: dict, results: dict, command: str) -> str:
    """The results page's tables: the medians, then C and its split per anatomy (%)."""
    windows = diagnosis.WINDOWS
    lines = [f"Made by `{command}` on {datetime.date.today().isoformat()}: every accepted anatomy's trained single-cell maps on its own "
             "three FE training beats (`optim.diagnosis`; no FE run). C² is split exactly into the windows the FE beat's valve events "
             "bound; the timing share is the part of C² that the best pure time shift of the LO beat removes.", "",
             f"Median over {summary['anatomies']} anatomies: C {100 * summary['C_median']:.2f} %; "
             + ", ".join(f"{w} {100 * summary['share_median'][w]:.0f} %" for w in windows)
             + f" of C²; best shift {summary['shift_ms_median']:.1f} ms, removing {100 * summary['timing_share_median']:.1f} % of C².", "",
             "| anatomy | C (%) | " + " | ".join(f"{w} (% of C²)" for w in windows) + " |", "|---" * (len(windows) + 2) + "|"]
    lines += [f"| {aid} | {100 * r['C']:.2f} | " + " | ".join(f"{100 * r['share'][w]:.0f}" for w in windows) + " |" for aid, r in results.items()]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=pathlib.Path, default=campaign.DATASET)
    parser.add_argument("--limit", type=int, default=None, help="first N accepted anatomies only")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/diagnosis"), help="folder of diagnosis.md")
    args = parser.parse_args()
    rows = [r for r in campaign.read_index(args.dataset) if r["status"] == "accepted"][: args.limit]
    results = {}
    for row in rows:
        lo = LOParams(**{name: row[name] for name in campaign.TRAINED})
        results[row["id"]] = diagnosis.diagnose(campaign.oracle_data(args.dataset, row["id"]), lo)
    summary = diagnosis.summary(list(results.values())) if results else None
    if summary is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "diagnosis.md").write_text(markdown(summary, results, "python " + " ".join(sys.argv)))
    print(json.dumps({"summary": summary, "anatomies": results}, indent=1))


if __name__ == "__main__":
    main()
