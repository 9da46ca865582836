"""Train the amortised posterior estimator (optim.amortised) and write its artefact; prints JSON.

    python scripts/train_amortised.py [--pairs 1000000] [--sim-seconds 240] [--batch 256] [--train-seconds 150] [--out optim/data/amortised.npz]

Simulates (parameters, observation) pairs from optim.identify.posterior's prior
(`optim.amortised.simulate`), as many as ``--pairs`` or as fit into ``--sim-seconds``: a pilot
of ``--batch`` members compiles the env, a second one measures the rate, then one run sized to
the time left. Trains the flow (``--train-seconds`` at most, early stopping on the validation loss)
and saves the artefact to ``--out``. The JSON gives the pairs, uniform draws tried, those left
out by reason, simulated pairs per second (kept pairs over the main run's seconds, compilation
included), the training time and the validation loss, and the artefact's path.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import lvenv  # noqa: F401  (float64, CPU devices)
from optim import amortised
from optim.identify import PriorSample


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=1_000_000, help="at most this many training pairs (default %(default)s)")
    parser.add_argument("--sim-seconds", type=float, default=240.0, help="time budget of the simulation (s, default %(default)s)")
    parser.add_argument("--batch", type=int, default=256, help="env members per simulated batch (default %(default)s)")
    parser.add_argument("--train-seconds", type=float, default=150.0, help="time budget of the training (s, default %(default)s)")
    parser.add_argument("--batch-size", type=int, default=512, help="training minibatch (default %(default)s)")
    parser.add_argument("--learning-rate", type=float, default=1e-3, help="Adam's learning rate (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--code-version", default=None, help="code version for the metadata (default: lvenv's version and git commit)")
    parser.add_argument("--out", default=str(amortised.DEFAULT_ARTEFACT), help="artefact path (default %(default)s)")
    a = parser.parse_args()

    started = time.perf_counter()
    parts = [amortised.simulate(1, seed=a.seed, batch=a.batch)]  # compiles the env
    compile_seconds = time.perf_counter() - started
    t = time.perf_counter()
    parts.append(amortised.simulate(max(1, a.batch // 4), seed=a.seed + 1, batch=a.batch))
    rate = len(parts[-1].parameters) / (time.perf_counter() - t)
    main_pairs = int(min(a.pairs - sum(len(p.parameters) for p in parts), rate * max(0.0, a.sim_seconds - (time.perf_counter() - started))))
    main_seconds = 0.0
    if main_pairs > 0:
        t = time.perf_counter()
        parts.append(amortised.simulate(main_pairs, seed=a.seed + 2, batch=a.batch))
        main_seconds = time.perf_counter() - t
    left_out: dict[str, int] = {}
    for part in parts:
        for k, v in part.left_out.items():
            left_out[k] = left_out.get(k, 0) + v
    draws = PriorSample(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("parameters", "observations", "heart_rate", "base")),
                        parts[0].names, sum(p.tried for p in parts), left_out)
    sim_seconds = time.perf_counter() - started
    estimator = amortised.train(draws, seed=a.seed, batch_size=a.batch_size, learning_rate=a.learning_rate, max_seconds=a.train_seconds,
                                code_version=a.code_version)
    path = amortised.save(estimator, a.out)
    training = estimator.meta["training"]
    print(json.dumps({
        "pairs": len(draws.parameters), "tried": draws.tried, "left_out": left_out, "batch": a.batch,
        "simulation_seconds": sim_seconds, "compile_seconds": compile_seconds, "pilot_pairs_per_second": rate,
        "tried_per_second": draws.tried / sim_seconds,
        "pairs_per_second": (len(parts[-1].parameters) / main_seconds) if main_seconds else rate,
        "training_seconds": training["seconds"], "epochs": training["epochs"], "best_validation_loss": training["best_validation_loss"],
        "validation_loss": training["validation_loss"], "artefact": str(path), "code_version": estimator.meta["code_version"],
    }, indent=2))


if __name__ == "__main__":
    main()
