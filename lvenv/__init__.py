"""lvenv: a fast, batched low-order left-ventricle model (Di Achille et al. 2020) in JAX.

Importing lvenv enables JAX float64 (``jax_enable_x64``): the model runs in float64 by default.
It also asks XLA for one CPU device per core, so batches spread over all cores
(:mod:`lvenv.devices`; set ``LVENV_CPU_DEVICES=1`` to keep one).

It imports ``jax.extend`` too, before anything compiles. That import registers settings of
JAX's own (Pallas's) that are part of every jitted function's cache key, so importing it later
changes the key: every program compiled before it compiles again on its next call. Equinox
imports it, and the posteriors import Equinox when they first run (:mod:`optim.identify`,
:mod:`optim.amortised`), so without this a fit's step, compiled before a posterior, compiled
again after it (``tests/test_imports.py``).
"""

import jax
import jax.extend  # noqa: F401  (module docstring)

jax.config.update("jax_enable_x64", True)

from lvenv.devices import request_cpu_devices

request_cpu_devices()

from lvenv import geometry, presets
from lvenv.geometry import Geometry
from lvenv.params import CellParams, Circulation, Heart, LOParams, stack
from lvenv.simulation import STATUS, SimulationResult, simulate
from lvenv.sensitivity import Jacobian, jacobian

from lvenv.env import register as _register_envs
from lvenv.patients import Patient

_register_envs()

__all__ = [
    "Patient",
    "geometry", "presets", "Geometry", "Heart", "LOParams", "CellParams", "Circulation",
    "stack", "simulate", "SimulationResult", "STATUS", "jacobian", "Jacobian",
]
