"""Benchmark the vector env against the raw batched LO-heart core in the same run (JSON out).

    python scripts/bench_env.py [--num-envs 1 16 256 1024 4096]

For each num_envs, every member holds a fixed random parameter set; after two warm-up steps
(steady state reached), ``--repeats`` timed ``venv.step`` calls are compared with the same number
of calls of the jitted core (:data:`lvenv.simulation.run_beats_jit`, steady state from the same
warm state, results fetched to the host). Overhead = env time / core time − 1 (medians).
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
import jax.numpy as jnp  # noqa: E402
import gymnasium  # noqa: E402

import lvenv  # noqa: E402
from lvenv import model  # noqa: E402
from lvenv.devices import shard_members  # noqa: E402
from lvenv.simulation import run_beats_jit  # noqa: E402


def measure(num_envs: int, repeats: int, steps_per_beat: int, seed: int = 0) -> dict:
    venv = gymnasium.make_vec("lvenv/LVHeart-v0", num_envs=num_envs, max_episode_steps=None, tolerance=0.0, autoreset_mode="Disabled", steps_per_beat=steps_per_beat)
    space = venv.single_action_space
    rng = np.random.default_rng(seed)
    unit = rng.uniform(0.2, 0.8, (num_envs, space.shape[0]))
    actions = venv.config.actions.space.from_unit(unit)
    venv.reset(seed=seed)
    for _ in range(2):
        venv.step(actions)
    env_times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        venv.step(actions)
        env_times.append(time.perf_counter() - t0)

    config = venv.config
    params = model.model_params(lvenv.stack([venv.member_heart(i) for i in range(num_envs)]))
    (heart, y), _ = shard_members((params, venv.get_state()["y"].T), num_envs)
    core_call = lambda: jax.device_get(run_beats_jit(heart, y, jnp.asarray(config.rtol), steps=config.steps_per_beat, max_beats=config.max_beats, steady=True, record=False))
    out = core_call()
    core_times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        core_call()
        core_times.append(time.perf_counter() - t0)
    t_env, t_core = float(np.median(env_times)), float(np.median(core_times))
    return {
        "num_envs": num_envs,
        "env_steps_per_s": 1.0 / t_env,
        "member_evaluations_per_s": num_envs / t_env,
        "core_calls_per_s": 1.0 / t_core,
        "overhead": t_env / t_core - 1.0,
        "beats_per_step_median": float(np.median(out["beats"])),
        "env_times_s": env_times,
        "core_times_s": core_times,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 16, 256, 1024, 4096])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps-per-beat", type=int, default=1000)
    args = parser.parse_args()
    results = []
    for n in args.num_envs:
        r = measure(n, args.repeats, args.steps_per_beat)
        results.append(r)
        print(f"# num_envs {n}: {r['env_steps_per_s']:.2f} env steps/s, overhead {100 * r['overhead']:+.1f} %", file=sys.stderr, flush=True)
    print(json.dumps({"device": str(jax.devices()[0].device_kind), "n_devices": len(jax.devices()), "steps_per_beat": args.steps_per_beat, "results": results}, indent=2))


if __name__ == "__main__":
    main()
