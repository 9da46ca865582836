"""Cost of the candidate low-order hearts against the single cell, in the same run (issue 30's cost criterion; JSON out).

    python scripts/bench_candidates.py [--batches 256 1024] [--repeats 3]

Per batch size, beats per second (median of ``--repeats`` timed runs after one compile run, 2 beats
from the training-protocol state, 1000 ROS2 steps per beat, no traces) of the single-cell heart
(`lvenv.simulate`) and of the multi-element candidates of `scripts/candidate_study.py`
(`lvenv.simulate` of the same hearts carrying the arrangement, ``Heart.elements``: 5 cells in
series or in parallel, or 3 in series, with the N wall's onsets), and
``ratio_vs_single``: the single cell's beats/s over the candidate's (how many times it costs).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import lvenv  # noqa: E402
from lvenv.params import Arrangement  # noqa: E402
from scripts.bench_lo import cohort, timed  # noqa: E402

BEATS, STEPS = 2, 1000
#: The N wall's activation times at the 5 cells' quantiles less their median (s), at h = 6 mm
#: (`fe_oracle.activation.activation_quantiles`; the 3 cells' quantiles are the 1st, 3rd and 5th);
#: the cost does not depend on their values.
ONSETS = (-0.0198, -0.0088, 0.0, 0.0100, 0.0295)


def _median_rate(run, n: int, repeats: int) -> float:
    return BEATS * n / float(np.median(timed(run, repeats)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", nargs="+", type=int, default=[256, 1024])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    candidates = {"series-onsets": Arrangement("series", len(ONSETS), (1.0, 1.0), onsets=ONSETS),
                  "parallel-onsets": Arrangement("parallel", len(ONSETS), onsets=ONSETS),
                  "series3-onsets": Arrangement("series", 3, (1.0, 1.0), onsets=ONSETS[::2])}
    out = {"beats": BEATS, "steps_per_beat": STEPS, "repeats": args.repeats, "batches": {}}
    for n in args.batches:
        batch = cohort(n)
        single = _median_rate(lambda: lvenv.simulate(batch, beats=BEATS, traces=False, steps_per_beat=STEPS), n, args.repeats)
        row = {"single_beats_per_s": single}
        for name, arr in candidates.items():
            arranged = batch.replace(elements=arr)
            rate = _median_rate(lambda: lvenv.simulate(arranged, beats=BEATS, traces=False, steps_per_beat=STEPS), n, args.repeats)
            row[name] = {"beats_per_s": rate, "ratio_vs_single": single / rate}
        out["batches"][str(n)] = row
        print(f"# batch {n}: single {single:,.0f} beats/s; " + "; ".join(f"{k} x{v['ratio_vs_single']:.1f}" for k, v in row.items() if k != "single_beats_per_s"),
              file=sys.stderr, flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
