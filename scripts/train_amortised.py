"""Train the amortised posterior estimator (optim.amortised) and write its artefact; prints JSON.

    python scripts/train_amortised.py [--pairs 1000000] [--sim-seconds 240] [--batch 256] [--chunk 5000] [--draws FILE]
        [--bases normal heart_failure] [--extra-draws FILE ...] [--copies 1] [--train-seconds 150] [--plateau 3] [--decay 0.5]
        [--patience 10] [--flow-layers 6] [--nn-width 128] [--common-share 0.8] [--out optim/data/amortised.npz]

Simulates (parameters, observation) pairs from optim.identify.posterior's prior
(`optim.amortised.simulate`, over the heart kinds ``--bases``: base presets, and ``anatomy`` for
hearts drawn over the anatomy box with the anatomy regression's maps) in chunks of ``--chunk``
pairs, ``--batch`` env members at a time, until there are ``--pairs`` or ``--sim-seconds`` have
passed (a chunk under way finishes). ``--draws FILE`` keeps the pairs
(`optim.amortised.save_draws`, written after every chunk) and resumes from them: a second call
adds chunks with new seeds, or only trains if there are enough. ``--extra-draws`` adds the pairs
of other files (their own heart kinds, read only): e.g. preset pairs and anatomy pairs simulated
apart, by two processes, one per core. Chunk k uses seed ``--seed + 1 + k``; the held-out truths
of the calibration use seeds from 1000 on, so give two simulations far-apart ``--seed``s.
``--train-seconds 0`` only simulates. Trains the flow (``--train-seconds`` at most, early stopping on the validation loss, the
learning rate times ``--decay`` after every ``--plateau`` epochs without improvement; each pair
``--copies`` times per epoch, with fresh noise and masks every epoch, a share ``--common-share`` of them
the target sets patients carry, optim.amortised.COMMON_MASKS) and saves the artefact to ``--out``.
The JSON gives the pairs, uniform draws tried, those left out by reason, the chunks' seconds,
simulated pairs per second (median over the chunks after the first, which compiles the env),
the training time and the validation loss, the artefact's path, the machine and the command.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import sys
import time

import lvenv  # noqa: F401  (float64, CPU devices)
from optim import amortised
from optim.identify import PriorSample

#: Chunk seeds stay below the held-out truths' (optim.amortised.held_out_patients: seed + 1000).
SEED_LIMIT = 1000


def _epoch_done(epoch: int, train: float, validation: float, rate: float) -> None:
    """One line of training progress on stderr (losses in nats)."""
    print(f"epoch {epoch}: loss {train:.4f}, validation {validation:.4f}, learning rate {rate:.2e}", file=sys.stderr, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=1_000_000, help="at most this many training pairs (default %(default)s)")
    parser.add_argument("--sim-seconds", type=float, default=240.0, help="time budget of the simulation (s, default %(default)s)")
    parser.add_argument("--batch", type=int, default=256, help="env members per simulated batch (default %(default)s)")
    parser.add_argument("--chunk", type=int, default=5000, help="pairs per simulated chunk (default %(default)s)")
    parser.add_argument("--draws", default=None, help="file of simulated pairs: resumed from if it exists, written after every chunk")
    parser.add_argument("--bases", nargs="+", default=list(amortised.BASES), choices=amortised.KINDS,
                        help="heart kinds of the simulated pairs (default: %(default)s)")
    parser.add_argument("--extra-draws", nargs="*", default=[], metavar="FILE", help="more pairs to train on, read only")
    parser.add_argument("--copies", type=int, default=1, help="uses of each pair per epoch, each with fresh noise and masks (default %(default)s)")
    parser.add_argument("--train-seconds", type=float, default=150.0, help="time budget of the training (s, default %(default)s)")
    parser.add_argument("--batch-size", type=int, default=512, help="training minibatch (default %(default)s)")
    parser.add_argument("--learning-rate", type=float, default=1e-3, help="Adam's initial learning rate (default %(default)s)")
    parser.add_argument("--plateau", type=int, default=3, help="epochs without improvement before each decay of the rate (default %(default)s)")
    parser.add_argument("--decay", type=float, default=0.5, help="factor of each decay (default %(default)s)")
    parser.add_argument("--patience", type=int, default=10, help="epochs without improvement before stopping (default %(default)s)")
    parser.add_argument("--flow-layers", type=int, default=amortised.Architecture.flow_layers, help="coupling layers (default %(default)s)")
    parser.add_argument("--nn-width", type=int, default=amortised.Architecture.nn_width, help="conditioner MLP width (default %(default)s)")
    parser.add_argument("--common-share", type=float, default=amortised.COMMON_SHARE,
                        help="share of the training rows masked as patients are (optim.amortised.COMMON_MASKS; default %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--code-version", default=None, help="code version for the metadata (default: lvenv's version and git commit)")
    parser.add_argument("--out", default=str(amortised.DEFAULT_ARTEFACT), help="artefact path (default %(default)s)")
    a = parser.parse_args()

    parts: list[PriorSample] = []
    seeds: list[int] = []
    made_by = None
    bases = amortised.heart_kinds(a.bases)
    if a.draws and pathlib.Path(a.draws).exists():
        loaded, seeds, made_by, _ = amortised.load_draws(a.draws, bases=bases)
        parts.append(loaded)
    chunk_seconds: list[float] = []
    started = time.perf_counter()
    while sum(len(p.parameters) for p in parts) < a.pairs and time.perf_counter() - started < a.sim_seconds:
        seed = a.seed + 1 + len(seeds)
        if seed >= SEED_LIMIT:
            parser.error(f"chunk seed {seed} would reach the held-out truths' seeds (from {SEED_LIMIT}); use fewer, larger chunks")
        t = time.perf_counter()
        parts.append(amortised.simulate(min(a.chunk, a.pairs - sum(len(p.parameters) for p in parts)), bases=bases, seed=seed, batch=a.batch))
        chunk_seconds.append(time.perf_counter() - t)
        seeds.append(seed)
        if a.draws:
            amortised.save_draws(PriorSample.concatenate(parts), a.draws, seeds=seeds, bases=bases)
            print(f"{sum(len(p.parameters) for p in parts)} pairs in {a.draws}", file=sys.stderr, flush=True)
    steady = [len(p.parameters) / s for p, s in zip(parts[-len(chunk_seconds):][1:], chunk_seconds[1:])]
    simulated = {"pairs": sum(len(p.parameters) for p in parts), "chunks": len(seeds), "draws": a.draws, "draws_made_by": made_by,
                 "chunk_seconds": chunk_seconds, "pairs_per_second": statistics.median(steady) if steady else None}
    if a.train_seconds <= 0:
        print(json.dumps(simulated, indent=2))
        return
    kinds = set(bases)
    for path in a.extra_draws:
        extra, _, _, extra_kinds = amortised.load_draws(path)
        parts.append(extra)
        kinds |= set(extra_kinds)
    bases = amortised.heart_kinds(kinds)
    draws = PriorSample.concatenate(parts)
    architecture = amortised.Architecture(flow_layers=a.flow_layers, nn_width=a.nn_width)
    estimator = amortised.train(draws, bases=bases, architecture=architecture, seed=a.seed, copies=a.copies, batch_size=a.batch_size,
                                learning_rate=a.learning_rate, plateau=a.plateau, decay=a.decay, patience=a.patience, max_seconds=a.train_seconds,
                                common_share=a.common_share,
                                code_version=a.code_version, progress=_epoch_done)
    path = amortised.save(estimator, a.out)
    training = estimator.meta["training"]
    print(json.dumps({
        **simulated, "pairs": len(draws.parameters), "bases": list(bases), "extra_draws": a.extra_draws, "tried": draws.tried,
        "left_out": draws.left_out, "batch": a.batch, "training_seconds": training["seconds"], "epochs": training["epochs"], "best_validation_loss": training["best_validation_loss"],
        "validation_loss": training["validation_loss"], "learning_rates": training["learning_rates"], "architecture": estimator.meta["architecture"], "artefact": str(path), "code_version": estimator.meta["code_version"],
        "machine": f"{platform.machine()}, {os.cpu_count()} logical cores, {platform.python_implementation()} {platform.python_version()}",
        "command": "python scripts/train_amortised.py " + " ".join(sys.argv[1:]),
    }, indent=2))


if __name__ == "__main__":
    main()
