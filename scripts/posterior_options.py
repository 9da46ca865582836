"""The posterior sampler's command-line options, shared by the identification scripts
(``calibration.py``, ``narrowing.py``, ``posterior_patients.py``): ``--sampler`` and the sampler's
sizes, with :func:`optim.identify.posterior`'s own defaults. Not an entry point."""

from __future__ import annotations

import argparse
import inspect
from typing import Any

from optim.identify import SAMPLERS, posterior

__all__ = ["SAMPLER_SETTINGS", "add_sampler_options", "sampler_options"]


#: The sampler's size settings that scripts expose as options (``--chain-steps`` for
#: ``chain_steps``), with their help; the defaults are :func:`~optim.identify.posterior`'s own.
SAMPLER_SETTINGS = {
    "walkers": "the pilot ensemble's walkers",
    "steps": "the pilot's steps",
    "chains": "independent chains after the pilot (0: the pilot's walkers are the sample)",
    "chain_steps": "steps of each chain in the last round (NUTS: kept iterations of each chain)",
}


def add_sampler_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--sampler`` (:data:`~optim.identify.SAMPLERS`) and :data:`SAMPLER_SETTINGS` to ``parser``, the
    latter as integer options, all with :func:`~optim.identify.posterior`'s defaults."""
    defaults = inspect.signature(posterior).parameters
    parser.add_argument("--sampler", choices=SAMPLERS, default=defaults["sampler"].default,
                        help="what samples after the pilot: independent MH chains or NUTS through the heart (default %(default)s)")
    for name, text in SAMPLER_SETTINGS.items():
        parser.add_argument("--" + name.replace("_", "-"), type=int, default=defaults[name].default, help=f"{text} (default %(default)s)")


def sampler_options(args: argparse.Namespace) -> dict[str, Any]:
    """``sampler`` and the :data:`SAMPLER_SETTINGS` of parsed ``args``, as keywords of :func:`~optim.identify.posterior`."""
    return {"sampler": args.sampler, **{name: getattr(args, name) for name in SAMPLER_SETTINGS}}
