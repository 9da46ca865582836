"""Where the trained LO hearts miss their FE beats, over the anatomy campaign's dataset; prints one JSON object.

    python scripts/congruency_diagnosis.py [--dataset lvenv/data/anatomy] [--limit N]

For every accepted anatomy of the campaign (`optim.campaign`, no FE run): its trained maps on its
own three training beats, C split into the upstroke, ejection, relaxation and filling windows
and into timing (the share a pure time shift of the LO beat removes) and amplitude
(`optim.diagnosis`); then the medians over anatomies.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from lvenv.params import LOParams  # noqa: E402
from optim import campaign, diagnosis  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=pathlib.Path, default=campaign.DATASET)
    parser.add_argument("--limit", type=int, default=None, help="first N accepted anatomies only")
    args = parser.parse_args()
    rows = [r for r in campaign.read_index(args.dataset) if r["status"] == "accepted"][: args.limit]
    results = {}
    for row in rows:
        lo = LOParams(**{name: row[name] for name in campaign.TRAINED})
        results[row["id"]] = diagnosis.diagnose(campaign.oracle_data(args.dataset, row["id"]), lo)
    print(json.dumps({"summary": diagnosis.summary(list(results.values())) if results else None, "anatomies": results}, indent=1))


if __name__ == "__main__":
    main()
