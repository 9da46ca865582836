"""Test-wide setup: importing lvenv first enables float64 before any test builds arrays.

JAX's persistent compilation cache (:mod:`lvenv.jitcache`). The CLI keeps it in the user's
folder; the tests never touch that one. A test run makes a fresh folder of its own
(``LVENV_JIT_CACHE``, set by the controlling process before the xdist workers start, removed
at the end) and every process of the run uses it: the workers and the commands tests start
load the programs another test already compiled instead of compiling them again. Nothing
depends on what a previous run left. An ``LVENV_JIT_CACHE`` set by the caller (``off``
included) is kept. The tests of the cache itself give their processes folders of their own.
"""

import os
import shutil
import tempfile

import lvenv  # noqa: F401
from lvenv import jitcache

_RUN_FOLDER = "_lvenv_jit_cache"


def pytest_configure(config):
    controller = not hasattr(config, "workerinput")
    if controller and "LVENV_JIT_CACHE" not in os.environ:
        folder = tempfile.mkdtemp(prefix="lvenv-test-jax-")
        os.environ["LVENV_JIT_CACHE"] = folder
        setattr(config, _RUN_FOLDER, folder)
    jitcache.enable()


def pytest_unconfigure(config):
    folder = getattr(config, _RUN_FOLDER, None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        del os.environ["LVENV_JIT_CACHE"]
