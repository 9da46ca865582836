"""Command line: ``lvenv presets | simulate | reach`` (``lvenv --help``)."""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from lvenv import presets
from lvenv.events import METRIC_NAMES
from lvenv.geometry import cavity_volume
from lvenv.identification import OBSERVATION_TARGETS
from lvenv.simulation import simulate
from lvenv.units import METRIC_DISPLAY

PRESETS = {"normal": presets.normal, "heart_failure": presets.heart_failure}


def _table(rows: list[tuple[str, dict[str, float], str]], keys=METRIC_NAMES) -> str:
    head = ["case"] + [f"{METRIC_DISPLAY[k][0]} ({METRIC_DISPLAY[k][1]})" for k in keys] + ["status"]
    body = [[name] + [f"{METRIC_DISPLAY[k][2](m[k]):.1f}" if k != "CO" else f"{METRIC_DISPLAY[k][2](m[k]):.2f}" for k in keys] + [status] for name, m, status in rows]
    widths = [max(len(r[i]) for r in [head] + body) for i in range(len(head))]
    fmt = lambda r: "  ".join(c.rjust(w) for c, w in zip(r, widths))
    return "\n".join([fmt(head), fmt(["-" * w for w in widths])] + [fmt(r) for r in body])


def _member_rows(result, names):
    return [(name, {k: float(v[i]) for k, v in result.metrics.items()}, str(result.status[i])) for i, name in enumerate(names)]


def cmd_presets(args) -> int:
    """Simulate N and HF to steady state (closed loop) and under the training protocol."""
    t0 = time.perf_counter()
    steady_names, steady = list(PRESETS), [f() for f in PRESETS.values()]
    res = simulate(steady, max_beats=args.max_beats)
    train_names, train = [], []
    for name, heart in zip(steady_names, steady):
        for k in sorted(presets.TRAINING_CONDITIONS):
            train_names.append(f"{name} ({k})")
            train.append(presets.training_condition(k, heart))
    res_train = simulate(train, beats=1)
    v0 = {n: cavity_volume(h.geometry) for n, h in zip(steady_names, steady)}
    print("Steady state, closed loop, 60 bpm (beats to steady state: " + ", ".join(f"{n} {b}" for n, b in zip(steady_names, res.beats)) + ")")
    print(_table(_member_rows(res, steady_names)))
    print("\nTraining protocol (Table 2, one beat from passive equilibrium, P_c(0) = 10 kPa)")
    print(_table(_member_rows(res_train, train_names)))
    print("\nUnloaded cavity volume V0: " + ", ".join(f"{n} {v:.2f} ml" for n, v in v0.items()))
    print(f"wall time {time.perf_counter() - t0:.1f} s")
    return 0 if all(s in ("ok",) for s in list(res.status) + list(res_train.status)) else 1


def _parse_settings(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        if not value:
            raise SystemExit(f"--set expects NAME=VALUE, got {item!r}")
        out[name] = float(value)
    return out


def cmd_simulate(args) -> int:
    heart = PRESETS[args.preset]()
    if args.condition:
        heart = presets.training_condition(args.condition, heart)
    heart = heart.replace(**_parse_settings(args.set))
    res = simulate(heart, beats=args.beats, max_beats=args.max_beats)
    if args.json:
        print(json.dumps({"metrics": res.metrics, "status": res.status, "converged": bool(res.converged), "beats": int(res.beats)}, indent=2))
    else:
        print(_table([(args.preset, res.metrics, res.status)]))
    return 0 if res.status in ("ok", "not_converged") else 1


def cmd_reach(args) -> int:
    from lvenv import reachability

    heart = PRESETS[args.preset]()
    t0 = time.perf_counter()
    r = reachability.search(heart, seed=args.seed)
    print(f"Reachability search on {args.preset} ({r.evaluations} steady-state simulations, {time.perf_counter() - t0:.1f} s)")
    for name, value in r.params.items():
        print(f"  {name:5s} = {value:.4g}")
    for key, target in OBSERVATION_TARGETS.items():
        label, unit, conv = METRIC_DISPLAY[key]
        print(f"  {label:9s} target {conv(target):7.1f} {unit:4s} reached {conv(r.metrics[key]):7.1f}  ({100 * r.relative_error[key]:+.2f} %)")
    return 0 if max(abs(e) for e in r.relative_error.values()) < 0.01 else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lvenv", description="Low-order LV heart (Di Achille et al. 2020) in JAX.")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("presets", help="simulate the built-in N and HF hearts and print their metrics")
    p.add_argument("--max-beats", type=int, default=200)
    p.set_defaults(func=cmd_presets)
    p = sub.add_parser("simulate", help="simulate one preset with parameters changed by --set NAME=VALUE")
    p.add_argument("--preset", choices=sorted(PRESETS), default="normal")
    p.add_argument("--condition", type=int, choices=sorted(presets.TRAINING_CONDITIONS), help="apply a Table 2 training condition")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--beats", type=int, default=None, help="fixed number of beats (default: to steady state)")
    p.add_argument("--max-beats", type=int, default=200)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_simulate)
    p = sub.add_parser("reach", help="search (tau2, Sa, R2, R3, C, Cat) for human resting values (EF 60 %, ET 300 ms, IVRT 80 ms, 120/75 mmHg)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="normal")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_reach)
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except ValueError as err:
        print(f"lvenv: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
