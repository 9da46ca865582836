"""How much of the congruency error is the wall's spread of activation? (JSON out.)

    python scripts/synchronous_training.py [--hearts normal] [--mesh-size 6] [--budget 960]
        [--activations eikonal synchronous] [--cell beta1=0 ...]

For each heart, `optim.congruency.train` twice against the 3-D oracle: with its eikonal
activation (DESIGN §4) and with every point activated at the beat's onset
(`fe_oracle.run(..., activation="synchronous")`), like the single LO cell. The second removes the
spread of activation from the oracle, so what C it leaves is the part no activation parameter of
the single cell can absorb. Per heart and activation: C per training beat with and without the
activation delay, C of the paper's Table 3 maps, the trained values, and the times. ``--cell``
changes cell parameters (lvenv.params.CellParams, by name) in wall and LO cell alike, to test
which of the cell's mechanisms the remaining C comes from. The package's trained records are not
touched.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import fe_oracle  # noqa: E402
from lvenv.params import CellParams  # noqa: E402
from optim import congruency  # noqa: E402
from scripts.train_presets import HEARTS  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hearts", nargs="+", choices=sorted(HEARTS), default=["normal"])
    parser.add_argument("--mesh-size", type=float, default=fe_oracle.DEFAULT_MESH_SIZE, help="oracle mesh size h (mm)")
    parser.add_argument("--budget", type=int, default=960)
    parser.add_argument("--activations", nargs="+", choices=fe_oracle.ACTIVATIONS, default=list(fe_oracle.ACTIVATIONS))
    parser.add_argument("--cell", nargs="*", default=[], metavar="NAME=VALUE", help="cell parameters to change, e.g. beta1=0")
    args = parser.parse_args()
    try:
        changes = {name: float(value) for name, value in (item.split("=", 1) for item in args.cell)}
        cell = CellParams(**changes)
    except (TypeError, ValueError) as err:
        parser.error(f"--cell {' '.join(args.cell)}: give NAME=VALUE pairs of lvenv.params.CellParams fields ({err})")
    summary = {}
    for name in args.hearts:
        geometry, table3 = HEARTS[name]
        for activation in args.activations:
            t0 = time.perf_counter()
            data = congruency.oracle_data(geometry, cell=cell, progress=False, mesh_size=args.mesh_size, activation=activation)
            t_oracle = time.perf_counter() - t0
            t0 = time.perf_counter()
            trained = congruency.train(geometry, cell=cell, budget=args.budget, progress=False, mesh_size=args.mesh_size, activation=activation)
            t_train = time.perf_counter() - t0
            c3 = congruency.run_congruency(data, [table3], 1000)[0]
            summary[f"{name}/{activation}"] = {
                "C": trained.congruency, "C_without_delay": trained.congruency_without_delay,
                "C_table3": congruency.congruency_dict(c3),
                "trained": dataclasses.asdict(trained.lo), "mesh_size_mm": args.mesh_size, "cell_changes": changes,
                "activation_time_max_s": data.beats[congruency.CONDITIONS[0]].metadata["activation_time_max_s"],
                "training_s": t_train, "oracle_s": t_oracle,
            }
            print(f"# {name}, {activation}: C {trained.congruency['C']:.4f} ({t_oracle:.0f} s oracle, {t_train:.0f} s training)", file=sys.stderr, flush=True)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
