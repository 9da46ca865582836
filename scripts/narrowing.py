"""How much each added measurement narrows the posterior (issue 11 item 6): on synthetic patients.

    python scripts/narrowing.py [--truths 3] [--volume-sd ML] [--walkers 64] [--steps 200] [--chains 64] [--chain-steps 1200] [--out out/identify/narrowing.json]

Draws ``--truths`` random parameter sets inside the identification bounds whose hearts meet every
plausibility band (``optim.fit``'s synthetic truths), takes their noise-free steady-state metrics
as targets, and samples the posterior (`optim.identify.posterior`, started at the truth) for each
measurement set below. Per set and parameter it prints the median over the truths of the 90 %
interval width, as a fraction of the parameter's bound (log scale on log axes), and the ratio of
the base set's width to it (×2 = twice as narrow). JSON with every width goes to ``--out``.
About 2–3 minutes per posterior on 2 cores; each finished one is saved to ``--out`` with
``.ckpt.npz`` appended, and a rerun with the same settings resumes from it.

Measurement sets: the built-in patients' four targets (EF, ET, IVRT, pulse pressure), then with
EDV and ESV, with an end-diastolic pressure estimate, with a 20-frame volume trace (cine MRI,
`Patient.with_volume_trace`), and with both the trace and EDP. Measurement errors are
`optim.identify.NOISE` (volumes 5 % of each measured volume, frames included; pressures 5 mmHg);
``--volume-sd 5`` gives every volume an error of 5 ml instead.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.metrics import FRAME_NAMES
from lvenv.patients import Patient, builtin
from lvenv.archive import load_records, save_records
from optim.fit import draw_truths
from optim.identify import NOISE, VOLUME_NAMES, add_sampler_options, posterior, sampler_options

BASE = ("EF", "ET", "IVRT", "P_ao_pulse")
SETS = {
    "4 targets": BASE,
    "+ EDV, ESV": (*BASE, "EDV", "ESV"),
    "+ EDP": (*BASE, "EDP"),
    "+ volume trace": (*BASE, *FRAME_NAMES),
    "+ trace, EDP": (*BASE, *FRAME_NAMES, "EDP"),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truths", type=int, default=3)
    add_sampler_options(ap)
    ap.add_argument("--volume-sd", type=float, default=None, metavar="ML",
                    help="measurement error of every volume and frame, ml (default: 5 %% of the volume, identify.NOISE)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/identify/narrowing.json")
    a = ap.parse_args()
    noise = NOISE if a.volume_sd is None else {**NOISE, **dict.fromkeys(VOLUME_NAMES, a.volume_sd)}
    base = builtin("normal")
    metrics = tuple(dict.fromkeys(m for names in SETS.values() for m in names))
    truths, obs = draw_truths(a.truths, np.random.default_rng(a.seed), base, metrics)
    checkpoint = pathlib.Path(a.out + ".ckpt.npz")
    settings = {k: v for k, v in vars(a).items() if k != "out"}
    runs = load_records(checkpoint, settings)
    if runs:
        print(f"resuming after {len(runs)} posteriors from {checkpoint}", flush=True)
    done = {(r["truth"], r["set"]) for r in runs}
    for i, (truth, o) in enumerate(zip(truths, obs)):
        values = dict(zip(metrics, map(float, o)))
        start = dict(zip(DEFAULT_ACTION_PARAMS, map(float, truth)))
        for name, targets in SETS.items():
            if (i, name) in done:
                continue
            patient = Patient(f"truth {i}", base.heart, {k: values[k] for k in targets})
            t0 = time.perf_counter()
            post = posterior(patient, start=start, noise=noise, seed=a.seed + i, **sampler_options(a))
            runs.append({"truth": i, "set": name, "parameters": start, "widths": post.widths(), "rhat": post.rhat,
                         "acceptance": post.acceptance, "failed": post.failed, "wall_s": time.perf_counter() - t0})
            save_records(checkpoint, runs, settings)
            print(f"truth {i} {name:15s} widths " + " ".join(f"{n} {w:.3f}" for n, w in post.widths().items())
                  + f"  (R-hat ≤ {max(post.rhat.values()):.3f}, {time.perf_counter() - t0:.0f} s)", flush=True)
    widths = {name: [r["widths"] for r in runs if r["set"] == name] for name in SETS}
    median = {name: {n: float(np.median([w[n] for w in ws])) for n in DEFAULT_ACTION_PARAMS} for name, ws in widths.items()}
    first = median["4 targets"]
    print(f"\nmedian 90 % interval width over {a.truths} truths (fraction of the bound; × = narrowing against the four targets)")
    print("| measurements | " + " | ".join(DEFAULT_ACTION_PARAMS) + " |")
    print("|---|" + "---|" * len(DEFAULT_ACTION_PARAMS))
    for name, w in median.items():
        print(f"| {name} | " + " | ".join(f"{w[n]:.3f} (×{first[n] / w[n]:.1f})" for n in DEFAULT_ACTION_PARAMS) + " |")
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"median": median, "runs": runs, "options": vars(a)}, indent=2))
    checkpoint.unlink()
    print(f"JSON: {out}")


if __name__ == "__main__":
    main()
