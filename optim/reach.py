"""Physiological reachability: can the identification parameters reach human resting values?

The LO heart with the paper's cell defaults must be able to produce a normal human resting beat
within the identification bounds (README, "Reachability"). :func:`reach` asks CMA-ES
(:mod:`optim.cmaes`, through :func:`optim.minimize`) for values of the action parameters whose
closed-loop steady state matches :data:`lvenv.identification.OBSERVATION_TARGETS` (EF 60 %,
ET 300 ms, IVRT 80 ms, 120/75 mmHg), with equal weights.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import gymnasium

from lvenv.identification import DEFAULT_ACTION_PARAMS, OBSERVATION_TARGETS
from lvenv.params import Heart
from lvenv.patients import Patient
from optim.minimize import MinimizeResult, minimize

__all__ = ["reach"]


def reach(
    heart: Heart,
    targets: Mapping[str, float] = OBSERVATION_TARGETS,
    names: Sequence[str] = DEFAULT_ACTION_PARAMS,
    *,
    seed: int = 0,
    budget: int = 2048,
    num_envs: int = 64,
    steps_per_beat: int = 1000,
    max_beats: int = 60,
    progress: bool | None = None,
) -> MinimizeResult:
    """Fit ``names`` of ``heart`` (within their identification bounds) to ``targets``.

    One vector env of ``num_envs`` members; CMA-ES from the heart's own values with a budget of
    ``budget`` steady-state simulations. The result's ``relative_error`` holds the signed
    relative error per target at the best point.
    """
    venv = gymnasium.make_vec(
        "lvenv/LVHeart-v0", num_envs=num_envs, patient=Patient("reach", heart, dict(targets)), action_params=tuple(names),
        max_episode_steps=None, tolerance=0.0, autoreset_mode="Disabled", steps_per_beat=steps_per_beat, max_beats=max_beats,
    )
    try:
        return minimize(venv, "cma", budget=budget, seed=seed, progress=progress)
    finally:
        venv.close()
