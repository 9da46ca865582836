"""Ship the built-in hearts' FE runs with the package, so that a fresh machine compares LO hearts against them without an FE run; JSON out.

    python scripts/ship_fe_runs.py [--hearts normal heart_failure] [--dt 0.005] [--mesh-size 6] [--no-unseen]

For each built-in heart (N, HF, `scripts.train_presets.HEARTS`): the runs its training takes
(`optim.congruency.oracle_data`: the passive curve and the beats ①②③, h = 6 mm), its
unseen scenarios (`optim.studies.UNSEEN`, one beat each under condition ②) and two points inside
each scenario's axis (`optim.studies.INTERIOR`, `optim.studies.OUTER`), the runs
`scripts/candidate_study.py hearts` and `retune`, `scripts/generalisation.py`,
`scripts/smooth_maps.py` and `scripts/train_presets.py` compare against
(``--no-unseen``: the training runs alone; ``--dt`` and ``--mesh-size``: the oracle's, as for
`candidate_study.py hearts`). Each is
read from the oracle's cache or run (about a minute per beat on one core, more while other work
runs), then written to `fe_oracle.cache.SHIPPED` under its key,
without its solver log. `fe_oracle.run` reads them from there when the cache lacks them
(`fe_oracle.cache.lookup`). Their keys hold the oracle's code version, so after a change to the
oracle's code they are not read: run this again (the stale files are removed).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import fe_oracle  # noqa: E402
from fe_oracle import cache  # noqa: E402
from lvenv import presets  # noqa: E402
from optim import congruency  # noqa: E402
from optim.studies import INTERIOR, OUTER, UNSEEN, scenario  # noqa: E402
from scripts.train_presets import HEARTS  # noqa: E402


def add_oracle_arguments(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """``--dt`` and ``--mesh-size``, the oracle's options (here and in `candidate_study.py hearts`);
    ``prefix`` starts their help."""
    parser.add_argument("--dt", type=float, help=f"{prefix}the oracle's time step (s; default its own, {1000 * fe_oracle.DEFAULT_DT['dolfinx']:g} ms)")
    parser.add_argument("--mesh-size", type=float, help=f"{prefix}the oracle's mesh size h (mm; default its own, {fe_oracle.DEFAULT_MESH_SIZE:g} mm)")


def oracle_options(args: argparse.Namespace) -> dict:
    """`fe_oracle.run`'s keywords for the ``--dt`` and ``--mesh-size`` given (none: the oracle's defaults)."""
    return {k: v for k, v in (("dt", args.dt), ("mesh_size", args.mesh_size)) if v is not None}


def oracle_setting(args: argparse.Namespace | None = None) -> str:
    """The oracle's mesh size and time step as the tables write them: ``args``'s ``--mesh-size``
    and ``--dt`` where given, else the oracle's own (``fe_oracle.DEFAULT_MESH_SIZE``, ``DEFAULT_DT``)."""
    options = {"mesh_size": fe_oracle.DEFAULT_MESH_SIZE, "dt": fe_oracle.DEFAULT_DT["dolfinx"], **({} if args is None else oracle_options(args))}
    return f"h = {options['mesh_size']:g} mm, dt = {1000 * options['dt']:g} ms"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hearts", nargs="+", choices=sorted(HEARTS), default=sorted(HEARTS))
    add_oracle_arguments(parser)
    parser.add_argument("--no-unseen", action="store_true", help="the training runs alone, not the unseen scenarios and the points inside their axes")
    args = parser.parse_args()
    oracle = oracle_options(args)
    runs = {}
    for name in args.hearts:
        heart = getattr(presets, name)()
        data = congruency.oracle_data(heart.geometry, cell=heart.cell, progress=False, **oracle)
        results = {f"training {case}": r for case, r in (("passive", data.passive), *((str(k), b) for k, b in data.beats.items()))}
        for label, change in ({} if args.no_unseen else {**UNSEEN, **dict(INTERIOR.values()), **dict(OUTER.values())}).items():
            h = scenario(heart, change)
            results[label] = fe_oracle.run(h.geometry, h.circulation, cell=h.cell, progress=False, **oracle)
        for label, result in results.items():
            key = result.metadata["key"]
            cache.store(cache.SHIPPED, key, fe_oracle.OracleResult(result.traces, result.metadata, []))
            runs[key] = {"heart": name, "run": label, "code_version": result.metadata["code_version"]}
    stale = [path for path in cache.SHIPPED.glob("*.npz") if path.stem not in runs and cache.load(cache.SHIPPED, path.stem).metadata["code_version"] != cache.code_version()]
    for path in stale:
        path.unlink()
    print(json.dumps({"shipped": runs, "removed_stale": [p.name for p in stale], "directory": str(cache.SHIPPED)}, indent=1))


if __name__ == "__main__":
    main()
