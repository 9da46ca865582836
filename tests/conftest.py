"""Test-wide setup: importing lvenv first enables float64 before any test builds arrays.

The run has a persistent compilation cache of its own (:mod:`lvenv.jitcache`), a new temporary
folder that the first pytest process makes (``$LVENV_TEST_RUN_JIT_CACHE``) and removes at its
end. The xdist workers, the commands tests start and a child pytest inherit it, so a program
that another worker or a command has already compiled is loaded instead of compiled again.
Tests thus neither write to the user's cache nor depend on an earlier run. Tests of the cache
itself give their processes a folder of their own.

XLA compiles the run's programs at LLVM optimisation level 1 (``XLA_FLAGS``, inherited by the
commands, notebooks and Dask workers that tests start), not at its default 3, which users get.
Compiling takes most of the run's time (62 % of the time in tests at level 3), and level 1 compiles
about 1.6 times as fast, while the programs run about as fast: on one machine, one default run
each, back to back, took 1,367 s at level 3, 1,214 s at level 2 and 967 s at level 1, with the same
546 tests passing. Level 0 halves the compiling again (532 against 1,067 s in the pytest processes,
552 tests), but its programs can run 6 times as slowly (the jacobian's beat tangents), so the whole
run gained only 43 s (1,157 against 1,200 s, one run each), less than two level-1 runs differ
(1,200 and 1,299 s): the run stays at level 1. The programs compute the same thing, but LLVM
vectorises the members' loops differently at each level, so whether a member's last bits depend on
its batch can differ too. The checks that a batch's layout could break (a member's bits in batches
of any size and beside other members) therefore run at level 3, in a child pytest
(``tests/lvenv/test_batching.py::test_layout_checks_hold_as_users_compile``); the ``users_level``
marker keeps the two that cost most out of the level-1 processes. A level that the caller's
``XLA_FLAGS`` names is kept.
"""

import os
import shutil
import tempfile

#: The environment variable that names the run's compilation cache (module docstring).
RUN_JIT_CACHE = "LVENV_TEST_RUN_JIT_CACHE"
_MADE_HERE = RUN_JIT_CACHE not in os.environ
if _MADE_HERE:
    os.environ[RUN_JIT_CACHE] = tempfile.mkdtemp(prefix="lvenv-test-jit-")
os.environ["LVENV_JIT_CACHE"] = os.environ[RUN_JIT_CACHE]

OPTIMISATION_LEVEL = "--xla_backend_optimization_level"
if OPTIMISATION_LEVEL not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {OPTIMISATION_LEVEL}=1".strip()

import lvenv  # noqa: E402, F401
from lvenv import jitcache  # noqa: E402

jitcache.enable()


def pytest_unconfigure(config):
    """The process that made the run's cache removes it once every worker has ended."""
    if _MADE_HERE:
        shutil.rmtree(os.environ[RUN_JIT_CACHE], ignore_errors=True)
