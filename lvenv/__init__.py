"""lvenv: a fast, batched low-order left-ventricle model (Di Achille et al. 2020) in JAX.

Importing lvenv enables JAX float64 (``jax_enable_x64``): the model runs in float64 by default.
It also asks XLA for one CPU device per core, so batches spread over all cores
(:mod:`lvenv.devices`; set ``LVENV_CPU_DEVICES=1`` to keep one).
"""

import jax

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
