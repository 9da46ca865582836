"""The LO heart a :class:`~lvenv.params.Heart` carries, as the jitted code sees it.

``Heart.elements`` chooses the model: ``None`` the paper's single-cell heart
(:class:`lvenv.model.ModelParams`, state ``(9, B)``), an :class:`~lvenv.params.Arrangement` a
multi-element heart (:class:`lvenv.multielement.ElementParams`, flat state ``(7 n + 4, B)``,
:func:`lvenv.multielement.flatten`). Both parameter types share ``v0``, ``lo``, ``cell``,
``circ``, ``get`` and ``replace``; the beat loops (:mod:`lvenv.simulation`), the env and
:func:`lvenv.jacobian` reach the rest (the initial state, where V, P_c and P_at sit in the
state) through this module, so that each takes either model.
"""

from __future__ import annotations

import numpy as np

from lvenv import model, multielement
from lvenv.model import ModelParams
from lvenv.params import Arrangement, Heart
from lvenv.validation import InputError

__all__ = ["core_params", "initial_state", "n_states", "circulation_index", "is_multielement", "check_scheme"]


def core_params(heart: Heart) -> ModelParams:
    """Host-side: a stacked, validated Heart batch → the parameters of the model it carries."""
    if heart.elements is None:
        return model.model_params(heart)
    return multielement.element_params(heart, heart.elements)


def is_multielement(p: ModelParams) -> bool:
    """Whether ``p`` (:func:`core_params`) is a multi-element heart's."""
    return isinstance(p, multielement.ElementParams)


def initial_state(p: ModelParams) -> np.ndarray:
    """The training protocol's initial state (DESIGN §1.2) of every member, ``(n_states, B)``."""
    if is_multielement(p):
        return np.asarray(multielement.flatten(multielement.initial_state(p)))
    return model.initial_state(p)


def n_states(p: ModelParams) -> int:
    """Rows of ``p``'s state."""
    return multielement.n_states(p.n_elements) if is_multielement(p) else model.N_STATES


def circulation_index(of: ModelParams | Heart) -> tuple[int, int, int]:
    """Rows of V (ml), P_c and P_at (kPa) in the state of ``of``'s model (its parameters,
    :func:`core_params`, or a Heart: e.g. in :attr:`lvenv.SimulationResult.final_state`)."""
    if isinstance(of, Heart):
        n = None if of.elements is None else of.elements.n_elements
    else:
        n = of.n_elements if is_multielement(of) else None
    return (model.IDX_V, model.IDX_PC, model.IDX_PAT) if n is None else multielement.circulation_index(n)


def check_scheme(elements: Arrangement | None, scheme: str) -> None:
    """InputError if ``scheme`` (:data:`lvenv.simulation.SCHEMES`) cannot integrate the LO heart
    model ``elements`` (``Heart.elements``): a multi-element heart takes the fixed scheme only."""
    if elements is not None and scheme == "adaptive":
        raise InputError(f"scheme = 'adaptive' is not available for a multi-element heart (elements = {elements!r}); use scheme='fixed'")
