"""Test-wide setup: importing lvenv first enables float64 before any test builds arrays.

The CLI turns on JAX's persistent compilation cache; tests keep it off (``LVENV_JIT_CACHE=off``)
so that they neither write to the user's cache nor depend on it, except the test of the cache
itself, which runs its processes on a cache directory of its own.
"""

import os

os.environ.setdefault("LVENV_JIT_CACHE", "off")

import lvenv  # noqa: E402, F401
