"""Benchmark the vector env: member evaluations to steady state per second, for the integration
schemes side by side in the same run (JSON out).

    python scripts/bench_env.py [--num-envs 256 1024 4096] [--configs fixed adaptive adaptive+anderson]

A configuration is an integration scheme (``fixed``: ``--steps-per-beat`` equal steps, the old
default; ``adaptive``: step-size control), optionally ``+anderson``: the steady state by
Anderson-accelerated beats (``fixed`` alone is the env before December 2026).

Each member holds a random point of the action box; every timed ``venv.step`` moves every member
to a new point drawn around its own (normal steps of ``--spread`` in the unit box, as a
population optimiser's), so each evaluation is warm-started from a nearby steady state, the
optimisers' case. After one untimed step (compilation), ``--repeats`` steps are timed per
configuration; configurations take turns so machine noise hits all. Per num_envs and
configuration: member evaluations per second, beats per evaluation and ROS2 steps per beat
(medians), and the ratio to the first configuration.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import jax  # noqa: E402
import gymnasium  # noqa: E402

import lvenv  # noqa: E402,F401  (registers the environments)


def make(num_envs: int, config: str, steps_per_beat: int):
    scheme, _, acceleration = config.partition("+")
    return gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=num_envs, max_episode_steps=None, tolerance=0.0, autoreset_mode="Disabled",
                              steps_per_beat=steps_per_beat, scheme=scheme, acceleration=acceleration or "none")


def measure(num_envs: int, schemes: list[str], repeats: int, steps_per_beat: int, spread: float, seed: int = 0) -> list[dict]:
    envs = {s: make(num_envs, s, steps_per_beat) for s in schemes}
    space = next(iter(envs.values())).unwrapped.config.actions.space
    rng = np.random.default_rng(seed)
    center = rng.uniform(0.25, 0.75, (num_envs, len(space.names)))
    draws = [space.from_unit(np.clip(center + spread * rng.standard_normal(center.shape), 0.0, 1.0)) for _ in range(repeats + 1)]
    times = {s: [] for s in schemes}
    beats = {s: [] for s in schemes}
    steps = {s: [] for s in schemes}
    for s, venv in envs.items():
        venv.reset(seed=seed)
        venv.step(draws[0])
    for actions in draws[1:]:
        for s, venv in envs.items():
            t0 = time.perf_counter()
            _, _, _, _, info = venv.step(actions)
            times[s].append(time.perf_counter() - t0)
            beats[s].append(np.asarray(info["beats"]))
            steps[s].append(np.asarray(info["steps"]) / np.maximum(np.asarray(info["beats"]), 1))
    out = []
    for s in schemes:
        t = float(np.median(times[s]))
        out.append({
            "num_envs": num_envs, "config": s, "member_evaluations_per_s": num_envs / t,
            "beats_per_evaluation_median": float(np.median(np.concatenate(beats[s]))),
            "steps_per_beat_median": float(np.median(np.concatenate(steps[s]))),
            "beats_per_s": float(np.sum(np.concatenate(beats[s]))) / float(np.sum(times[s])),
            "times_s": times[s],
        })
    for r in out:
        r["speedup_vs_" + schemes[0]] = r["member_evaluations_per_s"] / out[0]["member_evaluations_per_s"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--num-envs", type=int, nargs="+", default=[256, 1024, 4096])
    parser.add_argument("--configs", dest="schemes", nargs="+", default=["fixed", "adaptive", "adaptive+anderson"],
                        help="SCHEME or SCHEME+anderson; the first is the baseline")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps-per-beat", type=int, default=1000, help="of the fixed scheme (the env's default)")
    parser.add_argument("--spread", type=float, default=0.05, help="std of each step's move in the unit box")
    args = parser.parse_args()
    results = []
    for n in args.num_envs:
        for r in measure(n, args.schemes, args.repeats, args.steps_per_beat, args.spread):
            results.append(r)
            print(f"# num_envs {n} {r['config']}: {r['member_evaluations_per_s']:,.0f} evaluations/s, {r['beats_per_evaluation_median']:.0f} beats "
                  f"x {r['steps_per_beat_median']:.0f} steps, x{r['speedup_vs_' + args.schemes[0]]:.2f}", file=sys.stderr, flush=True)
    print(json.dumps({"device": str(jax.devices()[0].device_kind), "n_devices": len(jax.devices()), "steps_per_beat": args.steps_per_beat,
                      "spread": args.spread, "results": results}, indent=2))


if __name__ == "__main__":
    main()
