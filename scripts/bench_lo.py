"""Benchmark the batched LO heart's integration schemes against the scipy Radau reference, all in the same run (JSON out).

    python scripts/bench_lo.py                       # CPU: batches 256 … 4096, fixed 1000 / 500 steps and adaptive
    python scripts/bench_lo.py --batches 1024 65536 262144 1048576 --dtype float32   # GPU
    python scripts/bench_lo.py --models single series3 --configs fixed:1000 --batches 1024   # a model's cost

A configuration is ``fixed:STEPS`` (equal ROS2 steps per beat; ``fixed:1000`` is the old
default) or ``adaptive:TOL`` (per-member step-size control at relative tolerance TOL).
Per configuration: its metrics error against a scipy ``solve_ivp(Radau, rtol=1e-8)`` loop on the
same equations (``--reference-members`` random hearts; the accuracy specification is EF within
0.5 points, phase durations within 2 ms, pressures within 1 %), ROS2 steps per beat, and per
batch size beats/s (median of --repeats timed runs after one compile run), both end to end
through ``lvenv.simulate`` (validation, V0, initial state, transfers included) and for the jitted
batch core alone on device-resident inputs (what the vector env steps); ``ratio_vs_first`` is
the core's beats/s over the first configuration's at the same batch.

``--models`` (`lvenv.presets.LO_MODELS`): run the configurations for each LO heart model, the
first model first; ``ratio_vs_first`` then also compares each model with the first model's first
configuration (a multi-element model takes the fixed configurations only, and has no Radau
reference: its ``error_vs_radau`` is null).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import lvenv  # noqa: E402
from lvenv import lo_model, presets  # noqa: E402
from lvenv.devices import shard_members  # noqa: E402
from lvenv.simulation import DEFAULT_STEP_TOL, run_beats_jit  # noqa: E402
from lvenv.geometry import cavity_volume  # noqa: E402
from tests.lvenv.reference_lo import simulate_reference  # noqa: E402

BEATS = 2


def cohort(n: int, seed: int = 0, model: str = "single") -> lvenv.Heart:
    """A stacked batch of n hearts alternating N / HF with randomised physiology, of the LO heart ``model``."""
    rng = np.random.default_rng(seed)
    pair = lvenv.stack([presets.normal(model=model), presets.heart_failure(model=model)])
    tiled = jax.tree.map(lambda x: np.resize(x, n), pair)
    if pair.elements is not None and np.ndim(pair.elements.element_onsets()) == 2:  # the walls' own onsets: one row per member
        rows = np.resize(pair.elements.element_onsets(), (n, pair.elements.n_elements))
        tiled = dataclasses.replace(tiled, elements=dataclasses.replace(pair.elements, onsets=tuple(map(tuple, rows))))
    return tiled.replace(tau2=rng.uniform(0.09, 0.25, n), Sa=rng.uniform(0.8, 1.5, n), R3=rng.uniform(0.12, 0.4, n), C=rng.uniform(6.0, 25.0, n), Cat=rng.uniform(1.5, 10.0, n))


def settings(config: str) -> dict:
    """``fixed:STEPS`` or ``adaptive:TOL`` as keyword arguments of ``lvenv.simulate``."""
    scheme, value = config.split(":")
    fixed = scheme == "fixed"
    return {"scheme": scheme, "steps_per_beat": int(value) if fixed else 1000, "step_tol": DEFAULT_STEP_TOL if fixed else float(value)}


def time_batch(batch, config, dtype, repeats):
    run = lambda: lvenv.simulate(batch, beats=BEATS, traces=False, dtype=dtype, **settings(config))
    t0 = time.perf_counter()
    first = run()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = run()
        times.append(time.perf_counter() - t0)
    assert np.all(res.status == "ok"), np.unique(res.status, return_counts=True)
    return first, compile_s, times


def time_core(batch, config, dtype, repeats):
    """The jitted batch core alone, on device-resident, pre-validated inputs (the env's hot path)."""
    p = lo_model.core_params(batch)
    (p_dev, y_dev), _ = shard_members((jax.tree.map(lambda x: np.asarray(x, dtype), p), np.asarray(lo_model.initial_state(p), dtype)), len(p.v0))
    kw = settings(config)
    run = lambda: jax.block_until_ready(run_beats_jit(p_dev, y_dev, jnp.asarray(1e-4, dtype), steps=kw["steps_per_beat"], max_beats=BEATS,
                                                      steady=False, record=False, scheme=kw["scheme"], step_tol=kw["step_tol"]))
    return timed(run, repeats)


def timed(run, repeats: int) -> list[float]:
    """One untimed run of ``run`` (the compile), then the wall times (s) of ``repeats`` runs."""
    run()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return times


def accuracy(hearts, config, dtype):
    res = lvenv.simulate(hearts, beats=BEATS, traces=False, dtype=dtype, **settings(config))
    t0 = time.perf_counter()
    refs = [simulate_reference(h, cavity_volume(h.geometry), beats=BEATS)[0] for h in hearts]
    radau_s = time.perf_counter() - t0
    err = {"EF_abs": 0.0, "timing_abs_s": 0.0, "pressure_rel": 0.0, "volume_rel": 0.0}
    for i, ref in enumerate(refs):
        m = res[i].metrics
        err["EF_abs"] = max(err["EF_abs"], abs(m["EF"] - ref["EF"]))
        err["timing_abs_s"] = max(err["timing_abs_s"], *(abs(m[k] - ref[k]) for k in ("IVCT", "ET", "IVRT")))
        err["pressure_rel"] = max(err["pressure_rel"], *(abs(m[k] / ref[k] - 1) for k in ("P_lv_peak", "P_ao_sys", "P_ao_dia", "P_ao_mean")))
        err["volume_rel"] = max(err["volume_rel"], *(abs(m[k] / ref[k] - 1) for k in ("EDV", "ESV")))
    return err, len(hearts) * BEATS / radau_s, float(np.median(res.steps)) / BEATS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", type=int, nargs="+", default=[256, 1024, 4096])
    parser.add_argument("--configs", nargs="+", default=["fixed:1000", "fixed:500", "adaptive:0.002"], help="fixed:STEPS or adaptive:TOL; the first is the baseline")
    parser.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reference-members", type=int, default=16, help="members integrated by the Radau baseline")
    parser.add_argument("--models", nargs="+", choices=list(presets.LO_MODELS), default=["single"], help="LO heart models; the first is the baseline")
    args = parser.parse_args()
    dtype = {"float64": jnp.float64, "float32": jnp.float32}[args.dtype]
    out = {
        "device": str(jax.devices()[0].device_kind), "n_devices": len(jax.devices()), "backend": jax.default_backend(),
        "dtype": args.dtype, "beats_per_run": BEATS, "runs": [],
    }
    ref_batch = cohort(args.reference_members, seed=1)
    ref_hearts = [jax.tree.map(lambda x, i=i: float(x[i]), ref_batch) for i in range(args.reference_members)]
    first: dict[int, float] = {}
    for name in args.models:
        multi = presets.LO_MODELS[name] is not None
        for config in args.configs:
            if multi and not config.startswith("fixed:"):
                continue  # the adaptive scheme is the single cell's
            err, radau_beats_per_s, steps = (None, None, int(config.split(":")[1])) if multi else accuracy(ref_hearts, config, dtype)
            entry = {"model": name, "config": config, "error_vs_radau": err, "steps_per_beat_median": steps, "radau_beats_per_s": radau_beats_per_s, "batches": []}
            for n in args.batches:
                batch = cohort(n, model=name)
                _, compile_s, times = time_batch(batch, config, dtype, args.repeats)
                core_times = time_core(batch, config, dtype, args.repeats)
                bps = n * BEATS / float(np.median(times))
                core_bps = n * BEATS / float(np.median(core_times))
                first.setdefault(n, core_bps)
                entry["batches"].append({
                    "batch": n, "beats_per_s_median": bps, "speedup_vs_radau": None if multi else bps / radau_beats_per_s, "times_s": times,
                    "first_call_s": compile_s, "core_beats_per_s_median": core_bps, "core_times_s": core_times, "ratio_vs_first": core_bps / first[n],
                })
                accurate = "" if multi else (f"; error EF {100 * err['EF_abs']:.2f} pt, timing {1e3 * err['timing_abs_s']:.2f} ms, "
                                             f"pressure {100 * err['pressure_rel']:.2f} %")
                print(f"# {name} {config} batch {n}: simulate() {bps:,.0f} beats/s, jitted core {core_bps:,.0f} beats/s (x{core_bps / first[n]:.2f})"
                      + accurate, file=sys.stderr, flush=True)
            out["runs"].append(entry)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
