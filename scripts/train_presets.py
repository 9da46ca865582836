"""Congruency-train the N and HF presets against the 3-D oracle and write the package records (JSON out).

    python scripts/train_presets.py [--hearts normal heart_failure] [--out lvenv/data] [--budget 960]
    python scripts/train_presets.py --model series3 [--budget 480]

For each heart: `optim.congruency.train` at the default mesh and time step (the oracle runs come
from its cache when they exist), the record written to `<out>/trained_<heart>.json`, and a JSON
summary: C per training beat with and without the activation delay and with the paper's Table 3
maps, the trained values beside Table 3, the passive fit's residual, the time of the active
training, and the oracle's time per run.

``--model`` (a multi-element model of `lvenv.presets.LO_MODELS`): instead, that model's maps,
trained from the heart's single-cell record in ``--out`` (`optim.congruency.train_model`, on the
same oracle runs), written to `<out>/trained_<heart>_<model>.json`; the summary gives C per
training beat beside the single cell's and the cells' onsets.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from lvenv import presets  # noqa: E402
from lvenv.trained import TrainedLO  # noqa: E402
from optim import congruency  # noqa: E402

HEARTS = {"normal": (presets.N_UNLOADED, presets.N_LO), "heart_failure": (presets.HF_UNLOADED, presets.HF_LO)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hearts", nargs="+", choices=sorted(HEARTS), default=list(HEARTS))
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("lvenv/data"))
    parser.add_argument("--budget", type=int, default=None, help="MADS evaluations per active fit (default 960; with --model 480)")
    parser.add_argument("--model", choices=presets.MULTI_ELEMENT_MODELS,
                        help="train this multi-element model's maps from the single-cell records")
    args = parser.parse_args()
    if args.model is not None:
        print(json.dumps(train_models(args), indent=2))
        return
    args.budget = 960 if args.budget is None else args.budget
    summary = {}
    for name in args.hearts:
        geometry, table3 = HEARTS[name]
        t0 = time.perf_counter()
        data = congruency.oracle_data(geometry, progress=False)
        t_oracle = time.perf_counter() - t0
        t0 = time.perf_counter()
        trained = congruency.train(geometry, budget=args.budget, progress=False)
        t_train = time.perf_counter() - t0
        trained.to_json(args.out / f"trained_{name}.json")
        c3 = congruency.run_congruency(data, [table3], 1000)[0]
        summary[name] = {
            "C": trained.congruency, "C_without_delay": trained.congruency_without_delay,
            "C_table3": congruency.congruency_dict(c3),
            "trained": dataclasses.asdict(trained.lo), "table3": dataclasses.asdict(table3),
            "passive_rmse_ml": trained.passive_rmse_ml, "training_s": t_train, "oracle_read_s": t_oracle,
            "oracle_run_s": {k: r.metadata.get("total_s") for k, r in [("passive", data.passive), *((str(k), r) for k, r in data.beats.items())]},
        }
        print(f"# {name}: C {trained.congruency['C']:.4f} ({t_train:.0f} s)", file=sys.stderr, flush=True)
    print(json.dumps(summary, indent=2))


def train_models(args) -> dict:
    """``--model``: each heart's maps of that model, from its single-cell record (module docstring)."""
    summary = {}
    for name in args.hearts:
        single = TrainedLO.from_json(args.out / f"trained_{name}.json")
        data = congruency.oracle_data(single.geometry, cell=single.cell, progress=False)
        t0 = time.perf_counter()
        record = congruency.train_model(data, single, args.model, budget=480 if args.budget is None else args.budget, progress=False)
        seconds = time.perf_counter() - t0
        record.to_json(args.out / f"trained_{presets.record_name(name, args.model)}.json")
        summary[name] = {"C": record.congruency, "C_single": single.congruency, "onsets_ms": [1000 * x for x in record.elements.onsets],
                         "trained": dataclasses.asdict(record.lo), "training_s": seconds}
        print(f"# {name} {args.model}: C {record.congruency['C']:.4f} (single cell {single.congruency['C']:.4f}; {seconds:.0f} s)", file=sys.stderr, flush=True)
    return summary


if __name__ == "__main__":
    main()
