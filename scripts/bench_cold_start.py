"""Benchmark the cold start of `lvenv fit` with and without JAX's persistent compilation cache,
in the same run (JSON out).

    python scripts/bench_cold_start.py [--repeats 3] [--patient normal]

Each measurement is a new process running `lvenv fit PATIENT --method cma --json`; its
`compile_time_s` (the env's first reset, which compiles its step, and first step: tracing,
compilation or loading from the cache, and the first evaluation) and its whole wall time are recorded. Sides: `cold` (a fresh, empty
cache directory: the first process of a new machine), `warm` (the same directory afterwards) and
`off` (`--no-jit-cache`). Medians over `--repeats` processes; ratios against `off`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np


def one(patient: str, cache: str | None) -> dict[str, float]:
    argv = [sys.executable, "-m", "lvenv.cli"] + (["--no-jit-cache"] if cache is None else [])
    argv += ["fit", patient, "--method", "cma", "--json"]
    env = {**os.environ, "LVENV_JIT_CACHE": cache or "off"}
    start = time.perf_counter()
    done = subprocess.run(argv, env=env, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - start
    return {"compile_time_s": json.loads(done.stdout)["compile_time_s"], "process_wall_s": wall}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--patient", default="normal")
    args = parser.parse_args(argv)
    runs: dict[str, list[dict[str, float]]] = {"cold": [], "warm": [], "off": []}
    for _ in range(args.repeats):
        cache = tempfile.mkdtemp(prefix="lvenv-jit-")
        runs["cold"].append(one(args.patient, cache))
        runs["warm"].append(one(args.patient, cache))
        runs["off"].append(one(args.patient, None))
    medians = {side: {k: float(np.median([r[k] for r in rs])) for k in rs[0]} for side, rs in runs.items()}
    ratios = {side: medians["off"]["compile_time_s"] / medians[side]["compile_time_s"] for side in ("cold", "warm")}
    json.dump({"patient": args.patient, "repeats": args.repeats, "median": medians, "compile_speedup_over_off": ratios, "runs": runs},
              sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
