"""How much each added measurement narrows the posterior (issue 11 item 6): on synthetic patients.

    python scripts/narrowing.py [--truths 3] [--seed 0] [--sets NAME ...] [--volume-sd ML] [--walkers 64] [--steps 200] [--chains 64] [--chain-steps 1200] [--out out/identify/narrowing.json]
    python scripts/narrowing.py --pool A.json B.json ...

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
`Patient.with_volume_trace`), and with both the trace and EDP; ``--sets`` runs only the named
ones after the four targets (``--sets trace`` for the issue's criterion; a seed's truths are the
same whichever sets run). ``--pool`` prints the
table over the truths of several earlier runs' JSON (different ``--seed``, same settings)
without sampling. Measurement errors are
`optim.identify.NOISE` (volumes 5 % of each measured volume, frames included; pressures 5 mmHg);
``--volume-sd 5`` gives every volume an error of 5 ml instead.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.metrics import FRAME_NAMES
from lvenv.patients import Patient, builtin
from lvenv.archive import load_records, save_records
from optim.fit import draw_truths
from optim.identify import NOISE, VOLUME_NAMES, posterior

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # the shared scripts/ module below
from scripts.posterior_options import add_sampler_options, sampler_options  # noqa: E402

BASE = ("EF", "ET", "IVRT", "P_ao_pulse")
SETS = {
    "4 targets": BASE,
    "+ EDV, ESV": (*BASE, "EDV", "ESV"),
    "+ EDP": (*BASE, "EDP"),
    "+ volume trace": (*BASE, *FRAME_NAMES),
    "+ trace, EDP": (*BASE, *FRAME_NAMES, "EDP"),
}
#: ``--sets`` names of the sets after the four targets.
SET_OPTIONS = {"volumes": "+ EDV, ESV", "edp": "+ EDP", "trace": "+ volume trace", "trace-edp": "+ trace, EDP"}


def _by_truth(runs: list[dict]) -> tuple[dict, list]:
    """Each run's widths by (truth, set), and the truths in order."""
    return {(r["truth"], r["set"]): r["widths"] for r in runs}, sorted({r["truth"] for r in runs})


def print_table(runs: list[dict]) -> dict[str, dict[str, float]]:
    """Print, per measurement set and parameter, the median width over the truths that ran the
    set and the narrowing: the four targets' median width over the same truths divided by it.
    Returns the medians."""
    width, truths = _by_truth(runs)
    median = {}
    print(f"\nmedian 90 % interval width over {len(truths)} truths (fraction of the bound; × = narrowing: the four targets' median "
          "width over the same truths / this one; in brackets the number of truths where a set ran on fewer)")
    print("| measurements | " + " | ".join(DEFAULT_ACTION_PARAMS) + " |")
    print("|---|" + "---|" * len(DEFAULT_ACTION_PARAMS))
    for name in SETS:
        ran = [t for t in truths if (t, name) in width and (t, "4 targets") in width]
        if not ran:
            continue
        median[name] = {n: float(np.median([width[t, name][n] for t in ran])) for n in DEFAULT_ACTION_PARAMS}
        base = {n: float(np.median([width[t, "4 targets"][n] for t in ran])) for n in DEFAULT_ACTION_PARAMS}
        label = name if len(ran) == len(truths) else f"{name} ({len(ran)})"
        print(f"| {label} | " + " | ".join(f"{median[name][n]:.3f} (×{base[n] / median[name][n]:.1f})" for n in DEFAULT_ACTION_PARAMS) + " |")
    return median


#: Options in which pooled runs may differ.
POOL_FREE = ("seed", "sets", "truths", "out", "pool")


def pool(paths: list[str]) -> None:
    """Print the table over the truths of earlier runs' JSON files, and each truth's narrowing
    of every parameter by each set (their median is not the ratio of the medians). Only the
    options in :data:`POOL_FREE` may differ between the runs; the sampler's and the volume
    error must be the same, or the run that differs is refused."""
    runs, first = [], None
    for k, path in enumerate(paths):
        record = json.loads(pathlib.Path(path).read_text())
        options = {key: v for key, v in record["options"].items() if key not in POOL_FREE}
        first = options if first is None else first
        if options != first:
            differ = sorted(key for key in first.keys() | options.keys() if first.get(key) != options.get(key))
            raise SystemExit(f"--pool: {path} was run with other settings ({', '.join(f'{key} = {options.get(key)!r} against {first.get(key)!r}' for key in differ)})")
        runs += [{**r, "truth": (k, r["truth"])} for r in record["runs"]]
    width, truths = _by_truth(runs)
    print_table(runs)
    print("\nper-truth narrowing against the four targets (median over the truths that ran the set)")
    for name in SETS:
        ratios = {n: [width[t, "4 targets"][n] / width[t, name][n] for t in truths if (t, name) in width] for n in DEFAULT_ACTION_PARAMS}
        if name == "4 targets" or not ratios[DEFAULT_ACTION_PARAMS[0]]:
            continue
        print(f"{name}: " + "; ".join(f"{n} median ×{np.median(v):.2f} ({', '.join(f'{x:.1f}' for x in v)})" for n, v in ratios.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truths", type=int, default=3)
    add_sampler_options(ap)
    ap.add_argument("--volume-sd", type=float, default=None, metavar="ML",
                    help="measurement error of every volume and frame, ml (default: 5 %% of the volume, identify.NOISE)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sets", nargs="+", choices=list(SET_OPTIONS), default=list(SET_OPTIONS),
                    help="measurement sets after the four targets, which always run (default: all)")
    ap.add_argument("--out", default="out/identify/narrowing.json")
    ap.add_argument("--pool", nargs="+", metavar="JSON", help="print the table over earlier runs' JSON output instead of sampling")
    a = ap.parse_args()
    if a.pool:
        pool(a.pool)
        return
    sets = {"4 targets": BASE, **{SET_OPTIONS[k]: SETS[SET_OPTIONS[k]] for k in a.sets}}
    noise = NOISE if a.volume_sd is None else {**NOISE, **dict.fromkeys(VOLUME_NAMES, a.volume_sd)}
    base = builtin("normal")
    metrics = tuple(dict.fromkeys(m for names in sets.values() for m in names))
    drawn = draw_truths(a.truths, np.random.default_rng(a.seed), base.heart)
    truths, obs = drawn.parameters, drawn.observations(metrics)
    checkpoint = pathlib.Path(a.out + ".ckpt.npz")
    settings = {k: v for k, v in vars(a).items() if k not in ("out", "pool")}
    runs = load_records(checkpoint, settings)
    if runs:
        print(f"resuming after {len(runs)} posteriors from {checkpoint}", flush=True)
    done = {(r["truth"], r["set"]) for r in runs}
    for i, (truth, o) in enumerate(zip(truths, obs)):
        values = dict(zip(metrics, map(float, o)))
        start = dict(zip(DEFAULT_ACTION_PARAMS, map(float, truth)))
        for name, targets in sets.items():
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
    median = print_table(runs)
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"median": median, "runs": runs, "options": vars(a)}, indent=2))
    checkpoint.unlink()
    print(f"JSON: {out}")


if __name__ == "__main__":
    main()
